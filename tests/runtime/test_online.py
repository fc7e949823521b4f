"""The online system on the embedded engine: outputs, faults, resume."""

from __future__ import annotations

import json

import numpy as np
import pytest

from edgerecon.dense import DenseConfig
from edgerecon.io.dataset import open_dataset
from edgerecon.runtime import FrameRange, SessionOptions, run_online
from edgerecon.viewer.rundir import RunFolder
from tests.runtime.conftest import runtime_config


def _lines(path):
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def test_embedded_run_outputs_and_summary(tiny, tmp_path):
    ds, scene = tiny
    opts = SessionOptions(frames=FrameRange(start=0, stop=4), ground_truth_threshold=0.08)
    summary, metrics = run_online(ds, runtime_config(), opts, tmp_path, scene=scene)
    assert [m.time_index for m in metrics] == [0, 1, 2, 3]
    assert all(m.status == "ok" and not m.degraded for m in metrics)
    assert metrics[0].phase == "golden" and metrics[0].scale == 1.0
    assert metrics[0].num_cameras == len(ds.rig)
    # The online estimate (the dense foreground against every camera's masks) is informative
    # on every task.
    assert all(m.online_fscore is not None and 0.2 < m.online_fscore <= 1.0 for m in metrics)
    assert all(m.offline_fscore is not None and m.offline_fscore > 0.1 for m in metrics)
    assert all(m.num_fg_points > 0 and m.critical_path_s > 0 for m in metrics)
    assert all(m.submitted for m in metrics)
    # The golden task's SfM (pi(N')) after its cloud, not on its critical path.
    assert {"scene", "sfm_mapping", "split", "merge", "online_quality"} <= set(metrics[0].stages)
    assert "sfm" not in metrics[0].stages
    lines = _lines(tmp_path / "metrics.jsonl")
    assert [x["time_index"] for x in lines] == [0, 1, 2, 3]
    run = RunFolder(tmp_path)
    for m in metrics:
        merged = run.cloud(m.time_index)
        assert merged is not None and len(merged) == m.num_merged_points
        assert (merged.labels > 0).sum() == m.num_fg_points
        np.testing.assert_array_equal(merged.attributes["bg_version"], m.bg_version)
    # Each background version the tasks merged with is stored once, the newest also as
    # background.ply (for --resume); a task stores its foreground, not the background.
    versions = {(m.bg_epoch, m.bg_version) for m in metrics if m.bg_version}
    stored = {p.name for p in (tmp_path / "backgrounds").glob("*.ply")}
    assert stored == {f"v{e}.{c}.ply" for e, c in versions}
    if versions:
        newest = max(versions)
        assert (tmp_path / "background.ply").read_bytes() == (
            tmp_path / "backgrounds" / f"v{newest[0]}.{newest[1]}.ply"
        ).read_bytes()
    assert not list(tmp_path.glob("tasks/*/merged.ply"))
    saved = json.loads((tmp_path / "summary.json").read_text())
    assert saved["tasks"] == 4 and saved["failed"] == 0
    assert summary.avg_time_s == pytest.approx(sum(m.critical_path_s for m in metrics) / 4)
    # Every output is readable by others (0644), like metrics.jsonl always was.
    for path in [tmp_path / "summary.json", tmp_path / "state.json", *tmp_path.rglob("*.ply")]:
        assert path.stat().st_mode & 0o777 == 0o644, path


def test_spare_time_makes_the_foreground_finer_than_the_golden_task(tiny, tmp_path):
    """A deadline far above the golden task on a rig whose golden foreground densifies at
    half resolution (here forced with ``min_resolution_px=0``): after the golden task r
    climbs above 1 with every camera, the foreground's depth maps get finer (more points),
    and with ``fine_foreground`` off r stays at 1."""
    ds, scene = tiny
    dense = DenseConfig(min_resolution_px=0)
    opts = SessionOptions(frames=FrameRange(start=0, stop=6))
    _, metrics = run_online(ds, runtime_config(dense=dense), opts, tmp_path / "fine", scene=scene)
    assert all(m.status == "ok" for m in metrics)
    assert metrics[0].phase == "golden" and metrics[0].scale == 1.0
    fine = [m for m in metrics if m.scale > 1.0]
    assert fine and all(m.num_cameras == len(ds.rig) and m.scale <= 2.0 for m in fine)
    assert max(m.num_fg_points for m in fine) > 1.5 * metrics[0].num_fg_points
    _, plain = run_online(
        ds,
        runtime_config(dense=dense, fine_foreground=False),
        SessionOptions(frames=FrameRange(start=0, stop=4)),
        tmp_path / "plain",
        scene=scene,
    )
    assert [m.scale for m in plain] == [1.0] * 4


def test_sfm_of_the_foreground_or_of_the_whole_scene(tiny, tmp_path):
    ds, scene = tiny
    opts = SessionOptions(frames=FrameRange(start=2, stop=4))
    runs = {}
    for scope in ("foreground", "scene", "hull"):
        config = runtime_config(sparse_scope=scope, background_updates=False)
        runs[scope] = run_online(ds, config, opts, tmp_path / scope, scene=scene)[1]
    fg, whole = runs["foreground"][0], runs["scene"][0]
    # The paper's order reconstructs the whole scene and splits it; ours only the foreground
    # (nearly all of its points are foreground), with the same foreground cloud after it.
    assert whole.num_sparse > 2 * fg.num_sparse
    assert fg.num_sparse_fg >= 0.5 * fg.num_sparse
    assert fg.num_fg_points > 0 and whole.num_fg_points > 0
    # "hull" (the default): no SfM on any task's critical path (the hull bounds the depth
    # search); the golden task's (pi(N') from its visibility) runs after its cloud; the
    # objects are counted all the same.
    golden, task = runs["hull"]
    assert golden.phase == "golden" and golden.num_sparse > 0 and "sfm" not in golden.stages
    assert golden.stages["sfm_mapping"] > 0
    assert task.phase != "golden" and task.num_sparse == 0 and "sfm" not in task.stages
    assert task.num_fg_points > 0 and task.num_objects >= 1
    assert runtime_config().sparse_scope == "hull"
    with pytest.raises(ValueError, match="sparse_scope"):
        runtime_config(sparse_scope="everything")


def test_backend_crash_midrun_recovers_and_backgrounds_advance(tiny, tmp_path):
    ds, scene = tiny
    config = runtime_config(backend_retry_s=0.2, background_scale=0.5)  # background updates on
    opts = SessionOptions(frames=FrameRange(start=0, stop=6), faults=((2, "crash", 0.0),))
    summary, metrics = run_online(ds, config, opts, tmp_path, scene=scene)
    assert [m.status for m in metrics] == ["ok"] * 6  # nothing lost
    # The masks are the front-end's own: a lost back-end degrades nothing of the task.
    assert not any(m.degraded for m in metrics)
    assert all(m.online_fscore is not None and m.num_fg_points > 0 for m in metrics)
    assert summary.backend_restarts == 1
    assert len(list((tmp_path / "tasks").iterdir())) == 6
    versions = [m.background_version for m in metrics]
    assert versions == sorted(versions), "the background version never goes back"
    assert metrics[-1].submitted, "the restarted back-end serves again"


def test_backend_crash_with_the_golden_estimate_degrades_and_recovers(tiny, tmp_path):
    ds, scene = tiny
    config = runtime_config(backend_retry_s=0.2, online_quality="golden")
    opts = SessionOptions(frames=FrameRange(start=0, stop=6), faults=((2, "crash", 0.0),))
    summary, metrics = run_online(ds, config, opts, tmp_path, scene=scene)
    assert [m.status for m in metrics] == ["ok"] * 6
    assert not any(m.degraded for m in metrics[:2])
    assert metrics[2].degraded and "back-end" in metrics[2].degraded_reason
    assert metrics[2].online_fscore is None and metrics[2].num_fg_points > 0
    assert not metrics[-1].degraded, "the restarted back-end serves again"
    assert summary.degraded == sum(m.degraded for m in metrics) >= 1
    assert summary.backend_restarts == 1


def test_backend_stall_costs_the_critical_path_nothing(tiny, tmp_path):
    ds, scene = tiny
    runs = {}
    for quality in ("silhouette", "golden"):
        config = runtime_config(golden_timeout_s=2.0, backend_retry_s=0.2, online_quality=quality)
        opts = SessionOptions(frames=FrameRange(start=0, stop=5), faults=((2, "stall", 8.0),))
        runs[quality] = run_online(ds, config, opts, tmp_path / quality, scene=scene)[1]
    silhouette, golden = runs["silhouette"], runs["golden"]
    assert all(m.status == "ok" and not m.degraded for m in silhouette)
    assert all("wait_golden" not in m.stages for m in silhouette)
    # The paper's estimate waits (after the critical path) for a reference that never comes.
    assert golden[2].degraded and golden[2].stages["wait_golden"] == pytest.approx(2.0, abs=0.6)
    assert golden[2].critical_path_s < sum(golden[2].stages.values())
    assert all(m.status == "ok" for m in golden)


def test_bad_frame_is_recorded_and_skipped(tiny_dataset, tmp_path_factory, tmp_path):
    import shutil

    src = tmp_path_factory.mktemp("broken") / "scene"
    shutil.copytree(tiny_dataset, src)
    # Corrupt one camera's frame 2 and delete another's frame 2: three cameras remain.
    (src / "frames" / "cam0" / "000002.png").write_bytes(b"not a png")
    (src / "frames" / "cam1" / "000002.png").unlink()
    ds = open_dataset(src)
    _, metrics = run_online(
        ds,
        runtime_config(),  # everything on: bad frames must not upset background rebuilds
        SessionOptions(frames=FrameRange(start=1, stop=4)),
        tmp_path / "a",
    )
    assert [m.status for m in metrics] == ["ok", "ok", "ok"]
    assert metrics[1].num_cameras == 3  # cam0 and cam1 left out of time 2
    (src / "frames" / "cam2" / "000003.png").unlink()
    (src / "frames" / "cam3" / "000003.png").unlink()
    (src / "frames" / "cam4" / "000003.png").write_bytes(b"")
    _, metrics = run_online(
        ds,
        runtime_config(),  # everything on: bad frames must not upset background rebuilds
        SessionOptions(frames=FrameRange(start=2, stop=5)),
        tmp_path / "b",
    )
    assert [m.status for m in metrics] == ["ok", "failed", "ok"]
    assert "usable camera" in metrics[1].error


def test_tasks_without_foreground_are_not_observations(tiny_dataset, tmp_path_factory, tmp_path):
    # The first two frames show the empty room (as in the first second of a stream without
    # an empty-scene clip, or a room everyone left): those tasks measure no MVS, so the
    # controller plans the golden task again until one has foreground, and neither the
    # adjustment nor pi(N') learns from them.
    import shutil

    src = tmp_path_factory.mktemp("empty_start") / "scene"
    shutil.copytree(tiny_dataset, src)
    for cam in sorted(p.name for p in (src / "frames").iterdir()):
        for t in (0, 1):
            shutil.copy(
                src / "background" / cam / "000000.png", src / "frames" / cam / f"{t:06d}.png"
            )
    _, metrics = run_online(
        open_dataset(src),
        runtime_config(),  # everything on, background rebuilds included
        SessionOptions(frames=FrameRange(start=0, stop=4)),
        tmp_path / "run",
    )
    assert [m.status for m in metrics] == ["ok"] * 4
    assert [m.num_fg_points for m in metrics[:2]] == [0, 0]
    assert metrics[2].num_fg_points > 0
    assert [m.phase for m in metrics] == ["golden", "golden", "golden", "adjust"]


def test_background_updates_run_between_tasks_with_the_same_masks(tiny_dataset, tmp_path):
    # Updates every frame: tasks every third frame leave two updates between tasks, which
    # the session applies after a task's cloud instead of on the next task's critical path.
    from edgerecon.runtime.engine import learn_scene_model
    from edgerecon.runtime.frontend import FixedController, FrontEnd
    from edgerecon.scene import ForegroundConfig
    from edgerecon.scene.stream import dataset_scene_at

    ds = open_dataset(tiny_dataset)
    fg_config = ForegroundConfig(update_interval_s=1.0 / ds.fps)
    scene = learn_scene_model(ds, fg_config)
    assert scene.step == 1
    config = runtime_config(foreground=fg_config)
    opts = SessionOptions(frames=FrameRange(start=0, stop=8, step=3))
    _, metrics = run_online(ds, config, opts, tmp_path, scene=scene)
    assert [m.time_index for m in metrics] == [0, 3, 6]
    assert all(m.status == "ok" for m in metrics)
    # Updates 1-2 and 4-5 between the tasks, none left on a task's path; none after the last.
    assert all("scene_update" not in m.stages for m in metrics)
    assert all(m.stages.get("scene_update_ahead", 0) > 0 for m in metrics[:2])
    assert "scene_update_ahead" not in metrics[2].stages
    # The models the next task segments with are the stream's at its time index.
    front = FrontEnd(
        ds.rig, config, FixedController(1.0, (0, 1, 2)), scene.tracker(ds.rig, fg_config)
    )
    with ds.open_frames() as source:
        front.learn_updates([source.read(s) for s in front.pending_updates(5)])
        frames = source.read(5)
    assert front.pending_updates(5) == []
    ours = front.scene.segment(frames).masks  # type: ignore[union-attr]
    theirs = dataset_scene_at(ds, 5, fg_config).segment(frames).masks
    for a, b in zip(ours, theirs, strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_background_update_that_raises_is_skipped_and_the_run_goes_on(
    tiny_dataset, tmp_path, monkeypatch, caplog
):
    # Updates every frame, tasks every third: the update of frame 4 (between the tasks at
    # 3 and 6) and that of frame 6 (the task's own frame) raise in the models' update.
    from edgerecon.runtime.engine import learn_scene_model
    from edgerecon.scene import ForegroundConfig
    from edgerecon.scene.foreground import RigForeground

    ds = open_dataset(tiny_dataset)
    fg_config = ForegroundConfig(update_interval_s=1.0 / ds.fps)
    scene = learn_scene_model(ds, fg_config)
    update = RigForeground.update

    def failing(self, frames, *args, **kw):  # type: ignore[no-untyped-def]
        if frames.time_index in (4, 6):
            raise RuntimeError(f"injected failure at {frames.time_index}")
        return update(self, frames, *args, **kw)

    monkeypatch.setattr(RigForeground, "update", failing)
    opts = SessionOptions(frames=FrameRange(start=0, stop=8, step=3))
    _, metrics = run_online(ds, runtime_config(foreground=fg_config), opts, tmp_path, scene=scene)
    # Every task ran, none with an update left on its path.
    assert [(m.time_index, m.status) for m in metrics] == [(0, "ok"), (3, "ok"), (6, "ok")]
    assert all("scene_update" not in m.stages for m in metrics)
    skipped = [r.getMessage() for r in caplog.records if "skipped, the models miss" in r.message]
    assert any("time 4" in m for m in skipped)


def test_the_original_pipeline_is_run_twice_unless_it_is_long(tiny, monkeypatch):
    """``measure_original``: the faster of two runs; a run past 20 s is not repeated."""
    import edgerecon.runtime.online as online

    real = online.reconstruct
    # The first run padded far beyond the real runs' spread on a loaded machine (0.5 s was
    # not: CI once found the second real run 0.4 s slower).
    extra = iter([8.0, 0.1, 25.0])
    calls = []

    def timed(*args, **kwargs):
        result = real(*args, **kwargs)
        result.timings.add("padding", next(extra))
        calls.append(result.timings.total)
        return result

    monkeypatch.setattr(online, "reconstruct", timed)
    ds = tiny[0]
    first = online.measure_original(ds, runtime_config(), [2])
    assert len(calls) == 2 and first.time_index == 2
    assert first.seconds == pytest.approx(min(calls), abs=1e-4)
    assert first.stages["padding"] == pytest.approx(0.1)
    long = online.measure_original(ds, runtime_config(), [3])
    assert len(calls) == 3 and long.seconds > 25.0
    assert online.original_times(ds, list(range(0, 8)), 0) == [0, 2, 4, 5, 7]
