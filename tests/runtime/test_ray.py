"""The Ray engine on a local two-node cluster (front-end node + back-end node, loopback)."""

from __future__ import annotations

import json
import os
import threading
import time
from pathlib import Path

import pytest

from edgerecon.io.dataset import open_dataset
from edgerecon.runtime import FrameRange, RuntimeConfig, SessionOptions, run_online
from edgerecon.runtime.engine import learn_scene_model
from edgerecon.runtime.frontend import FixedController
from edgerecon.runtime.ray_engine import (
    RayEngine,
    connect,
    keep_on_loopback,
    normal_priority,
    use_cluster_token,
)
from edgerecon.types import EdgereconError

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
    # Everything on, background rebuilds included: the recovery paths must hold with them.
    kw.setdefault("background_scale", 0.5)
    return RuntimeConfig(deadline_s=20.0, golden_timeout_s=30.0, **kw)


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


def test_each_role_runs_on_the_node_with_its_resource(cluster, tiny, capfd):
    # Asked of the actors themselves (their runtime context), so it runs on any Ray version
    # (the state API the old check needed is not in the installed Ray's ray.util namespace,
    # and the check silently did nothing).
    ds, scene = tiny
    engine = RayEngine(
        ds, _config(), FixedController(0.8, (0, 1, 2, 3, 4)), scene, address=cluster.address
    )
    try:
        placed = engine.node_ids()
    finally:
        engine.close()
    nodes = {n["NodeID"]: n["Resources"] for n in ray.nodes() if n["Alive"]}
    assert placed["frontend"] != placed["backend"]
    assert "frontend" in nodes[placed["frontend"]] and "backend" not in nodes[placed["frontend"]]
    assert "backend" in nodes[placed["backend"]] and "frontend" not in nodes[placed["backend"]]
    # The restartable back-end actor's constructor holds no object-store reference (an actor
    # handle counts): Ray cannot restart such an actor reliably and logs an error for it.
    assert "constructor arguments in the object store" not in capfd.readouterr().err


def test_a_deadline_share_is_timed_on_the_frontends_node(cluster, tiny, tmp_path):
    # run --engine ray --address ... --deadline 40%: the original pipeline runs where the
    # front-end's tasks will, not on the device that started the command.
    ds, scene = tiny
    config = RuntimeConfig(deadline_share=2.0, golden_timeout_s=30.0, background_scale=0.5)
    summary, metrics = run_online(
        ds,
        config,
        SessionOptions(frames=FrameRange(start=0, stop=2)),
        tmp_path / "run",
        engine="ray",
        address=cluster.address,
        scene=scene,
    )
    nodes = {n["NodeID"]: n["Resources"] for n in ray.nodes() if n["Alive"]}
    assert summary.original_node in nodes and "frontend" in nodes[summary.original_node]
    assert summary.original_s > 0 and summary.deadline_s == pytest.approx(
        2.0 * summary.original_s, abs=1e-3
    )
    assert [m.status for m in metrics] == ["ok", "ok"]
    # It is the run's state: a resumed run keeps the time and where it was taken.
    saved = json.loads((tmp_path / "run" / "state.json").read_text())["original"]
    assert saved["node"] == summary.original_node
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["original_node"] == (
        summary.original_node
    )


def _in_thread(fn):
    """``fn()`` on a thread of its own (niceness is per thread on Linux): its result."""
    out = {}
    th = threading.Thread(target=lambda: out.setdefault("v", fn()))
    th.start()
    th.join()
    return out["v"]


def _niced(nice):
    os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)


def _may_lower_niceness() -> bool:
    def probe():
        _niced(1)
        try:
            _niced(0)
        except PermissionError:
            return False
        return True

    return _in_thread(probe)


linux_only = pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="Linux threads")


@linux_only
def test_normal_priority_gives_every_thread_niceness_0():
    if not _may_lower_niceness():
        pytest.skip("this user may not lower niceness")
    release = threading.Event()
    ready = threading.Event()
    tid = {}

    def other():  # another thread of the process, at Ray's niceness
        tid["v"] = threading.get_native_id()
        _niced(15)
        ready.set()
        release.wait(30)

    th = threading.Thread(target=other)
    th.start()
    ready.wait(30)
    try:
        assert os.getpriority(os.PRIO_PROCESS, tid["v"]) == 15
        assert _in_thread(lambda: (_niced(15), normal_priority())[1]) == 0
        assert os.getpriority(os.PRIO_PROCESS, tid["v"]) == 0
    finally:
        release.set()
        th.join()


@linux_only
def test_normal_priority_lowers_to_its_target_and_never_raises():
    if not _may_lower_niceness():
        pytest.skip("this user may not lower niceness")
    # The driver run with `nice -n 5`: the front-end goes to 5, not to 0 ...
    assert _in_thread(lambda: (_niced(15), normal_priority(5), os.nice(0))[2]) == 5
    # ... and a thread already below the target stays there.
    assert _in_thread(lambda: (_niced(3), normal_priority(5), os.nice(0))[2]) == 3


@linux_only
def test_normal_priority_reports_what_it_could_not_lower(monkeypatch):
    def refuse(which, who, prio):
        raise PermissionError(1, "Operation not permitted")

    def run():
        _niced(7)
        monkeypatch.setattr(os, "setpriority", refuse)
        try:
            return normal_priority()
        finally:
            monkeypatch.undo()

    assert _in_thread(run) >= 7


def test_the_frontend_runs_at_normal_priority(cluster, tiny):
    # Ray starts its workers at niceness 15, the front-end actor included: the critical path
    # below every process at the default priority (the driver, Ray's daemons) on its node.
    @ray.remote(num_cpus=0)
    def worker_niceness():
        return os.nice(0)

    assert ray.get(worker_niceness.remote()) == 15, "the cluster's workers run at niceness 15"
    if not _may_lower_niceness():
        pytest.skip("this user may not lower niceness")
    ds, scene = tiny
    engine = RayEngine(
        ds, _config(), FixedController(0.8, (0, 1, 2, 3, 4)), scene, address=cluster.address
    )
    try:
        assert engine.status()["frontend_niceness"] == 0
    finally:
        engine.close()


def test_a_driver_uses_the_ray_token_it_finds(tmp_path):
    home = tmp_path / "home"
    env: dict[str, str] = {}
    assert not use_cluster_token(env, home) and env == {}  # no token: nothing to send
    (home / ".ray").mkdir(parents=True)
    (home / ".ray" / "auth_token").write_text("secret")
    assert use_cluster_token(env, home) and env == {"RAY_AUTH_MODE": "token"}
    env = {"RAY_AUTH_MODE": "disabled"}  # the user's choice stands
    assert not use_cluster_token(env, home) and env == {"RAY_AUTH_MODE": "disabled"}
    env = {"RAY_AUTH_TOKEN": "secret"}
    assert use_cluster_token(env, tmp_path) and env["RAY_AUTH_MODE"] == "token"
    env = {"RAY_AUTH_TOKEN_PATH": str(tmp_path / "missing")}
    assert not use_cluster_token(env, home)


def test_joining_a_cluster_started_by_ray_start(tmp_path):
    # Ray 2.59+ starts `ray start --head` clusters with token authentication, and a driver
    # joining by address defaults to none (Ray 2.60: refused, "Failed to connect"): the
    # README's two-device commands must work as written.
    import shutil
    import signal
    import socket
    import subprocess
    import sys

    ray_cli = shutil.which("ray") or str(Path(sys.executable).with_name("ray"))
    if not Path(ray_cli).exists():
        pytest.skip("no ray command")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_AUTH")}
    env["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"  # stay on loopback (keep_on_loopback)
    env["RAY_worker_niceness"] = "0"
    head = subprocess.Popen(
        [ray_cli, "start", "--head", "--block", "--node-ip-address=127.0.0.1", f"--port={port}",
         "--include-dashboard=false", "--resources", '{"frontend": 1, "backend": 1}'],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                time.sleep(0.5)
        code = (
            "from edgerecon.runtime.ray_engine import connect\n"
            f"connect('127.0.0.1:{port}')\n"
            "import ray\n"
            "print(ray.cluster_resources().get('frontend'))\n"
            "ray.shutdown()\n"
        )
        out = subprocess.run(
            [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120
        )
        assert out.returncode == 0, out.stderr[-2000:]
        assert out.stdout.strip().splitlines()[-1] == "1.0"
    finally:
        head.send_signal(signal.SIGTERM)
        head.wait(60)


def test_no_cluster_at_the_address_is_a_clear_error():
    import socket

    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(EdgereconError, match=f"no Ray cluster at --address 127.0.0.1:{port}"):
        connect(f"127.0.0.1:{port}")


def test_killing_the_backend_process_midrun(cluster, tiny, tmp_path):
    ds, scene = tiny
    config = _config(backend_retry_s=0.5)
    opts = SessionOptions(frames=FrameRange(start=0, stop=5), faults=((2, "kill", 0.0),))
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
    # The masks are the front-end's: the tasks stay whole while the back-end is gone.
    assert summary.degraded == 0
    assert all(m.num_fg_points > 0 and m.online_fscore is not None for m in metrics)
    assert len(list((tmp_path / "tasks").iterdir())) == 5


def test_a_killed_backend_actor_is_restarted_and_serves_again(cluster, tiny):
    # Not timed against the tasks of a run (how many tasks fit in the actor's restart depends
    # on the machine): wait for the restarted actor, then a task must use it.
    ds, scene = tiny
    engine = RayEngine(
        ds,
        _config(backend_retry_s=0.5),
        FixedController(0.8, (0, 1, 2, 3, 4)),
        scene,
        address=cluster.address,
    )
    try:
        engine.inject_backend_fault("kill")
        gone_by = time.monotonic() + 10
        while engine.status()["backend"] is not None and time.monotonic() < gone_by:
            time.sleep(0.2)
        back_by = time.monotonic() + 120
        while engine.status()["backend"] is None and time.monotonic() < back_by:
            time.sleep(0.5)
        assert engine.status()["backend"] is not None, "Ray restarted the back-end's actor"
        with ds.open_frames() as source:
            frames = source.read(0)
        out = engine.run_task(frames, engine.plan(0), 0, {})
        assert out.metrics.status == "ok"
        assert out.metrics.submitted, "the restarted actor serves again"
    finally:
        engine.close()
