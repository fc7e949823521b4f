"""NeRF-style ``transforms.json`` (nerfstudio, Instant-NGP, the Blender scenes): written as
those tools write it, read back to the rig, imported with frames and reconstructed; the
nerfstudio export read back."""

from __future__ import annotations

import dataclasses
import json
import math

import cv2
import numpy as np
import pytest

from edgerecon.cli import main
from edgerecon.geometry import Rig
from edgerecon.io import load_rig, open_dataset, read_ply
from edgerecon.io.calib_nerf import read_transforms, transforms_camera_names
from edgerecon.io.calibration import detect_calibration_format
from edgerecon.io.importer import import_dataset
from edgerecon.synth import GroundTruth
from edgerecon.types import CalibrationError, DataError
from tests.io.test_importer import reconstruct_score

GL = np.diag([1.0, -1.0, -1.0])


@pytest.fixture(scope="module")
def scene(tiny_dataset):
    ds = open_dataset(tiny_dataset)
    return ds, GroundTruth.open(tiny_dataset)


def _c2w(cam) -> list[list[float]]:
    """The OpenGL camera-to-world matrix nerfstudio stores (as its colmap_utils computes it:
    the inverse of world->camera, then y and z flipped)."""
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = cam.R, cam.t
    c2w = np.linalg.inv(w2c)
    c2w[:3, 1:3] *= -1
    return c2w.tolist()


def _nerfstudio(rig: Rig, paths: list[str]) -> dict:
    """A transforms.json as ns-process-data writes one for several cameras: per-frame
    intrinsics, OPENCV model."""
    frames = []
    for cam, path in zip(rig, paths, strict=True):
        k1, k2, p1, p2, k3 = np.asarray(cam.dist, float).ravel()[:5]
        frames.append(
            {
                "file_path": path,
                "fl_x": cam.K[0, 0],
                "fl_y": cam.K[1, 1],
                "cx": cam.K[0, 2],
                "cy": cam.K[1, 2],
                "w": cam.width,
                "h": cam.height,
                "k1": k1,
                "k2": k2,
                "p1": p1,
                "p2": p2,
                "k3": k3,
                "transform_matrix": _c2w(cam),
            }
        )
    return {"camera_model": "OPENCV", "frames": frames}


def _same(got: Rig, want: Rig, atol: float = 1e-9) -> None:
    assert got.names == want.names
    for a, b in zip(got, want, strict=True):
        assert a.size == b.size
        np.testing.assert_allclose(a.K, b.K, atol=atol)
        np.testing.assert_allclose(a.R, b.R, atol=atol)
        np.testing.assert_allclose(a.t, b.t, atol=atol)
        np.testing.assert_allclose(np.ravel(a.dist)[:5], np.ravel(b.dist)[:5], atol=atol)


def test_nerfstudio_file_reads_as_the_rig(scene, tmp_path):
    ds, _ = scene
    path = tmp_path / "transforms.json"
    path.write_text(json.dumps(_nerfstudio(ds.rig, [f"images/{n}.png" for n in ds.rig.names])))
    assert detect_calibration_format(path) == "nerf"
    assert detect_calibration_format(tmp_path) == "nerf"
    got = load_rig(tmp_path)
    _same(got, ds.rig)
    assert got.unit == "m" and got.up == (0.0, 0.0, 1.0)


def test_the_rig_at_several_timestamps_is_one_camera_each(scene, tmp_path):
    ds, _ = scene
    # Every camera's frames in its own folder, twice: the folder names the camera.
    names = list(ds.rig.names)
    paths = [f"{n}/{k:06d}.jpg" for k in range(2) for n in names]
    data = _nerfstudio(ds.rig, paths[: len(names)])
    data["frames"] += _nerfstudio(ds.rig, paths[len(names) :])["frames"]
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    assert transforms_camera_names(tmp_path) == names
    _same(read_transforms(tmp_path), ds.rig)


def test_blender_scene_sizes_from_its_images(scene, tmp_path):
    ds, _ = scene
    cams = list(ds.rig)[:3]
    (tmp_path / "train").mkdir()
    frames = []
    for k, cam in enumerate(cams):
        image = np.zeros((cam.height, cam.width, 3), np.uint8)
        cv2.imwrite(str(tmp_path / "train" / f"r_{k}.png"), image)
        angle = 2 * math.atan(0.5 * cam.width / float(cam.K[0, 0]))
        frames.append(
            {"file_path": f"./train/r_{k}", "camera_angle_x": angle, "rotation": 0.01,
             "transform_matrix": _c2w(cam)}
        )  # fmt: skip
    data = {"camera_angle_x": 0.5, "frames": frames}
    (tmp_path / "transforms_train.json").write_text(json.dumps(data))
    got = read_transforms(tmp_path)
    assert got.names == ["r_0", "r_1", "r_2"]
    for c, cam in zip(got, cams, strict=True):
        fx = float(cam.K[0, 0])
        assert c.size == cam.size
        np.testing.assert_allclose(
            c.K, [[fx, 0, cam.width / 2], [0, fx, cam.height / 2], [0, 0, 1]], rtol=1e-12
        )
        np.testing.assert_allclose(c.R, cam.R, atol=1e-12)
        np.testing.assert_allclose(c.center, cam.center, atol=1e-12)


def test_refused_models_and_bad_matrices(scene, tmp_path):
    ds, _ = scene
    data = _nerfstudio(ds.rig, [f"images/{n}.png" for n in ds.rig.names])
    path = tmp_path / "transforms.json"

    def fails(d, match):
        path.write_text(json.dumps(d))
        with pytest.raises(CalibrationError, match=match):
            read_transforms(path)

    fails({**data, "camera_model": "OPENCV_FISHEYE"}, "have fisheye lenses: import")
    fails({**data, "is_fisheye": True}, "have fisheye lenses: import")
    fails({**data, "camera_model": "EQUIRECTANGULAR"}, "camera_model EQUIRECTANGULAR")
    bad = json.loads(json.dumps(data))
    bad["frames"][1]["transform_matrix"][0][0] *= 3
    fails(bad, r"frame 1: transform_matrix's rotation is scaled")
    bad = json.loads(json.dumps(data))
    bad["frames"][2]["transform_matrix"] = [[1, 0], [0, 1]]
    fails(bad, r"frame 2: transform_matrix must be 4x4 or 3x4")
    bad = json.loads(json.dumps(data))
    for f in bad["frames"]:
        del f["fl_x"], f["fl_y"]
    fails(bad, "no focal length")
    bad = json.loads(json.dumps(data))
    for f in bad["frames"]:
        del f["w"], f["h"]
    fails(bad, r"no image size")
    path.write_text(json.dumps({"frames": [{"file_path": "a.png"}]}))
    with pytest.raises(CalibrationError, match="JSON file is neither"):
        detect_calibration_format(path)


def test_import_transforms_with_videos_and_reconstruct(scene, tmp_path, capsys):
    ds, gt = scene
    # Sizes from the frames (the file records none), a sixth camera that was not filmed.
    first = ds.rig.cameras[0]
    extra = dataclasses.replace(first, name="spare", t=first.t + np.array([0.3, 0.0, 0.0]))
    rig6 = Rig(cameras=(*ds.rig, extra))
    data = _nerfstudio(rig6, [f"images/{n}.png" for n in rig6.names])
    for f in data["frames"]:
        del f["w"], f["h"]
    root = tmp_path / "ns"
    root.mkdir()
    (root / "transforms.json").write_text(json.dumps(data))
    frames = [f"{n}={ds.root / 'frames' / n}" for n in ds.rig.names]
    out = tmp_path / "imported"
    assert main(["import", str(root), *frames, "--out", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["calibration_format"] == "nerf"
    assert "SfM scales are arbitrary" in report["unit_note"]
    assert any("spare" in n for n in report["notes"])
    imported = open_dataset(out)
    _same(imported.rig, dataclasses.replace(ds.rig, up=imported.rig.up))
    score = reconstruct_score(out, tmp_path, gt)
    assert score.precision > 0.85 and score.num_pred > 150, score
    with pytest.raises(CalibrationError, match="no image size"):
        load_rig(root)  # no frames to size the cameras
    with pytest.raises(DataError, match="no frames given"):
        import_dataset(tmp_path / "x", calibration=root / "transforms.json", frames=[])


def test_export_nerfstudio_reads_back(scene, tmp_path, capsys):
    ds, _ = scene
    rec = tmp_path / "rec"
    args = ["reconstruct", "--dataset", str(ds.root), "-t", "3", "-r", "0.6", "-o", str(rec)]
    assert main(args) == 0
    capsys.readouterr()
    out = tmp_path / "ns"
    assert main(["export", str(rec), "--to", "nerfstudio", "-o", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    data = json.loads((out / "transforms.json").read_text())
    assert data["ply_file_path"] == "points3D.ply"
    assert [f["file_path"] for f in data["frames"]] == [f"images/{n}.png" for n in ds.rig.names]
    for cam in ds.rig:
        image = cv2.imread(str(out / "images" / f"{cam.name}.png"))
        assert image is not None and image.shape[:2] == (cam.height, cam.width)
    cloud = read_ply(out / "points3D.ply")
    assert len(cloud) == report["num_points"] > 1000
    assert cloud.colors is not None
    # The export's cameras are the rig's, undistorted (the images are).
    _same(read_transforms(out), ds.rig.undistorted(), atol=1e-9)


def test_opengl_convention_of_a_look_at_pose(tmp_path):
    # Cameras built the way Blender / NeRF build them: z backwards from the target, y up.
    frames = []
    for k, centre in enumerate(([0.0, 4.0, 1.2], [4.0, 0.0, 1.2], [-3.0, -3.0, 2.0])):
        c = np.asarray(centre)
        z = c / np.linalg.norm(c)  # backwards: from the target (the origin) to the camera
        x = np.cross([0.0, 0.0, 1.0], z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        c2w = np.eye(4)
        c2w[:3, :3] = np.stack([x, y, z], axis=1)
        c2w[:3, 3] = c
        frames.append({"file_path": f"c{k}.png", "transform_matrix": c2w.tolist()})
    data = {"fl_x": 500.0, "w": 640, "h": 480, "frames": frames}
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    for cam in read_transforms(tmp_path):
        uv, depth = cam.project(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.5], [0.0, 0.0, -0.5]]))
        np.testing.assert_allclose(uv[0], [320.0, 240.0], atol=1e-9)  # the target at the centre
        assert depth[0] > 0
        assert uv[1, 1] < 240.0 < uv[2, 1]  # above the target is up in the image
