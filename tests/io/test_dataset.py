"""Datasets: descriptor files, auto-detected layouts, and their error paths."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from edgerecon.io import Dataset, FrameSpec, open_dataset, save_rig, write_dataset_descriptor
from edgerecon.types import CalibrationError, DataError
from tests.conftest import ring_rig, shared_data


def _write_image_dataset(root, rig, num_frames=3, pattern="frames/{cam}/{{index:06d}}.png"):
    """Frames whose pixel value encodes (camera, time) so reads can be checked exactly."""
    cams = {}
    for i, cam in enumerate(rig):
        rel = pattern.format(cam=cam.name)
        cams[cam.name] = rel
        for t in range(num_frames):
            img = np.full((cam.height, cam.width, 3), (10 * i, 10 * t, 7), np.uint8)
            path = root / rel.format(index=t)
            path.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(path), img)
    return cams


def test_descriptor_round_trip_with_images(tmp_path):
    rig = ring_rig(3, width=64, height_px=48, focal_px=50.0)
    cams = _write_image_dataset(tmp_path, rig, num_frames=4)
    (tmp_path / "gt").mkdir()
    write_dataset_descriptor(
        tmp_path,
        rig=rig,
        frames={"kind": "images", "cameras": cams},
        name="tiny",
        fps=10.0,
        ground_truth="gt",
    )
    ds = open_dataset(tmp_path)
    assert isinstance(ds, Dataset)
    assert ds.name == "tiny" and ds.layout == "descriptor"
    assert ds.rig == rig
    assert ds.num_frames == 4 and ds.fps == 10.0
    assert ds.ground_truth == tmp_path / "gt"
    assert ds.background is None and ds.open_background() is None
    with ds.open_frames() as src:
        fs = src.read(2)
    assert fs.timestamp_s == pytest.approx(0.2)
    for i, img in enumerate(fs.images):
        assert img is not None and tuple(img[0, 0]) == (10 * i, 20, 7)


def test_descriptor_errors_name_the_problem(tmp_path):
    rig = ring_rig(3, width=64, height_px=48, focal_px=50.0)
    cams = _write_image_dataset(tmp_path, rig, num_frames=2)
    save_rig(tmp_path / "rig.json", rig)
    base = {"format": "edgerecon-dataset", "version": 1, "rig": "rig.json"}

    def write(d):
        (tmp_path / "dataset.json").write_text(json.dumps(d))

    write({**base, "frames": {"kind": "images", "cameras": {**cams, "cam9": "x"}}})
    with pytest.raises(DataError, match="cam9"):
        open_dataset(tmp_path)
    partial = dict(list(cams.items())[:2])
    write({**base, "frames": {"kind": "images", "cameras": partial}})
    with pytest.raises(DataError, match="cam2"):
        open_dataset(tmp_path)
    write({**base, "frames": {"kind": "film", "cameras": cams}})
    with pytest.raises(DataError, match="kind"):
        open_dataset(tmp_path)
    write({**base, "rig": "nope.json", "frames": {"kind": "images", "cameras": cams}})
    with pytest.raises(DataError, match=r"nope\.json"):
        open_dataset(tmp_path)
    write({"format": "edgerecon-dataset", "frames": {}})
    with pytest.raises(DataError, match="'rig'"):
        open_dataset(tmp_path)
    (tmp_path / "dataset.json").write_text("{not json")
    with pytest.raises(DataError, match="not valid JSON"):
        open_dataset(tmp_path)
    # Frames of the wrong size for the calibration.
    small = ring_rig(3, width=32, height_px=24, focal_px=25.0)
    save_rig(tmp_path / "rig.json", small)
    write({**base, "frames": {"kind": "images", "cameras": cams}})
    with pytest.raises(CalibrationError, match=r"cam0.*64x48.*32x24"):
        open_dataset(tmp_path)
    # Fewer than three cameras in the rig.
    rig_json = json.loads((tmp_path / "rig.json").read_text())
    rig_json["cameras"] = rig_json["cameras"][:2]
    (tmp_path / "rig.json").write_text(json.dumps(rig_json))
    with pytest.raises(CalibrationError, match="at least 3 cameras"):
        open_dataset(tmp_path)


def test_missing_dataset_and_unknown_layout(tmp_path):
    with pytest.raises(DataError, match="not found"):
        open_dataset(tmp_path / "absent")
    with pytest.raises(DataError, match="not a dataset"):
        open_dataset(tmp_path)


def test_utrecht_autodetect_reads_frame_200():
    root = shared_data("utrecht4cam")
    ds = open_dataset(root)
    assert ds.layout == "utrecht4cam"
    assert ds.rig.names == ["cam1", "cam2", "cam3", "cam4"]
    assert ds.rig.unit == "mm" and ds.rig.up == (0.0, 0.0, -1.0)
    assert ds.fps == 50.0
    # Headers claim 428 frames; 426 decode in every camera.
    assert ds.num_frames == 426
    assert ds.background is not None
    with ds.open_frames() as src:
        fs = src.read(200)
    assert fs.time_index == 200 and fs.timestamp_s == pytest.approx(4.0)
    assert [im.shape for im in fs.images] == [(486, 644, 3)] * 4
    # Distinct cameras see distinct images.
    assert not np.array_equal(fs.images[0], fs.images[1])
    assert isinstance(ds.frames, FrameSpec) and ds.frames.kind == "video"


def test_middlebury_autodetect_is_static():
    root = shared_data("middlebury_templeSparseRing")
    ds = open_dataset(root)
    assert ds.layout == "middlebury" and ds.is_static and ds.num_frames == 1
    assert len(ds.rig) == 16 and ds.rig.unit == "m"
    with ds.open_frames() as src:
        fs = src.read(0)
        with pytest.raises(DataError, match="out of range"):
            src.read(1)
    assert all(im.shape == (480, 640, 3) for im in fs.images)


def _write_video(path, color, num_frames, size=(64, 48)):
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 20.0, size)
    for _ in range(num_frames):
        writer.write(np.full((size[1], size[0], 3), color, np.uint8))
    writer.release()


def test_descriptor_with_frame_specs_videos_and_background(tmp_path):
    import pickle

    rig = ring_rig(3, width=64, height_px=48, focal_px=50.0)
    for i, cam in enumerate(rig):
        (tmp_path / cam.name).mkdir()
        _write_video(tmp_path / cam.name / "scene.avi", (40 * i, 0, 0), 6)
        _write_video(tmp_path / cam.name / "empty.avi", (0, 40 * i, 0), 4)
    frames = FrameSpec(
        kind="video", cameras=tuple((c.name, str(tmp_path / c.name / "scene.avi")) for c in rig)
    )
    background = FrameSpec(
        kind="video", cameras=tuple((c.name, str(tmp_path / c.name / "empty.avi")) for c in rig)
    )
    path = write_dataset_descriptor(tmp_path, rig=rig, frames=frames, background=background)
    data = json.loads(path.read_text())
    assert data["frames"]["cameras"]["cam1"] == "cam1/scene.avi"  # written relative to root
    assert data["rig"] == "rig.json" and "fps" not in data
    ds = open_dataset(tmp_path / "dataset.json")
    assert ds.num_frames == 6 and ds.fps == 20.0  # the videos' own rate
    ds = pickle.loads(pickle.dumps(ds))  # datasets travel to other processes
    with ds.open_background() as bg:
        assert bg.num_frames == 4
        assert int(bg.read(3).images[2][10, 10, 1]) == pytest.approx(80, abs=4)
    with pytest.raises(ValueError, match="do not match"):
        write_dataset_descriptor(
            tmp_path, rig=rig, frames={"kind": "video", "cameras": {"cam0": "x.avi"}}
        )


def test_a_dataset_opened_by_a_relative_path_is_described_again_elsewhere(tmp_path, monkeypatch):
    """A dataset's frame specs copied into a descriptor in another folder (as the live
    wrapper of a recorded capture does with its background clip) still name its files when
    the dataset was opened through a path relative to the working directory."""
    rig = ring_rig(3, width=64, height_px=48, focal_px=50.0)
    src = tmp_path / "data" / "capture"
    for i, cam in enumerate(rig):
        (src / cam.name).mkdir(parents=True)
        _write_video(src / cam.name / "scene.avi", (40 * i, 0, 0), 6)
        _write_video(src / cam.name / "empty.avi", (0, 40 * i, 0), 4)
    write_dataset_descriptor(
        src,
        rig=rig,
        frames={"kind": "video", "cameras": {c.name: f"{c.name}/scene.avi" for c in rig}},
        background={"kind": "video", "cameras": {c.name: f"{c.name}/empty.avi" for c in rig}},
    )
    (tmp_path / "work").mkdir()
    monkeypatch.chdir(tmp_path / "work")
    ds = open_dataset("../data/capture")
    assert ds.background is not None
    copy = tmp_path / "runs" / "live"
    write_dataset_descriptor(copy, rig=rig, frames=ds.frames, background=ds.background)
    again = open_dataset(copy)
    with again.open_background() as bg:
        assert bg.num_frames == 4
        assert int(bg.read(0).images[1][10, 10, 1]) == pytest.approx(40, abs=4)
    with again.open_frames() as frames:
        assert frames.num_frames == 6
    # Inside the descriptor's own folder the paths stay relative to it.
    write_dataset_descriptor("../data/capture", rig=rig, frames=ds.frames)
    data = json.loads((src / "dataset.json").read_text())
    assert data["frames"]["cameras"]["cam2"] == "cam2/scene.avi"


def test_descriptor_camera_pattern_start_and_xml_rig(tmp_path):
    rig = ring_rig(3, width=64, height_px=48, focal_px=50.0)
    for i, cam in enumerate(rig):
        folder = tmp_path / "calib" / cam.name
        folder.mkdir(parents=True)
        fs = cv2.FileStorage(str(folder / "config.xml"), cv2.FILE_STORAGE_WRITE)
        fs.write("CameraMatrix", cam.K)
        fs.write("DistortionCoeffs", cam.dist[None])
        fs.write("Rotation", cv2.Rodrigues(cam.R)[0])
        fs.write("Translation", cam.t[:, None])
        fs.release()
        for t in (1, 2, 3):
            p = tmp_path / "img" / cam.name / f"{t:03d}.png"
            p.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(p), np.full((48, 64, 3), 10 * i + t, np.uint8))
    write_dataset_descriptor(
        tmp_path,
        rig="calib",
        frames={"kind": "images", "pattern": "img/{camera}/{index:03d}.png", "start": 1},
    )
    ds = open_dataset(tmp_path)
    assert ds.rig.unit == "mm"  # the OpenCV-XML folder convention
    assert [c.size for c in ds.rig] == [(64, 48)] * 3  # sizes taken from the frames
    assert ds.num_frames == 3
    with ds.open_frames() as src:
        assert [int(im[0, 0, 0]) for im in src.read(0).images] == [1, 11, 21]


def test_middlebury_ring_gets_vertical_up():
    ds = open_dataset(shared_data("middlebury_templeSparseRing"))
    # The temple stands along +y (its bounding box is tallest in y) and the cameras look down.
    assert ds.rig.up[1] > 0.99
