"""The online system on live MJPEG streams (loopback): sync spread per task, a stalled
camera left out of tasks and back once it returns."""

from __future__ import annotations

import pytest

from edgerecon.io.dataset import open_dataset
from edgerecon.io.mjpeg import serve_dataset
from edgerecon.runtime import FrameRange, RuntimeConfig, SessionOptions, run_online


@pytest.mark.slow
def test_online_run_on_three_live_streams_with_a_stall(tiny_dataset, tmp_path, monkeypatch):
    import edgerecon.runtime.online as online
    from edgerecon.runtime.memory import MMAP_THRESHOLD

    tuned: list[dict] = []  # (this test process's malloc left as it is)
    monkeypatch.setattr(online, "tune_malloc", lambda **kw: tuned.append(kw))
    server = serve_dataset(
        tiny_dataset,
        tmp_path / "live",
        cameras=[0, 1, 3],
        fps=10.0,
        stamp_ticks=False,
        stream_options={"sync_tolerance_s": 0.05, "stall_s": 0.8, "max_wait_s": 1.0},
    )
    stalled_at: list[int] = []

    def on_task(m):
        if m.task == 1:  # cam3 (stream index 2) stops for 3 s from now
            server.add_stall(2, 0.0, 3.0)
            stalled_at.append(m.task)

    try:
        ds = open_dataset(tmp_path / "live")
        assert ds.is_live and len(ds.rig) == 3
        # Everything on, background rebuilds included, while a camera stalls and returns.
        config = RuntimeConfig(deadline_s=5.0, golden_timeout_s=20.0, background_scale=0.5)
        options = SessionOptions(policy="newest", duration_s=10.0, frames=FrameRange(start=0))
        summary, metrics = run_online(
            ds, config, options, tmp_path / "run", fixed=(1.0, None), on_task=on_task
        )
    finally:
        server.stop()
    assert stalled_at == [1]
    assert {"mmap_threshold": MMAP_THRESHOLD} in tuned  # a live run is a long one
    assert [m.time_index for m in metrics] == list(range(len(metrics)))
    ok = [m for m in metrics if m.status == "ok"]
    assert ok[0].task == 0 and ok[0].camera_ids == [0, 1, 2]
    # Every task with frames reports its spread, within the tolerance.
    assert all(m.sync_spread_s is not None and m.sync_spread_s <= 0.05 for m in ok)
    # While cam3 stalls it is left out (a task needs 3 cameras: those tasks fail, recorded,
    # and the run goes on); afterwards it is back.
    without = [m for m in metrics if m.status != "ok" or 2 not in m.camera_ids]
    assert without, "the stall never reached a task"
    assert any(m.status == "ok" and m.camera_ids == [0, 1, 2] for m in metrics[without[-1].task :])
    stream = summary.stream
    # cam3 stalled once and came back; while it was away no set had the 3 cameras a task
    # needs (each read gave up after max_wait_s: the task recorded failed).
    assert stream["stalls"] == 1 and stream["returns"] == 1
    assert stream["no_set"] >= 1 and stream["sets"] >= len(ok)
    assert stream["frames_dropped"] > 0 and summary.frames_dropped == stream["frames_dropped"]
    assert stream["sync_spread_max_s"] <= 0.05
