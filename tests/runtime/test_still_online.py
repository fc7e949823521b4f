"""The online system's still foreground: the back-end's snapshot reaches the front-end, whose
tasks densify only what changed since (scene.still)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from edgerecon.runtime.backend import still_snapshot
from edgerecon.runtime.frontend import FixedController, FrontEnd
from edgerecon.scene.still import StillSnapshot
from tests.runtime.conftest import run_frames, runtime_config


def test_a_task_on_unchanged_frames_keeps_the_snapshot_and_densifies_little(tiny):
    ds, scene = tiny
    config = runtime_config()
    cams = tuple(range(len(ds.rig)))
    fe = FrontEnd(ds.rig, config, FixedController(1.0, cams), scene.tracker(ds.rig))
    works = []
    with ds.open_frames() as src:
        frames, later = src.read(3), src.read(7)
    first = fe.run_task(frames, fe.next_plan(3), works.append, time.sleep, task=0)
    assert first.metrics.status == "ok" and first.metrics.still_share is None
    assert first.metrics.num_still_points == 0
    # The back-end's snapshot of that time (its own function, as a rebuild runs it).
    snap = still_snapshot(ds.rig, config, frames, works[0].foreground)
    assert isinstance(snap, StillSnapshot) and snap.time_index == 3 and len(snap.cloud) > 100
    assert fe.snapshots_received == 0
    fe.push_background(snap)
    assert fe.still is not None and fe.still.snapshot_time == 3
    assert fe.snapshots_received == 1  # what the run's summary reports (snapshots_pushed)
    # The same frames again: everything is still, the snapshot's points are the foreground.
    again = fe.run_task(frames, fe.next_plan(3), works.append, time.sleep, task=1)
    m = again.metrics
    assert m.status == "ok" and m.still_share is not None and m.still_share > 0.95
    assert m.num_still_points > 0.8 * len(snap.cloud)
    assert m.num_fg_points >= m.num_still_points
    assert again.foreground is not None and (again.foreground.labels > 0).all()
    # Four frames later the actors have walked: they are densified again.
    moved = fe.run_task(later, fe.next_plan(7), works.append, time.sleep, task=2)
    mm = moved.metrics
    assert mm.status == "ok" and mm.num_fg_points > 0
    assert mm.still_share is None or mm.still_share < 0.9
    assert mm.num_still_points < m.num_still_points


def test_without_still_foreground_the_rebuilds_make_no_snapshot_and_tasks_densify_all(tiny):
    ds, scene = tiny
    config = runtime_config(still=None)
    with ds.open_frames() as src:
        frames = src.read(3)
    fg = scene.tracker(ds.rig).segment(frames)
    assert still_snapshot(ds.rig, config, frames, fg) is None
    fe = FrontEnd(ds.rig, config, FixedController(1.0, (0, 1, 2)), scene.tracker(ds.rig))
    assert fe.still is None and fe.snapshots_received == 0
    out = fe.run_task(frames, fe.next_plan(3), lambda w: None, time.sleep, task=0)
    assert out.metrics.still_share is None and "still" not in out.metrics.stages


def test_a_run_with_snapshots_has_every_task_and_no_stray_points(tiny, tmp_path):
    # Everything on (background rebuilds with their snapshots): a pause after the second
    # task lets the back-end's first rebuilds arrive; the tasks after it may reuse them.
    def pause(m) -> None:
        if m.task == 1:
            time.sleep(8.0)

    summary, metrics = run_frames(tiny, tmp_path, 0, 8, runtime_config(), on_task=pause)
    assert summary.tasks == 8 and summary.failed == 0
    reused = [m.still_share for m in metrics if m.still_share is not None]
    assert summary.still_tasks == len(reused)
    if reused:
        assert summary.avg_still_share == pytest.approx(np.mean(reused), abs=1e-4)
        assert summary.snapshots_pushed >= 1
    for m in metrics:
        assert m.num_still_points <= m.num_fg_points
        if m.still_share is None:
            assert m.num_still_points == 0
    assert np.isfinite([m.critical_path_s for m in metrics]).all()


def test_the_back_end_makes_fewer_snapshots_while_no_task_uses_them(tiny):
    from edgerecon.runtime.backend import BackEnd

    ds, _ = tiny
    be = BackEnd(ds.rig, runtime_config(background_process=False))
    made = []

    def cycle(t: int, uses: int | None) -> bool:
        # A rebuild: the front-end's newest report on the last snapshot, then the decision.
        last = be._snap_time
        be._still_report = None if last is None or uses is None else (last, uses)
        due = be._snapshot_due()
        if due:
            be._snap_time, be._snap_judged = t, False
            made.append(t)
        return due

    assert cycle(0, None)  # the first rebuild makes one
    assert [cycle(t, 0) for t in range(1, 16)] == [
        False, True,  # not used: every 2nd rebuild
        False, False, False, True,  # still not: every 4th
        *[False] * 7, True,  # then every 8th, at most
        False,
    ]  # fmt: skip
    # Once a snapshot is used, every rebuild makes one again.
    assert [cycle(t, 3) for t in range(16, 30)].count(False) <= 7
    assert all(cycle(t, 2) for t in range(30, 34))
    assert be.stats["snapshots_skipped"] > 0


def test_a_still_plan_that_raises_leaves_the_task_whole(tiny, monkeypatch, caplog):
    # The still foreground is an optimisation: when it fails the task densifies its whole
    # foreground (one warning), it does not fail.
    ds, scene = tiny
    config = runtime_config()
    fe = FrontEnd(ds.rig, config, FixedController(1.0, (0, 1, 2, 3, 4)), scene.tracker(ds.rig))
    works = []
    with ds.open_frames() as src:
        frames = src.read(3)
    fe.run_task(frames, fe.next_plan(3), works.append, time.sleep, task=0)
    fe.push_background(still_snapshot(ds.rig, config, frames, works[0].foreground))

    def broken(*args, **kw):
        raise ValueError("a bug in the comparison")

    monkeypatch.setattr("edgerecon.scene.still.plan_still", broken)
    outs = [fe.run_task(frames, fe.next_plan(3), works.append, time.sleep, task=k) for k in (1, 2)]
    for out in outs:
        assert out.metrics.status == "ok" and out.metrics.still_share is None
        assert out.metrics.num_fg_points > 0
    assert sum("still foreground failed" in r.getMessage() for r in caplog.records) == 1
