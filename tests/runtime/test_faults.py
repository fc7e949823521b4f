"""A task can fail; a run cannot (issue 11 item 5): unusable frames, a stage that raises on the
front-end or the back-end, a stage that hangs, and the two-object crash, each with background
updates on."""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import re
import shutil
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

import edgerecon.pipeline
import edgerecon.runtime.backend
import edgerecon.scene.objects
from edgerecon.cli.run import parse_fault, task_row
from edgerecon.io.calibration import save_rig
from edgerecon.io.dataset import open_dataset
from edgerecon.quality.calibration import knocked
from edgerecon.quality.frames import FrameCheckConfig, FrozenCameras, frame_defect
from edgerecon.runtime import RuntimeConfig
from edgerecon.runtime.backend import RebuildTimeout, _RebuildWorker, rebuild_background
from edgerecon.runtime.engine import EmbeddedEngine
from edgerecon.runtime.interrupt import Runner, ThreadAbandoned, stop_thread
from edgerecon.scene.foreground import RigForeground
from tests.runtime.conftest import run_frames, runtime_config, wait_until


def test_frame_defects_known_answers():
    rng = np.random.default_rng(0)
    textured = rng.integers(0, 255, (240, 320, 3), dtype=np.uint8)
    dark_noise = rng.integers(0, 6, (240, 320, 3), dtype=np.uint8)  # lights out, sensor noise
    grey = np.clip(128 + rng.normal(0, 1.0, (240, 320, 3)), 0, 255).astype(np.uint8)
    assert frame_defect(textured) is None
    assert frame_defect(np.zeros((240, 320, 3), np.uint8)) == "black"
    assert frame_defect(dark_noise) == "black"
    assert frame_defect(np.full((240, 320, 3), 255, np.uint8)) == "saturated"
    assert frame_defect(grey) == "textureless"
    assert frame_defect(grey, FrameCheckConfig(textureless_max_std=0.5)) is None
    with pytest.raises(ValueError, match="black_max_level"):
        FrameCheckConfig(black_max_level=250)


def test_black_frames_give_empty_tasks_fast_with_one_warning(
    tiny, tiny_dataset, tmp_path_factory, tmp_path, caplog
):
    # Lights out at times 3-4 (every camera) and two cameras blinded at time 5. The lit
    # background model took every black pixel for foreground: the visual hull filled the
    # room and each such task cost many times a normal one (minutes per task at full HD).
    src = tmp_path_factory.mktemp("dark") / "scene"
    shutil.copytree(tiny_dataset, src)
    for cam in range(5):
        for t in (3, 4):
            path = src / "frames" / f"cam{cam}" / f"{t:06d}.png"
            cv2.imwrite(str(path), np.zeros((240, 320, 3), np.uint8))
    for cam in (0, 1):
        cv2.imwrite(
            str(src / "frames" / f"cam{cam}" / "000005.png"), np.zeros((240, 320, 3), np.uint8)
        )
    caplog.set_level(logging.WARNING)
    summary, metrics = run_frames((open_dataset(src), tiny[1]), tmp_path, 0, 7)
    assert [m.status for m in metrics] == ["ok"] * 7
    for m in metrics[3:5]:
        assert m.frame_defects == {f"cam{k}": "black" for k in range(5)}
        assert m.num_fg_points == 0 and m.num_cameras == 0 and not m.submitted
        assert m.num_merged_points >= 0
    # Fast: an empty task costs the frame check, not a reconstruction.
    assert metrics[4].wall_time - metrics[3].wall_time < 0.5 * (
        metrics[3].wall_time - metrics[1].wall_time
    )
    assert metrics[5].frame_defects == {"cam0": "black", "cam1": "black"}
    assert metrics[5].num_cameras == 3 and metrics[5].num_fg_points > 0
    assert metrics[6].frame_defects == {} and metrics[6].num_cameras == 5
    assert summary.empty == 2 and summary.failed == 0
    unusable = [r for r in caplog.records if "unusable frames" in r.getMessage()]
    # One warning when the lights go out, one when two cameras stay blinded, then recovery.
    assert len(unusable) == 2
    assert any("usable again" in r.getMessage() for r in caplog.records)


def test_a_camera_whose_frames_stop_changing_is_frozen_until_they_change():
    rng = np.random.default_rng(1)

    def frames(t, images):
        from edgerecon.types import FrameSet

        # Every other set without a time: at time_index / fps (10), the same seconds.
        return FrameSet(time_index=t, images=tuple(images), timestamp_s=None if t % 2 else t / 10)

    noise = [rng.integers(0, 255, (120, 160, 3), dtype=np.uint8) for _ in range(40)]
    watch = FrozenCameras(FrameCheckConfig(frozen_after_s=1.0), fps=10.0)
    events = []
    for t in range(30):
        # cam1 repeats its frame of t = 5 until t = 20 and has none at t = 17; cam2 has no
        # frame from t = 8 to 25 (stalled: not frozen).
        cam1 = None if t == 17 else noise[5] if 5 <= t < 20 else noise[t + 1]
        cam2 = None if 8 <= t < 26 else noise[(t + 2) % 40]
        events.append(watch.update(frames(t, [noise[t], cam1, cam2])))
        if t in (15, 17):
            assert watch.frozen == {1}
    froze = [t for t, (a, _) in enumerate(events) if a]
    thawed = [t for t, (_, b) in enumerate(events) if b]
    assert froze == [15] and events[15] == ([1], [])  # 1.0 s after its frame of t = 5
    assert thawed == [20] and events[20] == ([], [1]) and watch.frozen == set()
    # A still scene (every camera the same, or a paused stream) freezes nobody; 0 = no check.
    still = FrozenCameras(FrameCheckConfig(frozen_after_s=0.5), fps=10.0)
    off = FrozenCameras(FrameCheckConfig(frozen_after_s=0.0), fps=10.0)
    for t in range(20):
        assert still.update(frames(t, noise[:3])) == ([], [])
        assert off.update(frames(t, [noise[0], noise[t], noise[t + 1]])) == ([], [])
    with pytest.raises(ValueError, match="frozen_after_s"):
        FrameCheckConfig(frozen_after_s=-1.0)


def test_a_frozen_camera_is_said_once_and_recorded_with_everything_on(
    tiny, tiny_dataset, tmp_path_factory, tmp_path, caplog
):
    # cam3 repeats its frame of time 1 at times 2-5 (a stuck camera), then recovers.
    src = tmp_path_factory.mktemp("frozen") / "scene"
    shutil.copytree(tiny_dataset, src)
    frames = src / "frames" / "cam3"
    for t in range(2, 6):
        shutil.copy(frames / "000001.png", frames / f"{t:06d}.png")
    ds = open_dataset(src)
    step = 1.0 / (ds.fps or 25.0)
    config = runtime_config(frame_check=FrameCheckConfig(frozen_after_s=2.5 * step))
    caplog.set_level(logging.WARNING)
    summary, metrics = run_frames((ds, tiny[1]), tmp_path, 0, 8, config=config)
    assert [m.status for m in metrics] == ["ok"] * 8 and summary.failed == 0
    # Frozen from time 1's frame: 2.5 frame intervals later, at time 4, until time 6.
    assert [m.frozen_cameras for m in metrics] == [[], [], [], [], ["cam3"], ["cam3"], [], []]
    assert all(m.num_cameras == 5 for m in metrics)  # kept in the tasks
    assert task_row(metrics[4])[-1].endswith(" frozen cam3")  # run's row of the task
    said = [r.getMessage() for r in caplog.records if "cam3" in r.getMessage()]
    assert len(said) == 2 and "same frame" in said[0] and "new frame again" in said[1]


def test_a_stage_that_raises_is_a_failed_record(tiny, tmp_path, monkeypatch):
    # Time 1: the scene stage raises (the front-end computes the masks). Time 3: the
    # front-end's foreground MVS raises.
    real_mvs = edgerecon.pipeline.reconstruct_foreground
    real_segment = RigForeground.segment
    calls = {"n": 0}

    def mvs(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3:  # the third task that gets that far: time 3
            raise RuntimeError("boom in the foreground MVS")
        return real_mvs(*args, **kwargs)

    def segment(self, frames, **kw):
        if frames.time_index == 1:
            raise ValueError("zero-size array to reduction operation minimum which has no identity")
        return real_segment(self, frames, **kw)

    monkeypatch.setattr(edgerecon.pipeline, "reconstruct_foreground", mvs)
    monkeypatch.setattr(RigForeground, "segment", segment)
    summary, metrics = run_frames(tiny, tmp_path, 0, 5)
    assert [m.status for m in metrics] == ["ok", "failed", "ok", "failed", "ok"]
    assert "zero-size array" in metrics[1].error
    assert "RuntimeError: boom in the foreground MVS" in metrics[3].error
    assert "reconstruct_task" in metrics[3].error  # where it was raised
    assert not metrics[2].degraded and not metrics[4].degraded, "the run goes on whole"
    assert metrics[2].submitted and metrics[4].submitted, "the back-end serves on"
    assert summary.failed == 2 and not (tmp_path / "tasks" / "000003").exists()


def test_a_stage_that_hangs_is_abandoned_by_the_watchdog(tiny, tmp_path, monkeypatch):
    release = threading.Event()
    real = edgerecon.pipeline.reconstruct_foreground
    calls = {"n": 0}

    def hang(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:
            release.wait(120)  # a stage that never returns (until the test ends)
        return real(*args, **kwargs)

    monkeypatch.setattr(edgerecon.pipeline, "reconstruct_foreground", hang)
    try:
        summary, metrics = run_frames(
            tiny, tmp_path, 0, 4, runtime_config(task_timeout_s=12.0), fixed=(0.8, None)
        )
    finally:
        release.set()
    assert [m.status for m in metrics] == ["ok", "failed", "ok", "ok"]
    assert metrics[1].error.startswith("watchdog: still running after 12.0 s")
    assert metrics[2].wall_time - metrics[1].wall_time < 60
    # Blocked inside a native wait, its thread still runs at the end: the summary says so.
    assert summary.abandoned_threads == ["task 1 (time 1) abandoned by the watchdog"]
    assert RuntimeConfig(deadline_s=2.0).watchdog_s == 30.0
    assert RuntimeConfig(deadline_s=5.0).watchdog_s == 50.0


def test_a_stage_looping_for_ever_is_stopped_with_its_thread(tiny, tmp_path, monkeypatch):
    # A stage that never reaches a stage boundary (a loop that does not end) kept its thread
    # after the watchdog gave up on it: on a 2-core device a core lost for the whole run.
    real = edgerecon.pipeline.reconstruct_foreground
    calls = {"n": 0}
    loop: dict[str, float] = {}

    def spin(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:
            try:
                while True:  # Python code that never returns
                    time.sleep(0.005)
            finally:
                loop["ended"] = time.monotonic()
        return real(*args, **kwargs)

    monkeypatch.setattr(edgerecon.pipeline, "reconstruct_foreground", spin)
    summary, metrics = run_frames(
        tiny, tmp_path, 0, 4, runtime_config(task_timeout_s=12.0), fixed=(0.8, None)
    )
    assert [m.status for m in metrics] == ["ok", "failed", "ok", "ok"]
    assert metrics[1].error.startswith("watchdog: still running after 12.0 s")
    assert "ended" in loop, "the looping stage was stopped"
    assert summary.abandoned_threads == []
    assert not [t for t in threading.enumerate() if t.name == "task-1"]


def test_the_hang_drill_fails_one_task_and_the_run_goes_on(tiny, tmp_path):
    # `--inject-fault TASK:hang`: the front-end's task loops for ever in Python code.
    summary, metrics = run_frames(
        tiny,
        tmp_path,
        0,
        4,
        runtime_config(task_timeout_s=8.0),
        fixed=(0.8, None),
        faults=((1, "hang", 0.0),),
    )
    assert [m.status for m in metrics] == ["ok", "failed", "ok", "ok"]
    assert metrics[1].error.startswith("watchdog: still running after 8.0 s")
    assert summary.abandoned_threads == []
    assert parse_fault("3:hang") == (3, "hang", 30.0)


def test_stop_thread_raises_in_the_thread_at_its_next_instruction():
    ended = threading.Event()

    def loop() -> None:
        try:
            while True:
                time.sleep(0.001)
        except ThreadAbandoned:
            ended.set()

    th = threading.Thread(target=loop, daemon=True)
    th.start()
    assert stop_thread(th)
    th.join(5.0)
    assert ended.is_set() and not th.is_alive()
    assert not stop_thread(th), "an ended thread is not stopped again"
    assert not stop_thread(threading.Thread(target=loop)), "nor one never started"


def test_a_runner_returns_raises_or_leaves_the_thread_to_the_caller():
    runner = Runner("r")
    done = runner.call(lambda: 7, 10.0)
    assert (done.timed_out, done.value, done.error) == (False, 7, None)
    failed = runner.call(lambda: 1 / 0, 10.0, name="t")
    assert not failed.timed_out and isinstance(failed.error, ZeroDivisionError)
    # Calls that end share one thread: a thread per call kept native per-thread data.
    assert failed.thread is done.thread and done.thread.is_alive() and done.thread.daemon
    release = threading.Event()
    slow = runner.call(lambda: release.wait(30.0), 0.2, name="slow")
    assert slow.timed_out and slow.value is None and slow.error is None
    assert slow.thread is done.thread and slow.thread.name == "slow"  # while it runs
    # Given up on: the next call runs on a new thread, the old one ends after its call.
    after = runner.call(lambda: threading.current_thread(), 10.0)
    assert after.value is not slow.thread and after.value is after.thread
    release.set()
    assert slow.wait(5.0) and not slow.timed_out
    assert after.thread.name == "r", "named after the runner when idle"
    slow.thread.join(5.0)
    assert not slow.thread.is_alive()
    # A runner dropped lets its idle thread end.
    kept = after.thread
    del runner, after
    kept.join(5.0)
    assert not kept.is_alive()


def _gone(pid: int, timeout: float = 10.0) -> bool:
    """The process ``pid`` ended (gone, or a zombie not yet reaped) within ``timeout``."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            with open(f"/proc/{pid}/stat") as f:
                if f.read().rsplit(")", 1)[1].split()[0] == "Z":
                    return True
        except FileNotFoundError:
            return True
        time.sleep(0.1)
    return False


def _sleep_for_ever() -> None:  # module level: the rebuild process imports it by name
    while True:
        time.sleep(1.0)


def test_a_background_rebuild_that_hangs_has_its_process_killed():
    # The back-end's thread waited for its rebuild process without a limit: one rebuild
    # that hangs, and the background stayed as it was for the rest of the run.
    worker = _RebuildWorker(nice=0)
    try:
        first = worker.call(os.getpid, timeout_s=120.0)  # the process starts (spawn)
        t0 = time.monotonic()
        with pytest.raises(RebuildTimeout, match="its process was killed"):
            worker.call(_sleep_for_ever, timeout_s=1.0)
        assert time.monotonic() - t0 < 10.0
        assert _gone(first), "the hung rebuild's process was killed"
        second = worker.call(os.getpid, timeout_s=120.0)
        assert second != first, "the next rebuild runs in a new process"
        assert worker.call(pow, 3, 3, timeout_s=60.0) == 27
    finally:
        worker.close()
    assert RuntimeConfig(deadline_s=2.0).rebuild_limit_s == 300.0
    assert RuntimeConfig(deadline_s=60.0).rebuild_limit_s == 6000.0
    assert RuntimeConfig(deadline_s=2.0, rebuild_timeout_s=5.0).rebuild_limit_s == 5.0
    with pytest.raises(ValueError, match="rebuild_timeout_s"):
        RuntimeConfig(deadline_s=2.0, rebuild_timeout_s=0.0)


def test_closing_the_rebuild_worker_kills_what_runs_there():
    # A rebuild (or calibration check) still running when the back-end stops: its result
    # has no taker; the stop waited for it (up to 5 s) and it ran on after the run ended.
    import concurrent.futures
    import threading
    from concurrent.futures.process import BrokenProcessPool

    worker = _RebuildWorker(nice=0)
    pid = worker.call(os.getpid, timeout_s=120.0)
    errors: list[BaseException] = []

    def rebuild() -> None:
        try:
            worker.call(_sleep_for_ever, timeout_s=600.0)
        except BaseException as exc:  # what the rebuild loop gets
            errors.append(exc)

    th = threading.Thread(target=rebuild)
    th.start()
    time.sleep(1.0)
    t0 = time.monotonic()
    worker.close()
    th.join(10.0)
    assert not th.is_alive() and time.monotonic() - t0 < 10.0
    assert len(errors) == 1
    assert isinstance(errors[0], (BrokenProcessPool, concurrent.futures.CancelledError))
    assert _gone(pid), "the worker's process was killed"


def _rebuild_hanging_once(rig, config, frames, masks):  # runs in the rebuild process
    marker = Path(os.environ["EDGERECON_TEST_REBUILD_MARKER"])
    if not marker.exists():
        marker.touch()
        _sleep_for_ever()
    return rebuild_background(rig, config, frames, masks)


@pytest.mark.parametrize("in_process", [True, False], ids=["process", "thread"])
def test_a_run_whose_first_background_rebuild_hangs_gets_its_backgrounds(
    tiny, tmp_path, monkeypatch, caplog, in_process
):
    # Everything on: the back-end's first rebuild (the stream's first background) hangs in
    # its process; it is killed, and the next rebuild, in a new process, reaches the tasks.
    # With background_process = false the rebuild's thread is stopped instead (it waited
    # without a limit).
    monkeypatch.setenv("EDGERECON_TEST_REBUILD_MARKER", str(tmp_path / "hung-once"))
    monkeypatch.setattr(edgerecon.runtime.backend, "rebuild_background", _rebuild_hanging_once)
    caplog.set_level(logging.ERROR)
    stopped = "its process was killed" if in_process else "its thread was stopped"

    def killed() -> bool:
        return any(stopped in r.getMessage() for r in caplog.records)

    def pause(m) -> None:  # after task 3, idle time for the next rebuild once one was killed
        if m.task == 3:
            end = time.monotonic() + 60.0
            while not killed() and time.monotonic() < end:
                time.sleep(0.2)
            time.sleep(20.0)

    n = tiny[0].num_frames
    summary, metrics = run_frames(
        tiny,
        tmp_path / "run",
        0,
        n,
        runtime_config(rebuild_timeout_s=10.0, background_process=in_process),
        fixed=(0.8, None),
        on_task=pause,
    )
    assert [m.status for m in metrics] == ["ok"] * n
    assert (tmp_path / "hung-once").exists(), "the first rebuild hung"
    assert killed()
    assert summary.abandoned_threads == [], "the hung rebuild's thread ended"
    assert summary.backgrounds_pushed >= 1, "a background after the killed rebuild"
    assert metrics[-1].background_version > metrics[0].background_version


def test_two_object_crash_is_a_failed_record_also_after_resume(tiny, tmp_path, monkeypatch):
    # The two-person capture crashed the whole run in scene/objects.py _component_gaps, and
    # again after --resume. Whatever raises there now fails only the task.
    real = edgerecon.scene.objects._component_gaps
    broken = {"times": {1, 3}}
    current = {"t": -1}

    def gaps(cc, num_comp):
        if current["t"] in broken["times"]:
            return np.zeros((0,)).min()  # the original 'zero-size array' ValueError
        return real(cc, num_comp)

    real_segment = RigForeground.segment

    def segment(self, frames, **kw):
        current["t"] = frames.time_index
        return real_segment(self, frames, **kw)

    monkeypatch.setattr(edgerecon.scene.objects, "_component_gaps", gaps)
    monkeypatch.setattr(RigForeground, "segment", segment)
    _, first = run_frames(tiny, tmp_path, 0, 3)
    assert [m.status for m in first] == ["ok", "failed", "ok"]
    assert "zero-size array" in first[1].error and "scene/objects.py" in first[1].error
    summary, metrics = run_frames(tiny, tmp_path, 0, 5, resume=True)
    assert [m.status for m in metrics] == ["ok", "failed", "ok", "failed", "ok"]
    assert summary.tasks == 5 and summary.failed == 2


def test_a_scene_stage_that_hangs_leaves_the_background_models_to_the_next_tasks(
    tiny_dataset, tmp_path, monkeypatch
):
    # The scene stage of the second task hangs holding the background models; with
    # updates every frame (between tasks and on the tasks' own frames) the later tasks go
    # on with the models' copy from before it, the updates since applied again.
    from edgerecon.runtime.engine import learn_scene_model
    from edgerecon.scene import ForegroundConfig

    ds = open_dataset(tiny_dataset)
    fg_config = ForegroundConfig(update_interval_s=1.0 / ds.fps)
    scene = learn_scene_model(ds, fg_config)
    release = threading.Event()
    segment = RigForeground.segment

    def hang(self, frames):  # type: ignore[no-untyped-def]
        if frames.time_index == 2:
            release.wait(120)  # a stage that never returns (until the test ends)
        return segment(self, frames)

    monkeypatch.setattr(RigForeground, "segment", hang)
    config = runtime_config(task_timeout_s=12.0, foreground=fg_config)
    try:
        _, metrics = run_frames((ds, scene), tmp_path, 0, 6, config, fixed=(0.8, None))
    finally:
        release.set()
    assert [m.status for m in metrics] == ["ok", "ok", "failed", "ok", "ok", "ok"]
    assert metrics[2].error.startswith("watchdog: still running after 12.0 s")
    # The next tasks did not wait for the hung one's models (each within its own time).
    assert metrics[3].wall_time - metrics[2].wall_time < 12.0
    assert all(m.num_fg_points > 0 for m in metrics[3:])


def test_a_camera_turned_during_a_run_is_said_and_recorded_with_everything_on(
    tiny_dataset, tmp_path_factory, tmp_path, caplog, monkeypatch
):
    from edgerecon.io.calibration import save_rig
    from edgerecon.runtime.engine import learn_scene_model
    from tests.quality.test_calibration import turned

    src = tmp_path_factory.mktemp("turned") / "scene"
    shutil.copytree(tiny_dataset, src)
    save_rig(src / "rig.json", turned(open_dataset(src).rig, 1, 2.0, (1.0, 0.0, 0.0)))
    ds = open_dataset(src)
    caplog.set_level(logging.WARNING)
    config = runtime_config(calib_check_s=1e-3)  # at every rebuild
    # Tasks of a second or so, so that rebuilds (and checks) run beside them.
    dense = edgerecon.pipeline.reconstruct_foreground

    def slow(*args, **kwargs):
        time.sleep(1.0)
        return dense(*args, **kwargs)

    monkeypatch.setattr(edgerecon.pipeline, "reconstruct_foreground", slow)
    summary, metrics = run_frames((ds, learn_scene_model(ds)), tmp_path, 0, 7, config=config)
    assert summary.failed == 0 and len(metrics) == 7
    assert summary.calibration is not None
    assert summary.calibration["fits"] is False and summary.calibration["off"] == ["cam1"]
    # What `edgerecon calib --write` would do, from the run's frames.
    turn = re.fullmatch(
        r"cam1 re-aimed by ([0-9.]+) degrees: the calibration then fits",
        summary.calibration["repair"],
    )
    assert turn is not None and float(turn[1]) == pytest.approx(2.0, abs=0.1)
    said = [
        r.getMessage() for r in caplog.records if "moved since it was calibrated" in r.getMessage()
    ]
    assert len(said) <= 1  # said once (when two checks in a row agree), never repeated
    assert all("cam1 re-aimed by" in m and "rig.repaired.json" in m for m in said)
    saved = json.loads((tmp_path / "summary.json").read_text())
    assert saved["calibration"]["off"] == ["cam1"]
    # The rig the repair made fit is in the run folder (not in the summary), and
    # `calib --adopt` names it in the dataset (what a live dataset has to go by); the run's
    # --resume goes on with it.
    from edgerecon.cli import main
    from edgerecon.cli.calib import RECALIBRATED
    from edgerecon.io.calibration import load_rig
    from edgerecon.runtime import FrameRange, SessionOptions, run_online
    from tests.quality.test_calibration import angle_deg

    assert saved["calibration"]["repaired_rig_file"] == "rig.repaired.json"
    assert "repaired_rig" not in saved["calibration"]
    repaired = load_rig(tmp_path / "rig.repaired.json")
    calibrated = open_dataset(tiny_dataset).rig
    assert angle_deg(repaired[1], calibrated[1]) < 0.3
    assert (
        main(["calib", "--dataset", str(src), "--adopt", str(tmp_path / "rig.repaired.json")]) == 0
    )
    assert json.loads((src / "dataset.json").read_text())["rig"] == RECALIBRATED
    adopted = open_dataset(src)
    assert angle_deg(adopted.rig[1], calibrated[1]) < 0.3
    summary, metrics = run_online(
        adopted,
        config,
        SessionOptions(frames=FrameRange(start=0, stop=8), resume=True),
        tmp_path,
    )
    assert summary.failed == 0 and [m.time_index for m in metrics] == list(range(8))
    (rec,) = summary.recalibrations
    assert rec["cameras"] == ["cam1"] and rec["turned_deg"][0] == pytest.approx(2.0, abs=0.3)
    assert summary.calibration is None or summary.calibration["fits"] is not False


def slow_tasks_until_said(tmp_path, caplog, monkeypatch, wait_at: int) -> None:
    """Checks at every rebuild (``tmp_path / "cfg.toml"``) and tasks of a second or so, so
    that rebuilds and checks run beside them; from task ``wait_at`` on, each task waits up
    to 40 s for the back-end's (confirmed) verdict that a camera moved (the back-end checks
    at its rebuilds, which need new frames: a loaded machine may take more than one)."""
    (tmp_path / "cfg.toml").write_text("[runtime]\ncalib_check_s = 0.001\n")
    dense = edgerecon.pipeline.reconstruct_foreground
    calls = []

    def said():
        return any("moved since it was calibrated" in r.getMessage() for r in caplog.records)

    def slow(*args, **kwargs):
        calls.append(1)
        time.sleep(1.0)
        if len(calls) >= wait_at and not said():
            wait_until(said, timeout=40)
        return dense(*args, **kwargs)

    monkeypatch.setattr(edgerecon.pipeline, "reconstruct_foreground", slow)


def adopting_run(src: Path, tmp_path: Path, caplog, capsys) -> dict:
    """``edgerecon run --adopt-repairs --json`` on ``src`` (its 8 timestamps, every task
    run once) with ``tmp_path / "cfg.toml"``: its JSON."""
    from edgerecon.cli import main

    caplog.set_level(logging.WARNING)
    out = tmp_path / "run"
    args = ["run", "--dataset", str(src), "--out", str(out), "--deadline", "20"]
    args += ["--config", str(tmp_path / "cfg.toml"), "--adopt-repairs", "--json"]
    assert main(args) == 0
    result = json.loads(capsys.readouterr().out)
    assert [t["time_index"] for t in result["tasks"]] == list(range(8))
    return result


def test_run_adopt_repairs_goes_on_with_the_turned_camera_re_aimed(
    tiny_dataset, tmp_path, caplog, capsys, monkeypatch
):
    """``run --adopt-repairs``, everything on: the back-end's confirmed repair is named in
    the dataset and the run goes on with it (as a --resume would), every task once."""
    from edgerecon.cli.calib import RECALIBRATED
    from edgerecon.io.calibration import save_rig
    from tests.quality.test_calibration import angle_deg, turned

    src = tmp_path / "scene"
    shutil.copytree(tiny_dataset, src)
    calibrated = open_dataset(src).rig
    save_rig(src / "rig.json", turned(calibrated, 1, 2.0, (1.0, 0.0, 0.0)))
    slow_tasks_until_said(tmp_path, caplog, monkeypatch, wait_at=4)
    import edgerecon.runtime.online as online

    learned = []
    learn = online.learn_scene_model

    def counted(*args, **kwargs):
        learned.append(args)
        return learn(*args, **kwargs)

    monkeypatch.setattr(online, "learn_scene_model", counted)
    result = adopting_run(src, tmp_path, caplog, capsys)
    assert all(t["status"] == "ok" for t in result["tasks"])
    (rec,) = result["summary"]["recalibrations"]
    assert rec["cameras"] == ["cam1"] and rec["turned_deg"][0] == pytest.approx(2.0, abs=0.3)
    assert 0 < rec["from_task"] < 8
    assert json.loads((src / "dataset.json").read_text())["rig"] == RECALIBRATED
    assert angle_deg(open_dataset(src).rig[1], calibrated[1]) < 0.3
    adopted = [r.getMessage() for r in caplog.records if "--adopt-repairs" in r.getMessage()]
    assert len(adopted) == 1 and "cam1 (turned 2.0" in adopted[0]
    # The background models went on across the adoption: learned once, at the start.
    assert len(learned) == 1


def test_a_camera_knocked_during_a_run_is_re_aimed_once_and_stays_so(
    tiny_dataset, tmp_path, caplog, capsys, monkeypatch
):
    """``run --adopt-repairs`` with cam1 knocked by 2 degrees after the empty-scene clip was
    recorded (its frames seen turned; the clip as calibrated): the repair is adopted once
    and kept. The back-end that the adoption starts rebuilt and checked the clip, which
    shows cam1 as it was: it named cam1 again and the run turned it back (the demo scene,
    knocked at time 60 of 150: docs/BENCHMARKS.md)."""
    from tests.quality.test_calibration import angle_deg

    src = tmp_path / "scene"
    shutil.copytree(tiny_dataset, src)
    calibrated = open_dataset(src).rig
    c = calibrated[1]
    dR = cv2.Rodrigues(np.radians(2.0) * np.array([1.0, 0.0, 0.0]))[0]
    H = c.K @ dR @ np.linalg.inv(c.K)
    for t in range(8):
        path = src / "frames" / "cam1" / f"{t:06d}.png"
        image = cv2.imread(str(path))
        h, w = image.shape[:2]
        warped = cv2.warpPerspective(image, H, (w, h), borderMode=cv2.BORDER_REPLICATE)
        cv2.imwrite(str(path), warped)
    slow_tasks_until_said(tmp_path, caplog, monkeypatch, wait_at=5)
    import edgerecon.runtime.engine as engine

    seeded = []  # each back-end's first rebuild source (the clip's frames: time -1)
    backend_class = engine.BackEnd

    def backend(*args, **kwargs):
        first = kwargs.get("initial_background")
        seeded.append(None if first is None else first.time_index)
        return backend_class(*args, **kwargs)

    monkeypatch.setattr(engine, "BackEnd", backend)
    result = adopting_run(src, tmp_path, caplog, capsys)
    # The clip seeds the first back-end only: after the adoption it shows cam1 as it was.
    assert seeded == [-1, None]
    (rec,) = result["summary"]["recalibrations"]
    assert rec["cameras"] == ["cam1"] and rec["turned_deg"][0] == pytest.approx(2.0, abs=0.3)
    # The rig the run goes on with: cam1 as knocked.
    assert angle_deg(open_dataset(src).rig[1], calibrated[1]) == pytest.approx(2.0, abs=0.3)


def _knock(src: Path, camera: int, times: range, degrees: float = 2.0) -> None:
    """The frames ``times`` of the dataset ``src``'s camera turned (tilted) by ``degrees``
    (a pinhole's image warp, K dR K^-1), written over the originals."""
    c = open_dataset(src).rig[camera]
    dR = cv2.Rodrigues(np.radians(degrees) * np.array([1.0, 0.0, 0.0]))[0]
    H = c.K @ dR @ np.linalg.inv(c.K)
    for t in times:
        path = src / "frames" / c.name / f"{t:06d}.png"
        image = cv2.imread(str(path))
        h, w = image.shape[:2]
        cv2.imwrite(
            str(path), cv2.warpPerspective(image, H, (w, h), borderMode=cv2.BORDER_REPLICATE)
        )


def test_a_camera_knocked_while_the_run_was_stopped_is_said_after_resume(
    tiny_dataset, tmp_path, caplog, capsys, monkeypatch
):
    """A run stopped after time 2; cam1 knocked (2 degrees) before it goes on at time 3:
    ``--resume`` compares the first frames with the views saved at the stop
    (``views.npz``) and says the move, dated at the first frame after the stop and marked
    ``across_stop``; its frames are turned back from then on and the back-end is asked to
    check them (from time 5). Without the saved views the
    detector starts from the knocked frames and sees nothing."""
    from edgerecon.cli import main

    src = tmp_path / "scene"
    shutil.copytree(tiny_dataset, src)
    (tmp_path / "cfg.toml").write_text("[runtime]\ndeadline_s = 20.0\n")
    caplog.set_level(logging.WARNING)

    def run(out: Path, frames: str, *extra: str) -> dict:
        args = ["run", "--dataset", str(src), "--out", str(out), "--frames", frames]
        assert main([*args, "--config", str(tmp_path / "cfg.toml"), "--json", *extra]) == 0
        return json.loads(capsys.readouterr().out)

    for out in (tmp_path / "run", tmp_path / "bare", tmp_path / "placed"):
        run(out, "0:3")
    assert (tmp_path / "run" / "views.npz").is_file()
    (tmp_path / "bare" / "views.npz").unlink()
    _knock(src, 1, range(3, 8))
    checks = []
    real = EmbeddedEngine.check_calibration

    def check(self, since, cameras):
        checks.append((since, list(cameras)))
        return real(self, since, cameras)

    monkeypatch.setattr(EmbeddedEngine, "check_calibration", check)
    caplog.clear()
    result = run(tmp_path / "run", "0:8", "--resume")
    said = [r.getMessage() for r in caplog.records if "view moved" in r.getMessage()]
    caplog.clear()
    bare = run(tmp_path / "bare", "0:8", "--resume")
    assert [t["time_index"] for t in result["tasks"]] == list(range(8))
    assert len(said) == 1
    assert (
        "time 5: cam1's view moved while the run was stopped (between time 2 and time 3"
        in (said[0])
    )
    (move,) = result["summary"]["camera_moves"]
    assert move["camera"] == "cam1" and move["time_index"] == 3 and move["across_stop"]
    assert move["seen_at"] == 5 and move["turn_deg"] == pytest.approx(2.0, abs=0.3)
    assert checks == [(5, ["cam1"])]  # the frames turned back, from the task that saw it
    assert bare["summary"]["camera_moves"] == []
    assert not any("view moved" in r.getMessage() for r in caplog.records)
    # Placed again before the resume (``calib --write``): its new pose is its view.
    save_rig(src / "rig.json", knocked(open_dataset(src).rig, 1, (0.0, 0.0, 0.0), (2.0, 0, 0)))
    placed = run(tmp_path / "placed", "0:8", "--resume")
    assert [r["cameras"] for r in placed["summary"]["recalibrations"]] == [["cam1"]]
    assert placed["summary"]["camera_moves"] == []


def test_a_swaying_camera_is_said_then_its_frames_are_turned_back(
    tiny_dataset, tmp_path, caplog, capsys
):
    """cam1 sways (tilted +-1.5 degrees, turn about from time 1; every frame a move with
    ``moved_after_frames`` 1): from its first move on each of its frames is turned back
    onto its view before that move (as a knocked camera's); its first three moves are
    said, the fourth says it keeps moving: the tasks record the turn taken off (1.5
    degrees), the summary the tasks; a stop and ``--resume`` goes on turning them back
    without saying it all again, and no re-aimed rig is made of a sway."""
    from edgerecon.cli import main

    src = tmp_path / "scene"
    shutil.copytree(tiny_dataset, src)
    for t in range(1, 8):
        _knock(src, 1, range(t, t + 1), 1.5 if t % 2 else -1.5)
    (tmp_path / "cfg.toml").write_text(
        "[runtime]\ndeadline_s = 20.0\n[runtime.frame_check]\nmoved_after_frames = 1\n"
    )
    caplog.set_level(logging.WARNING)
    args = ["run", "--dataset", str(src), "--out", str(tmp_path / "run")]
    args += ["--config", str(tmp_path / "cfg.toml"), "--json"]
    assert main([*args, "--frames", "0:6"]) == 0  # stopped after time 5 ...
    capsys.readouterr()
    said = [r.getMessage() for r in caplog.records if "cam1's view" in r.getMessage()]
    caplog.clear()
    assert main([*args, "--frames", "0:8", "--resume"]) == 0  # ... and resumed
    result = json.loads(capsys.readouterr().out)
    assert len(said) == 4 and "keeps moving" in said[3] and "turned back" in said[3]
    # After the stop it goes on being turned back, its moves not said again.
    resumed = [r.getMessage() for r in caplog.records]
    assert not any("cam1's view" in m for m in resumed)
    assert sum("cam1 kept moving before the stop" in m for m in resumed) == 1
    # Turned back from its first move on (a knock's as a sway's).
    taken = [t["stabilised"] for t in result["tasks"]]
    assert taken[:1] == [{}]
    assert all(list(k) == ["cam1"] for k in taken[1:])
    assert all(k["cam1"] == pytest.approx(1.5, abs=0.15) for k in taken[1:])
    summary = result["summary"]["stabilised"]["cam1"]
    assert summary["tasks"] == 7 and summary["unmeasured"] == 0
    assert not (tmp_path / "run" / "rig.repaired.json").exists()
    assert summary["max_deg"] == pytest.approx(1.5, abs=0.15)


def test_a_camera_knocked_mid_run_is_said_turned_back_and_re_aimed_at_the_end(
    tiny_dataset, tmp_path, caplog, capsys, monkeypatch
):
    """cam1 knocked (turned 2 degrees) at time 3 of 8, everything on, the calibration checked
    at the default ``calib_check_s`` (60 s: not again within this run after its first):
    the session sees cam1's view move from its frames (``MovedCameras``), says so once, and
    from then on turns its frames back onto its view before the move (the tasks record 2
    degrees taken off); the back-end checks the frames from then on (time 5: those of 3
    and 4 went in as they came) at once, and they fit; the run ends with the rig whose cam1 is re-aimed by the turn taken
    off in ``rig.repaired.json`` (within 0.2 degrees of the knock)."""
    from edgerecon.cli import main
    from edgerecon.io.calibration import load_rig
    from tests.quality.test_calibration import angle_deg

    src = tmp_path / "scene"
    shutil.copytree(tiny_dataset, src)
    _knock(src, 1, range(3, 8))
    (tmp_path / "cfg.toml").write_text("[runtime]\ndeadline_s = 20.0\n")
    dense = edgerecon.pipeline.reconstruct_foreground
    calls = []

    def checked():  # the back-end's check of the frames turned back: they fit
        for r in caplog.records:
            m = re.search(r"calibration fits the frames: .* \(times? ([0-9, ]+)\)", r.getMessage())
            if m and max(int(x) for x in m[1].split(",")) >= 5:
                return True
        return False

    def slow(*args, **kwargs):  # the tasks after the move wait for the back-end's verdict
        calls.append(1)
        time.sleep(0.5)
        if len(calls) >= 7 and not checked():
            wait_until(checked, timeout=40)
        return dense(*args, **kwargs)

    monkeypatch.setattr(edgerecon.pipeline, "reconstruct_foreground", slow)
    caplog.set_level(logging.WARNING)
    caplog.set_level(logging.INFO, logger="edgerecon.quality.calibration")
    out = tmp_path / "run"
    args = ["run", "--dataset", str(src), "--out", str(out), "--config", str(tmp_path / "cfg.toml")]
    assert main([*args, "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert [t["time_index"] for t in result["tasks"]] == list(range(8))
    moved = [r.getMessage() for r in caplog.records if "view moved" in r.getMessage()]
    assert len(moved) == 1 and "time 5: cam1's view moved at time 3" in moved[0]
    assert "From now on its frames are turned back onto its view before the move" in moved[0]
    (move,) = result["summary"]["camera_moves"]
    assert move["camera"] == "cam1" and move["time_index"] == 3 and move["seen_at"] == 5
    assert move["turn_deg"] == pytest.approx(2.0, abs=0.3)
    moves = [[m["camera"] for m in t["camera_moves"]] for t in result["tasks"]]
    assert moves == [[]] * 5 + [["cam1"]] + [[]] * 2
    taken = [t["stabilised"] for t in result["tasks"]]
    assert taken[:5] == [{}] * 5
    assert all(k["cam1"] == pytest.approx(2.0, abs=0.15) for k in taken[5:])
    assert checked()
    verdict = result["summary"]["calibration"]
    assert verdict["fits"] is True and min(verdict["times"]) >= 5  # turned back only
    assert verdict["repaired_rig_file"] == "rig.repaired.json"
    turn = re.match(r"cam1 re-aimed by ([0-9.]+) degrees \(the turn taken off", verdict["repair"])
    assert turn is not None and float(turn[1]) == pytest.approx(2.0, abs=0.15)
    repaired = load_rig(out / "rig.repaired.json")
    rig = open_dataset(src).rig
    dR = cv2.Rodrigues(np.radians(2.0) * np.array([1.0, 0.0, 0.0]))[0]
    expected = dataclasses.replace(rig[1], R=dR @ rig[1].R, t=dR @ rig[1].t)
    assert angle_deg(repaired[1], expected) < 0.2
    assert np.allclose(repaired[1].center, rig[1].center, atol=1e-6)
    assert all(angle_deg(repaired[i], rig[i]) < 1e-6 for i in (0, 2, 3, 4))


def test_a_knocked_camera_turned_back_goes_on_so_after_resume_and_is_re_aimed_at_the_end(
    tiny_dataset, tmp_path, caplog, capsys
):
    """cam1 knocked (2 degrees) at time 3, seen there (``moved_after_frames`` 1) and turned
    back from then on; the run stopped after time 4 and resumed: its frames go on being
    turned back from the first resumed task (``views.npz`` keeps its view and that it was
    knocked once, not swaying), and the resumed run ends with cam1 re-aimed by the turn in
    ``rig.repaired.json``."""
    from edgerecon.cli import main
    from edgerecon.io.calibration import load_rig
    from tests.quality.test_calibration import angle_deg

    src = tmp_path / "scene"
    shutil.copytree(tiny_dataset, src)
    _knock(src, 1, range(3, 8))
    (tmp_path / "cfg.toml").write_text(
        "[runtime]\ndeadline_s = 20.0\n[runtime.frame_check]\nmoved_after_frames = 1\n"
    )
    caplog.set_level(logging.WARNING)
    out = tmp_path / "run"
    args = ["run", "--dataset", str(src), "--out", str(out)]
    args += ["--config", str(tmp_path / "cfg.toml"), "--json"]
    assert main([*args, "--frames", "0:5"]) == 0  # stopped after time 4 ...
    first = json.loads(capsys.readouterr().out)
    assert [t["stabilised"] for t in first["tasks"]][3:] == [
        {"cam1": pytest.approx(2.0, abs=0.15)}
    ] * 2
    caplog.clear()
    assert main([*args, "--frames", "0:8", "--resume"]) == 0  # ... and resumed
    result = json.loads(capsys.readouterr().out)
    said = [r.getMessage() for r in caplog.records]
    assert sum("cam1 was knocked before the stop" in m for m in said) == 1
    assert not any("cam1's view" in m for m in said)
    taken = [t["stabilised"] for t in result["tasks"]]
    assert all(k["cam1"] == pytest.approx(2.0, abs=0.15) for k in taken[3:])
    assert result["summary"]["calibration"]["repaired_rig_file"] == "rig.repaired.json"
    rig = open_dataset(src).rig
    dR = cv2.Rodrigues(np.radians(2.0) * np.array([1.0, 0.0, 0.0]))[0]
    expected = dataclasses.replace(rig[1], R=dR @ rig[1].R, t=dR @ rig[1].t)
    assert angle_deg(load_rig(out / "rig.repaired.json")[1], expected) < 0.2
