"""Videos at different or variable frame rates are paired by their frames' timestamps."""

from __future__ import annotations

import fractions
import json

import cv2
import numpy as np
import pytest

from edgerecon.io import FrameSpec, VideoFrameSource
from edgerecon.io.frames import probe_video

W, H = 32, 24


def _encode(k: int) -> np.ndarray:
    """A flat frame whose colour encodes its own index ``k`` (< 40,000; survives MJPG)."""
    return np.full((H, W, 3), (8 * (k % 32), 8 * ((k // 32) % 32), 8 * (k // 1024)), np.uint8)


def _decode(image: np.ndarray) -> int:
    b, g, r = (np.round(image[H // 2, W // 2].astype(float) / 8)).astype(int)
    return int(b + 32 * g + 1024 * r)


def _video(path, fps: float, n: int):
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (W, H))
    assert writer.isOpened()
    for k in range(n):
        writer.write(_encode(k))
    writer.release()
    return path


def test_equal_constant_rates_pair_by_index(tmp_path):
    paths = {f"c{i}": _video(tmp_path / f"c{i}.avi", 25.0, 30) for i in range(3)}
    with VideoFrameSource(paths) as src:
        assert src.pairing == "index" and src.fps == 25.0 and src.num_frames == 30
        assert [_decode(im) for im in src.read(17).images] == [17, 17, 17]


def test_different_rates_pair_by_time(tmp_path):
    # A 10 fps camera and a 20 fps one: time index t is 0.1 t seconds, frame 2t of the fast one.
    paths = {
        "slow": _video(tmp_path / "s.avi", 10.0, 20),
        "fast": _video(tmp_path / "f.avi", 20.0, 41),
    }
    paths["slow2"] = _video(tmp_path / "s2.avi", 10.0, 22)
    with VideoFrameSource(paths) as src:
        assert src.pairing == "time" and src.fps == pytest.approx(10.0)
        assert src.num_frames == 20  # the slow camera's 20 frames; the fast one has 20.5 s x 2
        for t in (0, 1, 7, 19, 3):  # 3 after 19: a read back restarts the video
            slow, fast, slow2 = (_decode(im) for im in src.read(t).images)
            assert (slow, fast, slow2) == (t, 2 * t, t)
    # Offsets count the camera's own frames: the fast one starts at its frame 4 (0.2 s).
    spec = FrameSpec(kind="video", cameras=tuple(paths.items()), offsets=(("fast", 4),))
    with spec.open() as src:
        assert [_decode(im) for im in src.read(5).images] == [5, 14, 5]


def test_29_97_against_30_fps_does_not_drift(tmp_path):
    n = 1100
    paths = {
        "a": _video(tmp_path / "a.avi", 30.0, n),
        "b": _video(tmp_path / "b.avi", 30000 / 1001, n),
        "c": _video(tmp_path / "c.avi", 30.0, n),
    }
    with VideoFrameSource(paths) as src:
        assert src.pairing == "time"
        assert src.fps == pytest.approx(30000 / 1001)
        # Time index t is t / 29.97 s: frame t of the 29.97 fps camera, frame round(1.001 t)
        # of the others (index pairing is a frame off from t = 500 on).
        for t in (0, 499, 700, 1000, 1098):
            a, b, c = (_decode(im) for im in src.read(t).images)
            assert b == t and a == c == round(t * 1.001), (t, a, b, c)


def test_variable_frame_rate_video(tmp_path):
    av = pytest.importorskip("av")
    rng = np.random.default_rng(1)
    gaps_ms = rng.choice([17, 33, 33, 33, 50], size=89)
    pts = np.concatenate([[0], np.cumsum(gaps_ms)])  # a phone's uneven frame times (ms)
    path = tmp_path / "vfr.mp4"
    with av.open(str(path), "w") as out:
        stream = out.add_stream("mpeg4", rate=30)
        stream.width, stream.height, stream.pix_fmt = W, H, "yuv420p"
        stream.codec_context.time_base = stream.time_base = fractions.Fraction(1, 1000)
        stream.codec_context.qmax = 2  # flat colours decode within a grey level or two
        for k, p in enumerate(pts):
            frame = av.VideoFrame.from_ndarray(_encode(k)[:, :, ::-1].copy(), format="rgb24")
            frame.pts, frame.time_base = int(p), fractions.Fraction(1, 1000)
            for packet in stream.encode(frame):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    info = probe_video(path)
    np.testing.assert_allclose(info.timestamps_s, pts / 1000.0)
    assert not info.regular
    paths = {
        "vfr": path,
        "b": _video(tmp_path / "b.avi", 30.0, 100),
        "c": _video(tmp_path / "c.avi", 30.0, 100),
    }
    with VideoFrameSource(paths) as src:
        # The slowest camera's mean rate: the variable one's (89 gaps over 2.98 s).
        assert src.pairing == "time" and src.fps == pytest.approx(info.mean_fps)
        assert info.mean_fps is not None and info.mean_fps < 30.0
        for t in range(0, 80, 7):
            time_s = t / src.fps
            nearest = int(np.argmin(np.abs(pts / 1000.0 - time_s)))
            even = int(np.argmin(np.abs(np.arange(100) / 30.0 - time_s)))
            vfr, b, c = (_decode(im) for im in src.read(t).images)
            assert (vfr, b, c) == (nearest, even, even), t


def test_import_says_how_frames_pair(tmp_path, capsys):
    from edgerecon.cli import main
    from edgerecon.io import open_dataset
    from edgerecon.io.calibration import save_rig
    from tests.conftest import ring_rig

    rig = ring_rig(3, width=W, height_px=H, focal_px=30.0)
    save_rig(tmp_path / "rig.json", rig)
    rates = dict(zip(rig.names, (30.0, 60.0, 30.0), strict=True))
    videos = [f"{n}={_video(tmp_path / f'{n}.avi', r, int(r))}" for n, r in rates.items()]
    out = tmp_path / "ds"
    assert main(["import", str(tmp_path / "rig.json"), *videos, "--out", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert any("pairs each camera's frame nearest in time" in n for n in report["notes"])
    with open_dataset(out).open_frames() as src:
        assert src.fps == pytest.approx(30.0) and src.num_frames == 30
        assert [_decode(im) for im in src.read(12).images] == [12, 24, 12]


def test_phone_video_with_rotation_metadata_reads_upright(tmp_path):
    # Phones store portrait video as landscape pixels plus a display rotation: the frames and
    # the probed size are the upright ones (what calibration tools reading the video saw).
    av = pytest.importorskip("av")
    from edgerecon.io.frames import probe_video

    path = tmp_path / "portrait.mp4"
    with av.open(str(path), "w") as out:
        stream = out.add_stream("mpeg4", rate=10)
        stream.width, stream.height, stream.pix_fmt = W, H, "yuv420p"
        stream.set_display_rotation(90)
        for _ in range(5):
            image = np.zeros((H, W, 3), np.uint8)
            image[:8, :12] = 255  # a mark in the stored frame's top-left corner
            for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    info = probe_video(path)
    assert (info.width, info.height) == (H, W)
    with VideoFrameSource({"p": path}) as src:
        frame = src.read(2).images[0]
    assert frame.shape[:2] == (W, H)  # rows, columns: upright portrait


def _stamped(folder, times_ns, index_of) -> None:
    """Image files named by their capture time (ns), each encoding ``index_of(time)``."""
    folder.mkdir(parents=True)
    for ns in times_ns:
        cv2.imwrite(str(folder / f"{ns}.png"), _encode(index_of(ns)))


def test_image_folders_named_by_capture_times_pair_by_time(tmp_path, capsys):
    from edgerecon.io import ImageFolderFrameSource

    t0 = 1_700_000_000_000_000_000  # ns on one clock (ROS time)
    tick = 50_000_000  # 20 Hz
    tick_of = lambda ns: round((ns - t0) / tick)  # noqa: E731 - the encoded moment
    a = [t0 + k * tick for k in range(60)]
    b = [t0 + k * tick + 2_000_000 for k in range(3, 60) if k != 30]  # late, one dropped
    c = [t0 + k * 2 * tick + 1_000_000 for k in range(30)]  # 10 Hz
    for name, times in (("a", a), ("b", b), ("c", c)):
        _stamped(tmp_path / name, times, tick_of)
    with ImageFolderFrameSource({n: tmp_path / n for n in "abc"}) as src:
        assert src.pairing == "time" and src.fps == pytest.approx(10.0, rel=1e-3)
        # Time index t is 0.15 s (b's first frame) + t / 10 s: the moment 3 + 2 t of a's clock.
        for t in (0, 5, 13, 26):
            got = [_decode(im) for im in src.read(t).images]
            assert got[0] == 3 + 2 * t and got[2] in (2 + 2 * t, 4 + 2 * t), (t, got)
            assert got[1] == 3 + 2 * t or (3 + 2 * t == 30 and got[1] in (29, 31)), (t, got)
    # The import says so.
    from edgerecon.cli import main
    from edgerecon.io.calibration import save_rig
    from tests.conftest import ring_rig

    rig = ring_rig(3, width=W, height_px=H, focal_px=30.0)
    save_rig(tmp_path / "rig.json", rig)
    sources = [f"{n}={tmp_path / f}" for n, f in zip(rig.names, "abc", strict=True)]
    out = tmp_path / "ds"
    assert main(["import", str(tmp_path / "rig.json"), *sources, "-o", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert any("named by capture times" in n for n in report["notes"]), report["notes"]
    # Sequence numbers (not times) keep index pairing.
    for name in ("d", "e", "f"):
        (tmp_path / name).mkdir()
        for k in range(5):
            cv2.imwrite(str(tmp_path / name / f"{k:06d}.png"), _encode(k))
    with ImageFolderFrameSource({n: tmp_path / n for n in "def"}) as src:
        assert src.pairing == "index"


def test_hevc_with_b_frames_reads_in_display_order(tmp_path):
    # iPhones record HEVC with B-frames: decoded in display order, timestamps increasing,
    # one constant rate (index pairing), every frame the right one.
    av = pytest.importorskip("av")
    if "libx265" not in av.codecs_available:
        pytest.skip("no HEVC encoder in this PyAV")
    path = tmp_path / "iphone.mov"
    with av.open(str(path), "w") as out:
        stream = out.add_stream("libx265", rate=30, options={"x265-params": "log-level=none"})
        stream.width, stream.height, stream.pix_fmt = W, H, "yuv420p"
        for k in range(40):
            frame = av.VideoFrame.from_ndarray(_encode(k)[:, :, ::-1].copy(), format="rgb24")
            for packet in stream.encode(frame):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    from edgerecon.io.frames import probe_video

    info = probe_video(path)
    assert info.num_frames == 40 and info.regular
    others = {n: _video(tmp_path / f"{n}.avi", 30.0, 40) for n in ("b", "c")}
    with VideoFrameSource({"a": path, **others}) as src:
        assert src.pairing == "index"
        assert [_decode(im) for im in src.read(23).images] == [23, 23, 23]
