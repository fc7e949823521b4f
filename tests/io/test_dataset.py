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
