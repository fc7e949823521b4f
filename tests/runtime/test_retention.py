"""What a long run keeps on disk: the newest task clouds within a count and the free space
(``runtime.retention``), on fabricated folders and in whole runs with everything on."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from edgerecon.runtime.frontend import FrontEnd
from edgerecon.runtime.retention import CloudRetention, RetentionConfig
from edgerecon.runtime.state import BACKGROUNDS, TASK_DROPPED, TASK_FOREGROUND, task_dir
from edgerecon.viewer.rundir import RunFolder, has_task_cloud
from tests.runtime.conftest import run_frames, runtime_config, wait_until


def _task(root: Path, t: int, size: int = 1000) -> None:
    d = task_dir(root, t)
    d.mkdir(parents=True)
    (d / TASK_FOREGROUND).write_bytes(b"x" * size)
    (d / TASK_DROPPED).write_bytes(b"y" * 10)


def _background(root: Path, version: tuple[int, int], size: int = 5000) -> None:
    (root / BACKGROUNDS).mkdir(exist_ok=True)
    (root / BACKGROUNDS / f"v{version[0]}.{version[1]}.ply").write_bytes(b"z" * size)


def _backgrounds(root: Path) -> set[str]:
    return {p.name for p in (root / BACKGROUNDS).glob("*.ply")}


def _tasks(root: Path) -> list[int]:
    return sorted(int(p.name) for p in (root / "tasks").iterdir())


def test_the_count_keeps_the_newest_clouds_and_their_backgrounds(tmp_path):
    kept = CloudRetention(tmp_path, RetentionConfig(keep_clouds=2, min_free_mb=0))
    versions = [(1, 1), (1, 1), (1, 2), (1, 2), (1, 3)]
    for t, v in enumerate(versions):
        _background(tmp_path, v)
        _task(tmp_path, t)
        assert kept.make_room(v, None, cloud=True)
        kept.cloud_written(t, v)
        kept.committed(v)
        assert len(kept.kept) == min(t + 1, 2)
    assert _tasks(tmp_path) == [3, 4] and kept.kept == [3, 4]
    # v1.1 is gone with its last task; v1.2 is still referenced by task 3; v1.3 the newest.
    assert _backgrounds(tmp_path) == {"v1.2.ply", "v1.3.ply"}
    assert kept.pruned == 3 and kept.skipped == 0
    # A resumed run takes up the clouds on disk (a task whose cloud is gone is not kept).
    again = CloudRetention(
        tmp_path, RetentionConfig(keep_clouds=2, min_free_mb=0), list(enumerate(versions))
    )
    assert again.kept == [3, 4]


def test_low_disk_removes_old_clouds_then_skips_new_ones_never_the_newest(tmp_path, caplog):
    capacity = [0]

    def free(path):
        used = sum(p.stat().st_size for p in Path(path).rglob("*") if p.is_file())
        return capacity[0] - used

    mib = 2**20
    config = RetentionConfig(min_free_mb=1.0)
    kept = CloudRetention(tmp_path, config, disk_free=free)
    capacity[0] = mib + 10_000  # room for the floor and about 9 task clouds of 1010 bytes
    for t in range(20):
        v = (1, 1 + t // 5)
        new_bg = t % 5 == 0
        room = kept.make_room(v, 100 if new_bg else None, cloud=True)
        if new_bg:
            _background(tmp_path, v, size=3200)
            kept.background_written(v, 100)
        if room:
            _task(tmp_path, t)
            kept.cloud_written(t, v)
        kept.committed(v)
        assert free(tmp_path) >= 0
    assert kept.skipped == 0 and kept.pruned > 0
    # The newest clouds are on disk, contiguous up to the last task; the backgrounds they
    # refer to and the newest are kept, the others were removed first.
    on_disk = _tasks(tmp_path)
    assert on_disk == kept.kept == list(range(20 - len(on_disk), 20)) and len(on_disk) >= 2
    assert _backgrounds(tmp_path) == {f"v1.{1 + t // 5}.ply" for t in on_disk}
    # The disk shrinks under the floor: clouds go down to the newest one, then new ones are
    # not written; the newest stays for the viewer.
    capacity[0] = mib + 2_000
    for _ in range(20, 24):
        room = kept.make_room((1, 4), None, cloud=True)
        assert not room
        kept.committed((1, 4))
    assert kept.kept == [19] and _tasks(tmp_path) == [19] and kept.skipped == 4
    # Said once each, not every task.
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert sum("oldest task clouds are removed" in w for w in warned) == 1
    assert sum("not written until there is room" in w for w in warned) == 1
    # Room again: written again.
    capacity[0] = 10 * mib
    assert kept.make_room((1, 4), None, cloud=True)


def test_retention_settings_are_checked():
    with pytest.raises(ValueError, match="keep_clouds"):
        RetentionConfig(keep_clouds=0)
    with pytest.raises(ValueError, match="min_free_mb"):
        RetentionConfig(min_free_mb=-1)


@pytest.fixture
def pushes(monkeypatch):
    """The versions of the backgrounds the front-end takes, as it takes them."""
    taken = []
    real_push = FrontEnd.push_background

    def push(self, update):
        taken.append(update.version)
        return real_push(self, update)

    monkeypatch.setattr(FrontEnd, "push_background", push)
    return taken


def test_a_run_keeps_the_newest_clouds_across_a_resume(tiny, tmp_path, pushes):
    # Everything on (background rebuilds included): backgrounds arrive between tasks, tasks
    # refer to several versions, and only the newest clouds and what they refer to stay.

    def slow(m):  # frames arrive slowly after these tasks: the back-end pushes a background
        if m.task in (0, 3):
            count = len(pushes)
            assert wait_until(lambda: len(pushes) > count or (m.task == 0 and pushes))

    fixed = (0.8, None)
    summary, metrics = run_frames(
        tiny,
        tmp_path,
        0,
        6,
        runtime_config(),
        fixed=fixed,
        on_task=slow,
        retention=RetentionConfig(keep_clouds=2),
    )
    assert all(m.status == "ok" and m.cloud_written for m in metrics)
    assert _tasks(tmp_path) == [4, 5]
    assert (summary.clouds_written, summary.clouds_kept, summary.clouds_skipped) == (6, 2, 0)
    versions = {(m.bg_epoch, m.bg_version) for m in metrics if m.bg_version}
    assert len(versions) >= 2  # a version was removed with its tasks, or kept as the newest
    kept_versions = {(m.bg_epoch, m.bg_version) for m in metrics[4:]} | {max(versions)}
    assert _backgrounds(tmp_path) == {f"v{e}.{c}.ply" for e, c in kept_versions if c}
    run = RunFolder(tmp_path)
    run.poll()
    assert [m.time_index for m in run.tasks] == list(range(6))  # every metrics line stays
    for m in metrics:
        cloud = run.cloud(m.time_index)
        if m.time_index < 4:
            assert cloud is None and not has_task_cloud(tmp_path, m.time_index)
        else:
            assert cloud is not None and len(cloud) == m.num_merged_points
            np.testing.assert_array_equal(cloud.attributes["bg_version"], m.bg_version)
    assert run.newest_with_cloud().time_index == 5
    # --resume goes on with the clouds on disk.
    summary, metrics = run_frames(
        tiny,
        tmp_path,
        0,
        8,
        runtime_config(),
        fixed=fixed,
        resume=True,
        retention=RetentionConfig(keep_clouds=2),
    )
    assert len(metrics) == 8 and all(m.status == "ok" for m in metrics)
    assert _tasks(tmp_path) == [6, 7]
    assert (summary.clouds_written, summary.clouds_kept) == (8, 2)
    for m in metrics[6:]:
        assert RunFolder(tmp_path).cloud(m.time_index) is not None


def test_a_run_on_a_full_disk_goes_on_and_keeps_the_newest_cloud(
    tiny, tmp_path, monkeypatch, pushes
):
    # A disk that fills up: the run ends with every task recorded, the newest cloud on disk.
    import edgerecon.runtime.retention as retention

    out = tmp_path / "run"
    capacity = [10 * 2**30]

    def free(path):
        used = sum(p.stat().st_size for p in Path(out).rglob("*") if p.is_file())
        return capacity[0] - used

    monkeypatch.setattr(retention, "free_bytes", free)

    def fill(m):
        if m.task == 1:  # from now on the disk holds the floor and little else
            used = 2**30 * 10 - free(out)
            capacity[0] = used + 2**20 + 1000
            # A background arrives while the disk is short: it is written (--resume).
            assert wait_until(lambda: bool(pushes))

    summary, metrics = run_frames(
        tiny,
        out,
        0,
        6,
        runtime_config(),
        fixed=(0.8, None),
        on_task=fill,
        retention=RetentionConfig(min_free_mb=1.0),
    )
    assert len(metrics) == 6 and all(m.status == "ok" for m in metrics)
    assert metrics[0].cloud_written and metrics[1].cloud_written
    assert summary.clouds_skipped == sum(m.cloud_skipped for m in metrics) >= 1
    assert summary.clouds_kept == 1
    newest = RunFolder(out)
    newest.poll()
    last = newest.newest_with_cloud()
    assert last is not None and newest.cloud(last.time_index) is not None
    assert (out / "summary.json").exists() and (out / "background.ply").exists()
    held = max((m.bg_epoch, m.bg_version) for m in metrics)
    assert held[1] >= 1 and f"v{held[0]}.{held[1]}.ply" in _backgrounds(out)


def test_run_totals_are_the_summary_of_every_record():
    from edgerecon.runtime.messages import TaskMetrics
    from edgerecon.runtime.session import RunTotals

    rng = np.random.default_rng(3)
    records = []
    for k in range(40):
        status = "failed" if k % 11 == 5 else "ok"
        m = TaskMetrics(task=k, time_index=k, status=status)
        if status == "ok":
            m.phase = "search" if k < 8 else "adjust"
            m.scale = float(rng.uniform(0.3, 1.5))
            m.num_cameras = 2 if k == 20 else int(rng.integers(3, 5))
            m.frame_defects = {"cam0": "black"} if k == 20 else {}
            m.camera_ids = list(range(m.num_cameras))
            m.critical_path_s = float(rng.uniform(0.2, 0.8))
            m.deadline_met = m.critical_path_s < 0.5
            m.online_fscore = None if k % 7 == 0 else float(rng.uniform())
            m.search_steps = min(k, 6)
            m.stages = {"scene": 0.1 + 0.01 * k, "dense": 0.2}
            m.degraded = k == 30
            m.cloud_written = k % 3 != 0
        m.sync_spread_s = 0.001 * k
        records.append(m)
    totals = RunTotals()
    for m in records:
        totals.add(m)
    ok = [m for m in records if m.status == "ok"]
    rec = [m for m in ok if not (m.frame_defects and m.num_cameras < 3)]
    adjust = [m for m in rec if m.phase == "adjust"]
    assert (totals.tasks, totals.failed, totals.empty, totals.degraded) == (40, 4, 1, 1)
    assert totals.scale.value == pytest.approx(np.mean([m.scale for m in rec]))
    assert totals.time.value == pytest.approx(np.mean([m.critical_path_s for m in rec]))
    assert totals.adjust_time.value == pytest.approx(np.mean([m.critical_path_s for m in adjust]))
    assert totals.adjust_misses == sum(not m.deadline_met for m in adjust)
    on = [m.online_fscore for m in rec if m.online_fscore is not None]
    assert totals.online.value == pytest.approx(np.mean(on))
    assert totals.cameras_used == rec[-1].camera_ids and totals.search_steps == 6
    assert totals.stages["scene"] == pytest.approx(sum(m.stages["scene"] for m in rec))
    assert totals.clouds_written == sum(m.cloud_written for m in records)
    assert totals.spread_max == pytest.approx(0.039)


def test_a_run_keeps_the_newest_records_in_memory_and_counts_every_one(tiny, tmp_path):
    fixed = (0.8, None)
    whole, _ = run_frames(tiny, tmp_path / "whole", 0, 5, runtime_config(), fixed=fixed)
    summary, metrics = run_frames(
        tiny, tmp_path / "part", 0, 3, runtime_config(), fixed=fixed, keep_metrics=2
    )
    assert [m.time_index for m in metrics] == [1, 2] and summary.tasks == 3
    summary, metrics = run_frames(
        tiny, tmp_path / "part", 0, 5, runtime_config(), fixed=fixed, keep_metrics=2, resume=True
    )
    assert [m.time_index for m in metrics] == [3, 4]
    assert summary.tasks == 5 and summary.failed == 0
    assert summary.clouds_written == whole.clouds_written == 5
    lines = (tmp_path / "part" / "metrics.jsonl").read_text().splitlines()
    assert len(lines) == 5
    assert summary.avg_scale == pytest.approx(whole.avg_scale)
    assert summary.avg_cameras == pytest.approx(whole.avg_cameras)
    assert {"scene", "merge"} <= set(summary.stage_means_s)
