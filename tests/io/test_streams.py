"""Live streams from a loopback MJPEG server: newest frames, synchronization, stalls."""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest

from edgerecon.io.dataset import open_dataset, write_dataset_descriptor
from edgerecon.io.frames import FrameSpec
from edgerecon.io.mjpeg import MjpegServer, read_stamp, solid_frames, stamp
from edgerecon.io.streams import LIVE_FRAMES, StreamConfig, StreamFrameSource, best_group
from edgerecon.types import CalibrationError, DataError
from tests.conftest import ring_rig

W, H = 160, 120
FPS = 10.0


def test_stamps_survive_jpeg():
    import cv2

    image = np.full((H, W, 3), 90, np.uint8)
    for tick in (0, 1, 1234, 65535):
        _, buf = cv2.imencode(".jpg", stamp(image, tick), [cv2.IMWRITE_JPEG_QUALITY, 80])
        assert read_stamp(cv2.imdecode(buf, cv2.IMREAD_COLOR)) == tick


def test_best_group_is_the_largest_then_newest_window():
    assert best_group({0: 1.00, 1: 1.01, 2: 1.02}, 0.05) == [0, 1, 2]
    assert best_group({0: 1.00, 1: 1.01, 2: 1.30}, 0.05) == [0, 1]
    assert best_group({0: 1.00, 1: 1.30, 2: 1.60}, 0.05) == [2]  # all single: the newest
    assert best_group({0: 1.00, 1: 1.04, 2: 1.08}, 0.05) == [1, 2]  # two pairs: the newer
    assert best_group({}, 0.1) == []


def test_stream_config_is_validated():
    with pytest.raises(ValueError, match="stall_s"):
        StreamConfig(stall_s=0)
    assert StreamConfig().tolerance(25.0) == pytest.approx(0.04)
    assert StreamConfig(sync_tolerance_s=0.01).tolerance(25.0) == 0.01


def _source(server: MjpegServer, **config) -> StreamFrameSource:
    config.setdefault("sync_tolerance_s", 0.05)
    config.setdefault("stall_s", 0.6)
    config.setdefault("max_wait_s", 0.5)
    config.setdefault("min_cameras", 2)
    urls = {name: server.url(name) for name in server.camera_names}
    return StreamFrameSource(urls, fps=FPS, config=StreamConfig(**config))


def test_newest_synchronized_frames_and_a_stalled_camera_that_rejoins(caplog):
    names = ["cam0", "cam1", "cam2"]
    server = MjpegServer(
        solid_frames(W, H), names, fps=FPS, stalls={2: [(2.0, 4.0)]}, stamp_ticks=True
    ).start()
    caplog.set_level(logging.WARNING, logger="edgerecon.io.streams")
    try:
        with _source(server) as source:
            assert source.num_frames == LIVE_FRAMES
            records = []
            t = 0
            while time.monotonic() - server.start_time < 6.0:
                frames = source.read(t)
                elapsed = time.monotonic() - server.start_time
                ticks = [None if im is None else read_stamp(im) for im in frames.images]
                records.append((elapsed, ticks, frames.sync_spread_s))
                t += 1
                time.sleep(0.15)  # a task's work: frames keep arriving meanwhile
            stats = source.stats()
    finally:
        server.stop()
    assert len(records) > 15
    same = 0
    for elapsed, ticks, spread in records:
        got = [k for k in ticks if k is not None]
        # Synchronized: the cameras' frames are from the same tick (10 fps, 50 ms tolerance);
        # capture time is arrival time, so on a loaded machine a frame that arrives 50 ms
        # late can pass for the next tick's: never more than one tick apart.
        same += len(set(got)) == 1
        assert max(got) - min(got) <= 1, (elapsed, ticks)
        assert spread is not None and spread <= 0.05
        # Newest: the tick is at most a frame interval (plus the read) behind the clock.
        assert elapsed * FPS - max(got) < 3.0, (elapsed, ticks)
    assert same >= 0.85 * len(records)
    # cam2 is in every set before its stall, absent while it lasts (after stall_s), and back
    # after it (once its reader reconnected).
    assert all(ticks[2] is not None for e, ticks, _ in records if 0.8 < e < 2.0)
    assert all(ticks[2] is None for e, ticks, _ in records if 2.8 < e < 4.0)
    assert all(ticks[2] is not None for e, ticks, _ in records if e > 5.2)
    assert all(ticks[0] is not None and ticks[1] is not None for _, ticks, _ in records)
    stalled = [r for r in caplog.records if "left out of tasks" in r.getMessage()]
    back = [r for r in caplog.records if "is back" in r.getMessage()]
    assert len(stalled) == 1 and "cam2" in stalled[0].getMessage()
    assert len(back) == 1
    assert stats["left_out_stalled"] > 0 and stats["frames_dropped"] > stats["sets"]
    assert stats["stalls"] == 1 and stats["returns"] == 1
    assert stats["stalled"] == {"cam0": False, "cam1": False, "cam2": False}


def test_a_lagging_camera_is_waited_for_then_left_out(caplog):
    # cam1 sends only every third tick: most sets wait for it, some leave it out.
    names = ["cam0", "cam1"]
    server = MjpegServer(solid_frames(W, H), names, fps=FPS, stamp_ticks=True).start()
    lag = [(k / FPS + 0.01, (k + 2) / FPS + 0.01) for k in range(0, 200, 3)]
    server.stalls[1] = lag
    try:
        with _source(server, stall_s=2.0, max_wait_s=0.15, min_cameras=1) as source:
            sets = [source.read(t) for t in range(12)]
            stats = source.stats()
    finally:
        server.stop()
    for frames in sets:
        got = [read_stamp(im) for im in frames.images if im is not None]
        assert max(got) - min(got) <= 1
    assert stats["waited"] > 0
    assert stats["left_out_of_sync"] > 0  # after max_wait_s the lagging camera was left out
    assert stats["left_out_of_sync"] < 12


def test_stream_dataset_descriptor(tmp_path):
    rig = ring_rig(3, width=W, height_px=H)
    server = MjpegServer(solid_frames(W, H), rig.names, fps=FPS).start()
    try:
        frames = {
            "kind": "stream",
            "cameras": {n: server.url(n) for n in rig.names},
            "sync_tolerance_s": 0.03,
            "stall_s": 1.5,
        }
        write_dataset_descriptor(tmp_path / "live", rig=rig, frames=frames, fps=FPS)
        ds = open_dataset(tmp_path / "live")
        assert ds.is_live and ds.to_dict()["num_frames"] is None
        assert ds.frames.kind == "stream" and ds.frames.stream is not None
        assert ds.frames.stream.sync_tolerance_s == 0.03 and ds.frames.stream.stall_s == 1.5
        with ds.open_frames(missing="error") as source:
            first = source.read(0)
            assert all(im is not None and im.shape == (H, W, 3) for im in first.images)
        # A calibration of another size is found when the dataset is opened.
        big = ring_rig(3, width=2 * W, height_px=2 * H)
        write_dataset_descriptor(tmp_path / "big", rig=big, frames=frames, fps=FPS)
        with pytest.raises(CalibrationError, match="calibration"):
            open_dataset(tmp_path / "big")
    finally:
        server.stop()
    # Nothing serves: the dataset cannot be opened, and says which streams.
    spec = FrameSpec(
        kind="stream",
        cameras=tuple((n, f"http://127.0.0.1:9/{n}") for n in rig.names),
        stream=StreamConfig(open_timeout_s=1.0),
    )
    write_dataset_descriptor(tmp_path / "dead", rig=rig, frames=spec, fps=FPS)
    with pytest.raises(DataError, match="no camera stream delivered"):
        open_dataset(tmp_path / "dead")


def test_check_never_raises_and_names_who_is_missing():
    names = ["cam0", "cam1", "cam2"]
    server = MjpegServer(solid_frames(W, H), names, fps=FPS, stalls={2: [(0.0, 60.0)]}).start()
    try:
        with _source(server, open_timeout_s=4.0) as source:
            frames, problems = source.check(0)
            assert frames.images[2] is None and frames.images[0] is not None, problems
            assert set(problems) == {"cam2"}
            assert source.frame_counts["cam0"] >= 1 and source.frame_counts["cam2"] == 0
    finally:
        server.stop()
    # A set without a frame reports no spread from it.
    from edgerecon.types import FrameSet

    fs = FrameSet(time_index=0, images=(frames.images[0], None), capture_times_s=(10.0, 5.0))
    assert fs.sync_spread_s == 0.0


def test_mjpeg_http_reader_parts_without_length_auth_and_other_content():
    import threading
    from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

    import cv2

    from edgerecon.io.mjpeg import MjpegHttpCapture

    jpeg = cv2.imencode(".jpg", stamp(np.full((H, W, 3), 90, np.uint8), 77))[1].tobytes()
    seen = {}

    class Handler(BaseHTTPRequestHandler):
        def log_message(self, *args):
            pass

        def do_GET(self):
            seen["auth"] = self.headers.get("Authorization")
            if self.path == "/video.mp4":
                self.send_response(200)
                self.send_header("Content-Type", "video/mp4")
                self.end_headers()
                return
            if self.path != "/mjpg":
                self.send_error(404)
                return
            self.send_response(200)
            self.send_header("Content-Type", 'multipart/x-mixed-replace;boundary="--myb"')
            self.end_headers()
            for _ in range(3):  # parts without Content-Length
                self.wfile.write(b"--myb\r\nContent-Type: image/jpeg\r\n\r\n" + jpeg + b"\r\n")
            self.wfile.write(b"--myb--\r\n")

    httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    base = f"127.0.0.1:{httpd.server_address[1]}"
    try:
        cap = MjpegHttpCapture(
            f"http://me:se%20cret@{base}/mjpg", open_timeout_s=5, read_timeout_s=5
        )
        assert cap.isOpened()
        ticks = []
        while cap.grab():
            ok, image = cap.retrieve()
            assert ok and image.shape == (H, W, 3)
            ticks.append(read_stamp(image))
        assert ticks == [77, 77, 77]  # every part, the closing boundary ends the stream
        cap.release()
        import base64

        assert seen["auth"] == "Basic " + base64.b64encode(b"me:se cret").decode()
        other = MjpegHttpCapture(f"http://{base}/video.mp4", open_timeout_s=5, read_timeout_s=5)
        assert not other.isOpened() and other.not_mjpeg  # FFmpeg's turn
        missing = MjpegHttpCapture(f"http://{base}/nope", open_timeout_s=5, read_timeout_s=5)
        assert not missing.isOpened() and not missing.not_mjpeg and "404" in missing.error
    finally:
        httpd.shutdown()
        httpd.server_close()
