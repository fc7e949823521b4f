"""Run state with one owner: background versions across back-end restarts and resumes, the
saved background, the deadline and dataset on resume, pi(N') refreshes, late golden
references, and the output folder (lock, overwrite, torn lines)."""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import pytest

from edgerecon.cli._config import online_configs
from edgerecon.dense import DenseConfig
from edgerecon.io.ply import read_ply
from edgerecon.optimize.controller import BisectionController, ControllerConfig
from edgerecon.runtime import FrameRange, SessionOptions, run_online
from edgerecon.runtime.backend import BackEnd
from edgerecon.runtime.engine import EmbeddedEngine
from edgerecon.runtime.frontend import FixedController, FrontEnd
from edgerecon.runtime.messages import BackgroundUpdate, BgVersion
from edgerecon.runtime.online import make_controller
from edgerecon.runtime.state import (
    VIEWS_FILE,
    DatasetIdentity,
    OutputFolder,
    RunState,
    background_comment,
    comment_background,
)
from edgerecon.types import EdgereconError, PointCloud
from edgerecon.viewer.rundir import RunFolder
from tests.runtime.conftest import run_frames, runtime_config, wait_until


def _cloud(n):
    rng = np.random.default_rng(n)
    return PointCloud(points3D=rng.normal(size=(n, 3)), colors=np.zeros((n, 3), np.uint8))


def test_background_versions_order_by_epoch_then_counter():
    assert BgVersion(2, 1) > BgVersion(1, 9) > BgVersion(1, 2) > BgVersion()
    assert not BgVersion() and BgVersion(3, 1)
    assert BgVersion.from_list([2, 5]) == BgVersion(2, 5) and str(BgVersion(2, 5)) == "v2.5"


def _rig():
    from tests.conftest import ring_rig

    return ring_rig(4)


def test_frontend_takes_a_restarted_backends_backgrounds():
    # Before: every back-end counted from 1, so after a restart the front-end (holding v5)
    # dropped the new back-end's v1..v5 silently.
    fe = FrontEnd(_rig(), runtime_config(), FixedController(1.0, (0, 1, 2, 3)))
    first = fe.register_backend()
    assert first.epoch == 1 and first.first
    for k in range(1, 6):
        fe.push_background(BackgroundUpdate(version=BgVersion(1, k), cloud=_cloud(k), seconds=0))
    second = fe.register_backend()
    assert second.epoch == 2 and not second.first
    fe.push_background(BackgroundUpdate(version=BgVersion(2, 1), cloud=_cloud(50), seconds=0))
    assert fe.bg_version == BgVersion(2, 1) and len(fe.background()[0]) == 50
    # A late push from the dead back-end is older: ignored.
    fe.push_background(BackgroundUpdate(version=BgVersion(1, 6), cloud=_cloud(7), seconds=0))
    assert fe.bg_version == BgVersion(2, 1)
    state = fe.state()
    assert state.backend_epoch == 2 and state.backgrounds_received == 6
    # The state names the background a task published (saved as background.ply), not the
    # newest held: none before a task merged one.
    assert state.bg_version == BgVersion()
    assert fe._background_to_publish(*fe.background()) is not None  # a task merged v2.1
    assert fe._background_to_publish(*fe.background()) is None  # published once
    state = fe.state()
    assert state.bg_version == BgVersion(2, 1)
    # Restored (resume): the next back-end continues the epochs, the background is kept.
    again = FrontEnd(
        _rig(),
        runtime_config(),
        FixedController(1.0, (0, 1, 2, 3)),
        restored=state,
        background=_cloud(50),
    )
    assert again.bg_version == BgVersion(2, 1) and again.register_backend().epoch == 3


def test_embedded_backend_restart_keeps_backgrounds_advancing(tiny):
    ds, scene = tiny
    engine = EmbeddedEngine(
        ds, runtime_config(backend_retry_s=0.1), FixedController(0.6, (0, 1, 2, 3, 4)), scene
    )
    try:
        fe = engine.frontend
        assert wait_until(lambda: fe.bg_version.counter >= 1), "first background (from the clip)"
        assert fe.bg_version.epoch == 1
        engine.inject_backend_fault("crash")
        engine.link.mark_lost("test")
        engine.link._next_check = 0.0
        assert not engine.link.usable()  # found dead: restarted, not usable yet
        assert engine.backend_restarts == 1 and engine.backend.epoch == 2
        with ds.open_frames() as src:
            frames = src.read(3)
        engine.link._next_check = 0.0
        out = engine.run_task(frames, engine.plan(3), 0, {})
        assert out.metrics.status == "ok" and out.metrics.submitted
        assert wait_until(lambda: fe.bg_version.epoch == 2), (
            "the new back-end's background is taken"
        )
    finally:
        engine.close()


def test_embedded_backend_stuck_in_a_loop_is_restarted_and_its_thread_stopped(tiny, monkeypatch):
    # A back-end stuck past the watchdog is replaced; a task thread that loops in Python
    # code for ever would have kept a core of this process busy for the rest of the run.
    ds, scene = tiny
    loop: dict[str, float] = {}

    def spin(self, work):
        try:
            while True:
                time.sleep(0.005)
        finally:
            loop["ended"] = time.monotonic()

    monkeypatch.setattr(BackEnd, "_serve", spin)
    engine = EmbeddedEngine(
        ds,
        runtime_config(backend_retry_s=0.1, task_timeout_s=2.0),
        FixedController(0.6, (0, 1, 2, 3, 4)),
        scene,
    )
    try:
        stuck = engine.backend
        with ds.open_frames() as src:
            frames = src.read(3)
        out = engine.run_task(frames, engine.plan(3), 0, {})
        assert out.metrics.status == "ok" and out.metrics.submitted
        assert wait_until(lambda: stuck.ping()["task_age_s"] > 2.5, timeout=30)
        engine.link._next_check = 0.0
        assert not engine.link.usable()  # found stuck: restarted
        assert engine.backend_restarts == 1 and engine.backend is not stuck
        assert wait_until(lambda: "ended" in loop and not stuck.task_thread.is_alive(), timeout=10)
        assert engine.status()["abandoned_threads"] == []
    finally:
        engine.close()


def test_resume_restores_state_background_and_equals_uninterrupted_run(tiny, tmp_path, monkeypatch):
    ds = tiny[0]
    config = runtime_config()
    fixed = (0.8, None)
    taken = []  # (front-end, version) of every push
    current = []  # the front-end of the run in progress (the last to register a back-end)
    real_push, real_register = FrontEnd.push_background, FrontEnd.register_backend

    def push(self, update):
        taken.append((self, update.version))
        return real_push(self, update)

    def register(self):
        current.append(self)
        return real_register(self)

    monkeypatch.setattr(FrontEnd, "push_background", push)
    monkeypatch.setattr(FrontEnd, "register_backend", register)

    # Frames arrive slowly after tasks 0 and 4: the back-end (of epoch 1, then of epoch 2
    # after the resume) has time to push a background.
    def slow(m):
        if m.task in (0, 4):
            epoch = 1 if m.task == 0 else 2
            pushed = lambda: any(fe is current[-1] and v.epoch == epoch for fe, v in taken)  # noqa: E731
            assert wait_until(pushed, timeout=180)

    whole = tmp_path / "whole"
    _, uninterrupted = run_frames(tiny, whole, 0, 7, config, fixed=fixed)
    taken.clear()  # the next run's pushes only
    part = tmp_path / "part"
    _, first = run_frames(tiny, part, 0, 3, config, fixed=fixed, on_task=slow)
    state = RunState.load(part)
    assert state.tasks_done == 3 and state.frontend.bg_version.epoch == 1
    # The saved background is the background itself, not a merged cloud with holes cut
    # where the last task's foreground was (a resumed run's clouds held ~7k of ~144k points).
    saved_bg = read_ply(part / "background.ply")
    last = RunFolder(part).cloud(first[-1].time_index)
    assert last is not None
    held = state.frontend.bg_version
    assert held.counter >= 1
    # The saved version is the one the last task merged with, which background.ply holds
    # (not a newer one that arrived after that task: the file would not match it).
    assert first[-1].background_version == held
    assert len(saved_bg) > (last.labels == 0).sum()
    # A crash left a torn last line: it is cut off and that task is done again.
    with open(part / "metrics.jsonl", "a") as f:
        f.write('{"task": 3, "time_index": 3, "sta')
    summary, resumed = run_online(
        ds,
        config,
        SessionOptions(frames=FrameRange(start=0, stop=7), resume=True),
        part,
        # As `run --resume`: the models (and their static scene) learned up to the first task
        # still to run, not replayed through that task's pending updates.
        fixed=fixed,
        on_task=slow,
    )
    lines = [json.loads(x) for x in (part / "metrics.jsonl").read_text().splitlines()]
    assert [x["task"] for x in lines] == list(range(7))
    assert [x["time_index"] for x in lines] == list(range(7))
    # The resumed run merged the saved background first, then the new back-end's (epoch 2).
    assert resumed[3].background_version == held
    assert max(m.background_version for m in resumed).epoch == 2
    assert summary.bg_version[0] == 2
    # Same foreground clouds as the uninterrupted run (the background models replayed the
    # frames the back-end had learned from before the interruption).
    for a, b in zip(resumed, uninterrupted, strict=True):
        assert a.status == b.status == "ok"
        assert (a.num_sparse, a.num_fg_points, a.num_sparse_fg) == (
            b.num_sparse,
            b.num_fg_points,
            b.num_sparse_fg,
        ), a.task
        fa = RunFolder(part).cloud(a.time_index)
        fb = RunFolder(whole).cloud(b.time_index)
        assert fa is not None and fb is not None
        np.testing.assert_array_equal(
            fa.points3D[fa.labels > 0], fb.points3D[fb.labels > 0], err_msg=str(a.task)
        )


def test_resume_applies_a_new_deadline_and_restarts_the_search():
    ctrl = BisectionController(ControllerConfig(deadline_s=2.0), {3: (0, 1, 2)}, 4)
    ctrl.next_config()
    ctrl.observe(1.0, 1.0)
    saved = ctrl.to_dict()
    ds = type("D", (), {"rig": _rig()})()
    same = make_controller(ds, runtime_config(deadline_s=2.0), saved_state=saved)
    assert isinstance(same, BisectionController) and same.events == []
    new = make_controller(ds, runtime_config(deadline_s=0.5), saved_state=saved)
    assert isinstance(new, BisectionController)
    assert new.config.deadline_s == 0.5 and new.events[-1]["reason"] == "deadline"
    # Cameras placed again (a resume with a recalibration): pi(N') came from the poses
    # before, so the search restarts with a golden task (which gives pi(N') again).
    again = make_controller(
        ds, runtime_config(deadline_s=2.0), saved_state=saved, recalibrated=True
    )
    assert isinstance(again, BisectionController)
    assert again.events[-1]["reason"] == "calibration"
    assert again.next_config().phase == "golden"


def _state(ds, frames=(0, 4, 1)):
    from edgerecon.runtime.frontend import FrontEndState

    return RunState(
        dataset=DatasetIdentity.of(ds),
        frames=frames,
        policy="all",
        deadline_s=2.0,
        tasks_done=2,
        frontend=FrontEndState(controller={"format": "edgerecon-fixed"}),
    )


def test_the_controller_goes_finer_than_golden_only_as_far_as_the_rig_allows(tiny):
    """``make_controller``: r_fine is the rig's limit (2 where the golden foreground
    densifies at level 1), a given one capped at it, none with ``fine_foreground`` off or on
    a rig densified at level 0; ``run``'s controller takes the runtime's adjust_target unless
    its [controller] table sets one."""
    ds = tiny[0]
    level1 = runtime_config(dense=DenseConfig(min_resolution_px=0))
    assert make_controller(ds, level1).config.r_fine == 2.0
    given = ControllerConfig(deadline_s=20.0, r_fine=5.0)
    assert make_controller(ds, level1, controller_config=given).config.r_fine == 2.0
    given = ControllerConfig(deadline_s=20.0, r_fine=1.5)
    assert make_controller(ds, level1, controller_config=given).config.r_fine == 1.5
    off = runtime_config(dense=DenseConfig(min_resolution_px=0), fine_foreground=False)
    assert make_controller(ds, off).config.r_fine is None
    assert make_controller(ds, runtime_config()).config.r_fine is None  # 320x240: level 0
    args = argparse.Namespace(deadline=2.0)
    runtime, controller = online_configs(args, {})
    assert controller.adjust_target == runtime.adjust_target == 0.95
    _, controller = online_configs(args, {"controller": {"adjust_target": 0.9}})
    assert controller.adjust_target == 0.9


def test_resume_refuses_another_dataset_or_frame_range(tiny, tiny_dataset, tmp_path):
    ds, _ = tiny
    _state(ds).save(tmp_path)
    ident = DatasetIdentity.of(ds)
    with OutputFolder(tmp_path).acquire() as folder:
        assert folder.prepare(resume=True, overwrite=False, identity=ident, frames=(0, 8, 1))
        other = DatasetIdentity(**{**ident.__dict__, "rig_fingerprint": "0" * 16})
        with pytest.raises(EdgereconError, match="different calibration"):
            folder.prepare(resume=True, overwrite=False, identity=other, frames=(0, 4, 1))
        with pytest.raises(EdgereconError, match="same start and step"):
            folder.prepare(resume=True, overwrite=False, identity=ident, frames=(1, 4, 1))
        with pytest.raises(EdgereconError, match="same start and step"):
            folder.prepare(resume=True, overwrite=False, identity=ident, frames=(0, 4, 2))
        with pytest.raises(EdgereconError, match="not empty"):
            folder.prepare(resume=False, overwrite=False, identity=ident, frames=(0, 4, 1))


def test_output_folder_lock_overwrite_and_torn_lines(tiny, tmp_path):
    ds, _ = tiny
    a = OutputFolder(tmp_path).acquire("edgerecon run A")
    with pytest.raises(EdgereconError, match=r"in use by another run \(pid \d+ .*run A"):
        OutputFolder(tmp_path).acquire()
    a.release()
    # A finished run's files, a stale task folder and a user's own file.
    (tmp_path / "tasks" / "000099").mkdir(parents=True)
    (tmp_path / "notes.txt").write_text("mine")
    _state(ds).save(tmp_path)
    lines = [json.dumps({"task": k, "time_index": k, "status": "ok"}) for k in range(3)]
    (tmp_path / "metrics.jsonl").write_text("\n".join(lines) + "\n" + '{"task": 3, "ti')
    with OutputFolder(tmp_path).acquire() as folder:
        # Two committed tasks: the third line (written before a crash, uncommitted) and the
        # torn fourth are cut off.
        records = folder.read_metrics(2)
        assert [m.task for m in records] == [0, 1]
        assert (tmp_path / "metrics.jsonl").read_text() == "\n".join(lines[:2]) + "\n"
        folder.prepare(
            resume=False, overwrite=True, identity=DatasetIdentity.of(ds), frames=(0, 4, 1)
        )
    assert sorted(p.name for p in tmp_path.iterdir()) == [".lock", "notes.txt"]


def test_unwritable_out_is_refused_before_any_work(tiny, tmp_path):
    ds, _ = tiny
    blocker = tmp_path / "file"
    blocker.write_text("x")
    t0 = time.perf_counter()
    with pytest.raises(EdgereconError, match="cannot write there"):
        run_online(
            ds,
            runtime_config(),
            SessionOptions(frames=FrameRange(start=0, stop=2)),
            blocker / "out",
        )
    assert time.perf_counter() - t0 < 2.0


def test_golden_task_refreshes_camera_mapping_and_late_golden_is_degraded(tiny):
    ds, scene = tiny
    ctrl = BisectionController(ControllerConfig(deadline_s=100.0), None, len(ds.rig))
    config = runtime_config(golden_timeout_s=0.3, online_quality="golden")
    fe = FrontEnd(ds.rig, config, ctrl, scene.tracker(ds.rig))
    with ds.open_frames() as src:
        framesets = [src.read(t) for t in range(3)]
    handed: list = []

    def run(task, frames):
        plan = fe.next_plan(frames.time_index)
        return plan, fe.run_task(frames, plan, handed.append, lambda t: time.sleep(t), task=task)

    plan, out = run(0, framesets[0])
    assert plan.phase == "golden" and fe.pi_source["task"] == 0
    # The back-end was handed the frames with the front-end's own masks, asked for a reference.
    assert handed[0].frames.time_index == 0 and handed[0].golden
    assert handed[0].foreground.masks[0] is not None and not handed[0].foreground.segmentations
    m = out.metrics
    # The golden reference came late: counted as degraded, and the wait is in the stages.
    assert m.degraded and "no golden reference" in m.degraded_reason
    assert m.stages["wait_golden"] == pytest.approx(0.3, abs=0.2)
    assert m.critical_path_s < sum(m.stages.values())  # the wait is after the critical path
    ctrl.restart("test", golden=True)  # a golden re-search recomputes pi(N') ...
    plan, out = run(1, framesets[1])
    assert plan.phase == "golden" and fe.pi_source == {
        "task": 1,
        "time_index": 1,
        "rows": fe.pi_source["rows"],
    }


def test_outputs_that_cannot_be_written_stop_the_run_cleanly(tiny, tmp_path, monkeypatch):
    import errno

    import edgerecon.runtime.state as state_module

    real = state_module.write_ply
    calls = {"n": 0}

    def full(path, cloud, **kw):
        calls["n"] += 1
        if calls["n"] == 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(path, cloud, **kw)

    monkeypatch.setattr(state_module, "write_ply", full)
    config = runtime_config()  # background rebuilds on: their files are written too
    with pytest.raises(EdgereconError, match=r"No space left.*after 1 committed tasks.*--resume"):
        run_frames(tiny, tmp_path, 0, 3, config, fixed=(0.6, None))
    assert RunState.load(tmp_path).tasks_done == 1
    monkeypatch.setattr(state_module, "write_ply", real)
    _, metrics = run_frames(tiny, tmp_path, 0, 3, config, fixed=(0.6, None), resume=True)
    assert [m.time_index for m in metrics] == [0, 1, 2]


def test_a_pushed_background_leaves_the_scene_stage_alone():
    """The masks depend on the stream alone: a background the back-end pushes (at whatever
    time) is merged into the output but never becomes the ghost check's static scene."""
    from edgerecon.scene.foreground import RigForeground
    from edgerecon.scene.stream import SceneTracker

    rig = _rig()
    blank = [[np.full((c.height, c.width, 3), 90, np.uint8)] for c in rig]
    scene = SceneTracker(foreground=RigForeground.learn(rig, blank), step=1, static_step=5)
    fe = FrontEnd(rig, runtime_config(), FixedController(1.0, (0, 1, 2, 3)), scene)
    g = np.linspace(-0.5, 0.5, 60)
    wall = np.stack(np.meshgrid(g, g, [0.0], indexing="ij"), -1).reshape(-1, 3)
    cloud = PointCloud(points3D=wall, colors=np.zeros((len(wall), 3), np.uint8))
    fe.push_background(BackgroundUpdate(version=BgVersion(1, 1), cloud=cloud, seconds=0))
    assert fe.background()[1] == BgVersion(1, 1)
    assert scene.foreground.static_depth is None and scene.static_from is None


def test_a_task_cloud_is_its_foreground_and_a_background_stored_once(tmp_path):
    """What a task merged is rebuilt from its foreground, the background points it overrode
    and its background version, stored once for all the tasks that merged with it; a run
    written before (one merged.ply per task) is read as it is."""
    from edgerecon.io.ply import write_ply
    from edgerecon.scene.merge import compose, foreground_part

    folder = OutputFolder(tmp_path)
    bg = _cloud(500)
    folder.write_background(bg, (2, 3), unit="m")
    assert (tmp_path / "background.ply").read_bytes() == (
        tmp_path / "backgrounds" / "v2.3.ply"
    ).read_bytes()
    fg = PointCloud(points3D=_cloud(40).points3D, labels=np.r_[np.ones(30), -np.ones(10)])
    dropped = np.array([0, 7, 499])
    for t in (5, 6):  # two tasks, one background file
        folder.write_task_cloud(t, foreground_part(fg, 3), dropped, (2, 3), unit="m")
    run = RunFolder(tmp_path)
    expected = compose(fg, bg, bg_version=3, dropped=dropped)
    for t in (5, 6):
        got = run.cloud(t)
        assert got is not None and len(got) == 40 + 500 - 3
        np.testing.assert_array_equal(got.points3D, expected.points3D.astype(np.float32))
        np.testing.assert_array_equal(got.labels, expected.labels)
        np.testing.assert_array_equal(got.attributes["bg_version"], 3)
    assert len(list((tmp_path / "backgrounds").iterdir())) == 1
    assert comment_background(["unit m", background_comment((2, 3))]) == (2, 3)
    assert comment_background(["background", "background vx.3", "unit m"]) is None
    # Before the first background (v0.0) a task's cloud is its foreground.
    folder.write_task_cloud(7, foreground_part(fg, 0), np.zeros(0, np.int64), (0, 0))
    assert len(run.cloud(7)) == 40
    # A missing background version: no cloud (a warning), never a wrong one.
    folder.write_task_cloud(8, foreground_part(fg, 4), dropped, (2, 4))
    assert run.cloud(8) is None
    # A resume saves the restored background under its version when it is missing.
    folder.ensure_background(read_ply(tmp_path / "background.ply"), (2, 4))
    assert run.cloud(8) is not None
    # The older layout.
    write_ply(tmp_path / "tasks" / "000009" / "merged.ply", expected)
    assert len(run.cloud(9)) == len(expected)
    assert run.cloud(10) is None


def test_the_golden_tasks_sfm_runs_after_its_cloud(tiny):
    """A golden-configuration task needs SfM only to build pi(N') (its cloud, like every
    other task's, takes its depth ranges from the hull, sparse_scope "hull"): the SfM runs
    after the task's cloud, off its critical path, and the controller sees the critical
    path; pi(N') comes from that SfM's visibility."""
    ds, scene = tiny
    seen: list[float] = []

    class Recording(BisectionController):
        def observe(self, time_s, quality=None):
            seen.append(time_s)
            super().observe(time_s, quality)

    ctrl = Recording(ControllerConfig(deadline_s=100.0), None, len(ds.rig))
    fe = FrontEnd(ds.rig, runtime_config(), ctrl, scene.tracker(ds.rig))
    with ds.open_frames() as src:
        framesets = [src.read(t) for t in range(2)]
    outs = []
    for task, frames in enumerate(framesets):
        plan = fe.next_plan(frames.time_index)
        outs.append((plan, fe.run_task(frames, plan, lambda w: None, time.sleep, task=task)))
    (golden, first), (after, second) = outs
    assert golden.phase == "golden" and after.phase != "golden"
    assert "sfm" not in first.metrics.stages and "sfm" not in second.metrics.stages
    assert first.metrics.stages["sfm_mapping"] > 0 and first.metrics.num_sparse > 0
    assert "sfm_mapping" not in second.metrics.stages
    assert fe.pi_source is not None and fe.pi_source["task"] == 0 and fe.pi_source["rows"] > 0
    assert seen[0] == pytest.approx(first.metrics.critical_path_s, abs=1e-5)
    assert seen[1] == pytest.approx(second.metrics.critical_path_s, abs=1e-5)
    # With the paper's online estimate every task runs SfM on its critical path.
    seen.clear()
    ctrl = Recording(ControllerConfig(deadline_s=100.0), None, len(ds.rig))
    config = runtime_config(online_quality="golden", golden_timeout_s=0.1)
    fe = FrontEnd(ds.rig, config, ctrl, scene.tracker(ds.rig))
    plan = fe.next_plan(framesets[0].time_index)
    out = fe.run_task(framesets[0], plan, lambda w: None, time.sleep, task=0)
    assert plan.phase == "golden" and out.metrics.stages["sfm"] > 0
    assert seen[0] == pytest.approx(out.metrics.critical_path_s, abs=1e-5)


def test_resume_goes_on_with_cameras_placed_again_without_the_old_background(
    tiny, tmp_path, monkeypatch
):
    """A resume whose dataset's rig placed a camera again (``calib --write``) goes on with
    it, everything on: the background built with the poses before is not merged again."""
    import dataclasses

    from edgerecon.io.calibration import load_rig
    from tests.quality.test_calibration import moved

    ds = tiny[0]
    config = runtime_config()
    pushed = []
    real_push = FrontEnd.push_background

    def push(self, update):
        pushed.append(update)
        return real_push(self, update)

    monkeypatch.setattr(FrontEnd, "push_background", push)

    def slow(m):  # the back-end of epoch 1 pushes a background before task 1
        if m.task == 0:
            assert wait_until(lambda: len(pushed) > 0, timeout=180)

    out = tmp_path / "run"
    run_frames(tiny, out, 0, 3, config, fixed=(0.8, None), on_task=slow)
    old = RunState.load(out)
    assert old.frontend.bg_version.epoch == 1 and (out / "background.ply").exists()

    placed = dataclasses.replace(ds, rig=moved(ds.rig, 1, (0.02, 0.0, 0.0), (0.0, 0.5, 0.0)))
    summary, resumed = run_online(
        placed,
        config,
        SessionOptions(frames=FrameRange(start=0, stop=6), resume=True),
        out,
        fixed=(0.8, None),
    )
    assert [m.time_index for m in resumed] == list(range(6))
    assert all(m.status == "ok" for m in resumed)
    # The resumed tasks merged with no background of the poses before (epoch 1).
    assert all(m.background_version.epoch != 1 for m in resumed[3:])
    (rec,) = summary.recalibrations
    assert rec["from_task"] == 3 and rec["cameras"] == ["cam1"]
    assert rec["moved"][0] == pytest.approx(0.02, abs=1e-6)
    assert rec["turned_deg"][0] == pytest.approx(0.5, abs=1e-4)
    state = RunState.load(out)
    assert state.dataset == DatasetIdentity.of(placed)
    assert [r.to_dict() for r in state.recalibrations] == [rec]
    assert DatasetIdentity.of(dataclasses.replace(ds, rig=load_rig(out / "rig.0.json"))) == (
        old.dataset
    )
    assert DatasetIdentity.of(dataclasses.replace(ds, rig=load_rig(out / "rig.json"))) == (
        state.dataset
    )


def test_resume_refuses_a_calibration_that_is_not_cameras_placed_again(tiny, tmp_path):
    import dataclasses

    from edgerecon.io.calibration import save_rig
    from tests.quality.test_calibration import moved

    ds = tiny[0]
    _state(ds).save(tmp_path)
    save_rig(tmp_path / "rig.json", ds.rig)

    def resume(rig):
        other = dataclasses.replace(ds, rig=rig)
        with OutputFolder(tmp_path).acquire() as folder:
            return folder.prepare(
                resume=True,
                overwrite=False,
                identity=DatasetIdentity.of(other),
                frames=(0, 4, 1),
                rig=other.rig,
            )

    cams = list(ds.rig)
    cams[0] = dataclasses.replace(cams[0], K=cams[0].K * [[1.01], [1.01], [1]])
    with pytest.raises(EdgereconError, match="cam0's lens or image size changed"):
        resume(dataclasses.replace(ds.rig, cameras=tuple(cams)))
    with pytest.raises(EdgereconError, match="another unit"):
        resume(dataclasses.replace(ds.rig, unit="mm"))
    three = ds.rig
    for i in (0, 1, 2):
        three = moved(three, i, (0.1, 0.0, 0.0), (0.0, 0.0, 0.0))
    with pytest.raises(EdgereconError, match="3 of 5 cameras moved: another world frame"):
        resume(three)
    # Refused ones changed nothing: the run state is the one before.
    assert RunState.load(tmp_path).dataset == DatasetIdentity.of(ds)
    (tmp_path / "rig.json").unlink()
    with pytest.raises(EdgereconError, match=r"own rig .* cannot be read"):
        resume(moved(ds.rig, 1, (0.1, 0.0, 0.0), (0.0, 0.0, 0.0)))
    save_rig(tmp_path / "rig.json", ds.rig)
    state = resume(moved(ds.rig, 1, (0.1, 0.0, 0.0), (0.0, 0.0, 0.0)))
    assert state is not None and state.recalibrations[0].cameras == ("cam1",)
    assert (tmp_path / "rig.0.json").exists()


def test_a_run_saved_with_the_fingerprint_before_resumes(tiny, tmp_path):
    """Run states saved before the fingerprint covered the rig's frame and unit resume
    (the same rig: no recalibration recorded; the state takes the new fingerprint)."""
    import dataclasses

    from edgerecon.io.calibration import save_rig
    from edgerecon.runtime.state import rig_fingerprint

    ds = tiny[0]
    old = _state(ds)
    legacy = dataclasses.replace(old.dataset, rig_fingerprint=rig_fingerprint(ds.rig, frame=False))
    dataclasses.replace(old, dataset=legacy).save(tmp_path)
    save_rig(tmp_path / "rig.json", ds.rig)
    with OutputFolder(tmp_path).acquire() as folder:
        state = folder.prepare(
            resume=True,
            overwrite=False,
            identity=DatasetIdentity.of(ds),
            frames=(0, 4, 1),
            rig=ds.rig,
        )
        assert folder.recalibration is None
    assert state is not None and state.recalibrations == ()
    assert RunState.load(tmp_path).dataset == DatasetIdentity.of(ds)
    assert not (tmp_path / "rig.0.json").exists()


def test_the_cameras_views_round_trip_and_a_torn_file_is_said_not_fatal(tmp_path, caplog):
    folder = OutputFolder(tmp_path)
    assert folder.read_views() is None
    views = {
        "cam0": np.arange(12, dtype=np.uint8).reshape(3, 4),
        "cam 1": np.full((2, 2), 7, np.uint8),
    }
    folder.write_views(views, 41, {"cam 1": views["cam0"]}, {"cam 1": 2})
    time_index, back, steady, moves = folder.read_views()
    assert time_index == 41 and list(back) == ["cam0", "cam 1"]
    assert all(np.array_equal(back[k], v) for k, v in views.items())
    assert list(steady) == ["cam 1"] and np.array_equal(steady["cam 1"], views["cam0"])
    assert moves == {"cam 1": 2}
    (tmp_path / VIEWS_FILE).write_bytes((tmp_path / VIEWS_FILE).read_bytes()[:50])
    assert folder.read_views() is None
    assert "a camera moved while the run was stopped is not seen" in caplog.text
