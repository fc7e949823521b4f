"""The Ray engine on a local two-node cluster (front-end node + back-end node, loopback)."""

from __future__ import annotations

import pytest

from edgerecon.io.dataset import open_dataset
from edgerecon.runtime import FrameRange, RuntimeConfig, SessionOptions, run_online
from edgerecon.runtime.engine import learn_scene_model
from edgerecon.runtime.ray_engine import keep_on_loopback

keep_on_loopback()  # before Ray is imported: the cluster below listens on 127.0.0.1 only
ray = pytest.importorskip("ray")
cluster_utils = pytest.importorskip("ray.cluster_utils")


@pytest.fixture(scope="module")
def cluster():
    c = cluster_utils.Cluster(
        initialize_head=True,
        head_node_args={
            "num_cpus": 1,
            "resources": {"frontend": 1},
            "node_ip_address": "127.0.0.1",
            "include_dashboard": False,
        },
    )
    c.add_node(num_cpus=1, resources={"backend": 1}, node_ip_address="127.0.0.1")
    c.wait_for_nodes()
    ray.init(address=c.address)
    yield c
    ray.shutdown()
    c.shutdown()


@pytest.fixture(scope="module")
def tiny(tiny_dataset):
    ds = open_dataset(tiny_dataset)
    return ds, learn_scene_model(ds)


def _config(**kw):
    return RuntimeConfig(
        deadline_s=20.0, masks_timeout_s=15.0, golden_timeout_s=30.0, background_updates=False, **kw
    )


def test_roles_run_on_their_nodes_and_match_embedded(cluster, tiny, tmp_path):
    ds, scene = tiny
    opts = SessionOptions(frames=FrameRange(start=0, stop=3))
    fixed = (0.8, None)
    _, on_ray = run_online(
        ds,
        _config(),
        opts,
        tmp_path / "ray",
        engine="ray",
        address=cluster.address,
        fixed=fixed,
        scene=scene,
    )
    _, embedded = run_online(ds, _config(), opts, tmp_path / "emb", fixed=fixed, scene=scene)
    assert [m.status for m in on_ray] == ["ok"] * 3
    assert not any(m.degraded for m in on_ray)
    keys = (
        "time_index",
        "scale",
        "camera_ids",
        "num_sparse",
        "num_sparse_fg",
        "num_fg_points",
        "num_objects",
        "online_fscore",
    )
    for a, b in zip(on_ray, embedded, strict=True):
        assert {k: getattr(a, k) for k in keys} == {k: getattr(b, k) for k in keys}
    # Each actor sits on the node that offers its role's resource.
    nodes = {n["NodeID"]: n["Resources"] for n in ray.nodes() if n["Alive"]}
    actors = (
        ray.util.state.list_actors(filters=[("state", "=", "ALIVE")])
        if hasattr(ray.util, "state")
        else []
    )
    for actor in actors:
        res = nodes[actor.node_id]
        if "Frontend" in actor.class_name:
            assert "frontend" in res
        if "Backend" in actor.class_name:
            assert "backend" in res


def test_killing_the_backend_process_midrun(cluster, tiny, tmp_path):
    ds, scene = tiny
    config = _config(backend_retry_s=0.5)
    opts = SessionOptions(frames=FrameRange(start=0, stop=5), fault=(2, "kill", 0.0))
    summary, metrics = run_online(
        ds,
        config,
        opts,
        tmp_path,
        engine="ray",
        address=cluster.address,
        fixed=(0.8, None),
        scene=scene,
    )
    assert [m.status for m in metrics] == ["ok"] * 5
    assert not metrics[0].degraded and not metrics[1].degraded
    assert metrics[2].degraded
    assert summary.degraded >= 1
    assert len(list((tmp_path / "tasks").iterdir())) == 5
