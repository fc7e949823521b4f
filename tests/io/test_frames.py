"""Frame sources on tiny generated videos and image folders."""

from __future__ import annotations

import logging
import os

import cv2
import numpy as np
import pytest

from edgerecon.io import FrameSpec, ImageFolderFrameSource, VideoFrameSource, probe_image_size
from edgerecon.io.frames import probe_video
from edgerecon.types import CalibrationError, DataError
from tests.conftest import ring_rig

W, H = 64, 48


def _frame(cam: int, t: int) -> np.ndarray:
    """A frame whose flat colour encodes (camera, time); survives MJPG compression."""
    return np.full((H, W, 3), (8 * t % 256, 60 * cam, 200), np.uint8)


def _decode_id(image: np.ndarray) -> tuple[int, int]:
    b, g, _ = image[H // 2, W // 2].astype(int)
    return round(g / 60), round(b / 8)


def _write_video(path, cam, num_frames, size=(W, H)):
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, size)
    assert writer.isOpened()
    for t in range(num_frames):
        writer.write(cv2.resize(_frame(cam, t), size))
    writer.release()
    return path


@pytest.fixture
def videos(tmp_path):
    return {f"cam{i}": _write_video(tmp_path / f"cam{i}.avi", i, 12) for i in range(3)}


def _rig(n=3):
    return ring_rig(n, width=W, height_px=H, focal_px=50.0)


def test_video_source_random_access_and_streaming_agree(videos):
    with VideoFrameSource(videos, rig=_rig()) as src:
        assert src.camera_names == ("cam0", "cam1", "cam2")
        assert src.num_frames == 12 and len(src) == 12 and src.fps == 25.0
        streamed = list(src.iter_frames())
        stats = src.stats()
        # One sequential pass: every frame decoded once, no skipping, no restart.
        assert stats == {"decoded": 36, "grabbed": 0, "rewinds": 0}
        assert [fs.time_index for fs in streamed] == list(range(12))
        assert streamed[5].timestamp_s == pytest.approx(5 / 25)
        for fs in streamed:
            assert [_decode_id(im) for im in fs.images] == [(c, fs.time_index) for c in range(3)]
        for t in (7, 3, 11, 0):
            fs = src.read(t)
            for a, b in zip(fs.images, streamed[t].images, strict=True):
                np.testing.assert_array_equal(a, b)


def test_iter_frames_with_step_skips_by_grabbing(videos):
    with VideoFrameSource(videos) as src:
        got = [fs.time_index for fs in src.iter_frames(start=2, stop=11, step=3)]
        assert got == [2, 5, 8]
        # Frames 0,1,3,4,6,7 skipped with grab(); 2,5,8 decoded; the stream never restarts.
        assert src.stats() == {"decoded": 9, "grabbed": 18, "rewinds": 0}
        # Reading before the stream position restarts each video once.
        assert _decode_id(src.read(1).images[2]) == (2, 1)
        assert src.stats()["rewinds"] == 3
        assert [fs.time_index for fs in src.iter_frames(start=10)] == [10, 11]
        with pytest.raises(ValueError, match="step"):
            next(src.iter_frames(step=0))


def test_frame_counts_differ_uses_minimum(tmp_path, caplog):
    paths = {f"cam{i}": _write_video(tmp_path / f"c{i}.avi", i, n) for i, n in enumerate((9, 7, 9))}
    with caplog.at_level(logging.WARNING, logger="edgerecon.io.frames"):
        src = VideoFrameSource(paths)
    assert src.num_frames == 7
    assert "different frame counts" in caplog.text and "'cam1': 7" in caplog.text
    with pytest.raises(DataError, match="time index 7 out of range"):
        src.read(7)
    with pytest.raises(DataError, match="out of range"):
        src.read(-1)


def test_video_errors(tmp_path, videos):
    with pytest.raises(DataError, match=r"'cam1'.*not found.*nope\.avi"):
        VideoFrameSource({"cam0": videos["cam0"], "cam1": tmp_path / "nope.avi"})
    garbage = tmp_path / "garbage.avi"
    garbage.write_bytes(os.urandom(2000))
    with pytest.raises(DataError, match=r"'cam2'.*garbage\.avi"):
        VideoFrameSource({"cam0": videos["cam0"], "cam2": garbage})
    big = {**videos, "cam1": _write_video(tmp_path / "big.avi", 1, 3, size=(80, 60))}
    with pytest.raises(CalibrationError, match=r"'cam1'.*big\.avi.*80x60.*calibration says 64x48"):
        VideoFrameSource(big, rig=_rig())
    with pytest.raises(DataError, match=r"\['cam9'\]"):
        VideoFrameSource({**videos, "cam9": videos["cam0"]}, rig=_rig())
    with pytest.raises(DataError, match=r"no frames given for cameras \['cam2'\]"):
        VideoFrameSource({"cam0": videos["cam0"], "cam1": videos["cam1"]}, rig=_rig())
    with pytest.raises(ValueError, match="missing"):
        VideoFrameSource(videos, missing="ignore")  # type: ignore[arg-type]


def test_truncated_video_frame_error_and_skip_policy(tmp_path):
    paths = {f"cam{i}": _write_video(tmp_path / f"cam{i}.avi", i, 12) for i in range(3)}
    strict = VideoFrameSource(paths)
    lenient = VideoFrameSource(paths, missing="skip_camera")
    # The file loses its tail after the sources were opened (a recording cut short).
    data = paths["cam1"].read_bytes()
    paths["cam1"].write_bytes(data[: len(data) // 2])
    with pytest.raises(DataError, match=r"camera 'cam1', time index 10"):
        strict.read(10)
    fs = lenient.read(10)
    assert fs.images[1] is None and fs.available == [0, 2]
    assert _decode_id(fs.images[2]) == (2, 10)
    strict.close()
    lenient.close()


def test_probe_video_counts_decodable_frames(videos):
    info = probe_video(videos["cam0"])
    assert (info.width, info.height, info.num_frames, info.fps) == (W, H, 12, 25.0)


# ---------------------------------------------------------------------------- image folders
def _write_images(folder, cam, indices, name="{:06d}.png"):
    folder.mkdir(parents=True, exist_ok=True)
    for t in indices:
        cv2.imwrite(str(folder / name.format(t)), _frame(cam, t))


def test_image_pattern_folder_and_single_file(tmp_path):
    _write_images(tmp_path / "a", 0, range(5))
    _write_images(tmp_path / "b", 1, [1, 2, 10, 3, 4], name="img{}.png")  # natural order
    _write_images(tmp_path / "c", 2, range(1, 6), name="f{:03d}.png")
    src = ImageFolderFrameSource(
        {
            "cam0": tmp_path / "a" / "{index:06d}.png",
            "cam1": tmp_path / "b",
            "cam2": tmp_path / "c" / "f{index:03d}.png",
        },
        rig=_rig(),
    )
    # cam2's pattern starts at 1 with start=0: file 0 is a gap, reported when read.
    assert src.num_frames == 5 and src.fps is None
    assert src.frame_sizes == {"cam0": (W, H), "cam1": (W, H), "cam2": (W, H)}
    fs = src.read(4)
    assert fs.timestamp_s is None
    assert _decode_id(fs.images[0]) == (0, 4)
    assert _decode_id(fs.images[1]) == (1, 10)  # sorted img1, img2, img3, img4, img10
    assert _decode_id(fs.images[2]) == (2, 4)
    with pytest.raises(DataError, match=r"camera 'cam2', time index 0.*f000\.png is missing"):
        src.read(0)
    shifted = ImageFolderFrameSource({"cam2": tmp_path / "c" / "f{index:03d}.png"}, start=1)
    assert shifted.num_frames == 5 and _decode_id(shifted.read(0).images[0]) == (2, 1)
    single = ImageFolderFrameSource([tmp_path / "a" / "000003.png"] * 3)
    assert single.num_frames == 1 and single.camera_names == ("cam0", "cam1", "cam2")
    assert [s.time_index for s in single.iter_frames()] == [0]


def test_image_missing_and_corrupt_frames(tmp_path, caplog):
    for i in range(3):
        _write_images(tmp_path / f"cam{i}", i, range(4))
    (tmp_path / "cam1" / "000002.png").unlink()
    (tmp_path / "cam2" / "000001.png").write_bytes(b"not a png at all")
    cams = {f"cam{i}": tmp_path / f"cam{i}" / "{index:06d}.png" for i in range(3)}
    src = ImageFolderFrameSource(cams, rig=_rig())
    assert src.num_frames == 4
    with pytest.raises(DataError, match=r"camera 'cam1', time index 2.*missing"):
        src.read(2)
    with pytest.raises(DataError, match=r"camera 'cam2', time index 1.*cannot be decoded"):
        list(src.iter_frames())
    lenient = ImageFolderFrameSource(cams, rig=_rig(), missing="skip_camera")
    with caplog.at_level(logging.WARNING, logger="edgerecon.io.frames"):
        sets = list(lenient.iter_frames())
    assert [fs.available for fs in sets] == [[0, 1, 2], [0, 1], [0, 2], [0, 1, 2]]
    assert "camera 'cam1', time index 2" in caplog.text
    # A frame of the wrong size is a configuration error under every policy.
    cv2.imwrite(str(tmp_path / "cam0" / "000003.png"), np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(CalibrationError, match=r"'cam0'.*000003\.png.*10x10.*64x48"):
        lenient.read(3)


def test_image_source_errors(tmp_path):
    with pytest.raises(DataError, match=r"'cam0'.*not found"):
        ImageFolderFrameSource({"cam0": tmp_path / "nothing"})
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match=r"'cam0'.*no image files"):
        ImageFolderFrameSource({"cam0": tmp_path / "empty"})
    with pytest.raises(DataError, match=r"'cam0'.*no frame matches"):
        ImageFolderFrameSource({"cam0": tmp_path / "empty" / "{index:04d}.png"})
    with pytest.raises(DataError, match=r"'cam0'.*bad frame pattern"):
        ImageFolderFrameSource({"cam0": tmp_path / "{index:q}.png"})
    with pytest.raises(DataError, match="not found"):
        probe_image_size(tmp_path / "x.png")
    cv2.imwrite(str(tmp_path / "g.jpg"), np.zeros((7, 9), np.uint8))
    assert probe_image_size(tmp_path / "g.jpg") == (9, 7)


def test_frame_spec_is_picklable_and_opens(tmp_path, videos):
    import pickle

    spec = FrameSpec(kind="video", cameras=tuple((k, str(v)) for k, v in videos.items()))
    spec = pickle.loads(pickle.dumps(spec))
    with spec.open(_rig()) as src:
        assert src.num_frames == 12
    with pytest.raises(ValueError, match="kind"):
        FrameSpec(kind="film", cameras=())  # type: ignore[arg-type]
