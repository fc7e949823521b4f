"""COLMAP models: COLMAP's documented text/binary layout, many images per camera, pycolmap."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from edgerecon.io import load_rig
from edgerecon.io.colmap import (
    ColmapCamera,
    ColmapImage,
    ColmapModel,
    ColmapPoints,
    read_colmap_model,
    rig_from_colmap,
    rig_to_colmap,
    rotation_to_quaternion,
    write_colmap_model,
)
from edgerecon.types import CalibrationError
from tests.conftest import ring_rig


def _model_with_points(rig, n=6, seed=0):
    """A model of ``rig`` with n points seen by every camera (tracks in rig order)."""
    rng = np.random.default_rng(seed)
    xyz = rng.normal(size=(n, 3)) * 0.3 + [0, 0, 1]
    uv = [cam.project(xyz)[0] for cam in rig]
    ids = [np.arange(1, n + 1) for _ in rig]
    nc = len(rig)
    points = ColmapPoints(
        ids=np.arange(1, n + 1),
        xyz=xyz,
        rgb=rng.integers(0, 256, (n, 3)).astype(np.uint8),
        error=rng.uniform(0.1, 1.0, n),
        track_offsets=np.arange(0, n * nc + 1, nc),
        track_image_ids=np.tile(np.arange(1, nc + 1), n),
        track_point2D_idxs=np.repeat(np.arange(n), nc),
    )
    return rig_to_colmap(rig, points2D=uv, point3D_ids=ids, points=points), xyz, uv


def test_binary_layout_is_colmaps(tmp_path):
    """Bytes written field by field from COLMAP's documented layout (read_write_model.py)."""
    cam = ColmapCamera(
        camera_id=7, model="OPENCV", width=640, height=480, params=np.arange(1.0, 9.0)
    )
    img = ColmapImage(
        image_id=3,
        qvec=np.array([1.0, 0, 0, 0]),
        tvec=np.array([0.5, -1.0, 2.0]),
        camera_id=7,
        name="cam0/000001.png",
        points2D=np.array([[10.5, 20.25], [30.0, 40.0]]),
        point3D_ids=np.array([11, -1]),
    )
    pts = ColmapPoints(
        ids=np.array([11]),
        xyz=np.array([[1.0, 2.0, 3.0]]),
        rgb=np.array([[10, 20, 30]], np.uint8),
        error=np.array([0.25]),
        track_offsets=np.array([0, 1]),
        track_image_ids=np.array([3]),
        track_point2D_idxs=np.array([0]),
    )
    model = ColmapModel(cameras={7: cam}, images={3: img}, points3D=pts)
    write_colmap_model(tmp_path, model, binary=True)
    expected_cameras = struct.pack("<Q", 1) + struct.pack("<iiQQ", 7, 4, 640, 480)
    expected_cameras += struct.pack("<8d", *range(1, 9))
    assert (tmp_path / "cameras.bin").read_bytes() == expected_cameras
    expected_images = struct.pack("<Q", 1) + struct.pack("<I", 3)
    expected_images += struct.pack("<7d", 1, 0, 0, 0, 0.5, -1, 2) + struct.pack("<I", 7)
    expected_images += b"cam0/000001.png\x00" + struct.pack("<Q", 2)
    expected_images += struct.pack("<ddq", 10.5, 20.25, 11) + struct.pack("<ddq", 30, 40, -1)
    assert (tmp_path / "images.bin").read_bytes() == expected_images
    expected_points = struct.pack("<Q", 1) + struct.pack("<Q3d3Bd", 11, 1, 2, 3, 10, 20, 30, 0.25)
    expected_points += struct.pack("<Q", 1) + struct.pack("<ii", 3, 0)
    assert (tmp_path / "points3D.bin").read_bytes() == expected_points
    # The text form, line by line.
    write_colmap_model(tmp_path / "txt", model)
    data = [
        ln for ln in (tmp_path / "txt" / "images.txt").read_text().splitlines() if ln[:1] != "#"
    ]
    assert data == [
        "3 1.0 0.0 0.0 0.0 0.5 -1.0 2.0 7 cam0/000001.png",
        "10.5 20.25 11 30.0 40.0 -1",
    ]
    cams = (tmp_path / "txt" / "cameras.txt").read_text().splitlines()
    assert cams[-1] == "7 OPENCV 640 480 1.0 2.0 3.0 4.0 5.0 6.0 7.0 8.0"
    pts_lines = (tmp_path / "txt" / "points3D.txt").read_text().splitlines()
    assert pts_lines[-1] == "11 1.0 2.0 3.0 10 20 30 0.25 3 0"


@pytest.mark.parametrize("binary", [False, True])
def test_model_round_trip(tmp_path, binary):
    rig = ring_rig(4, dist=(-0.05, 0.01, 0.001, -0.002, 0.0))
    model, xyz, uv = _model_with_points(rig)
    write_colmap_model(tmp_path, model, binary=binary)
    back = read_colmap_model(tmp_path)
    assert sorted(back.cameras) == [1, 2, 3, 4]
    assert back.cameras[2].model == "OPENCV"
    np.testing.assert_array_equal(back.points3D.xyz, xyz)
    np.testing.assert_array_equal(back.points3D.rgb, model.points3D.rgb)
    np.testing.assert_array_equal(back.points3D.track_lengths, [4] * 6)
    np.testing.assert_array_equal(back.images[3].points2D, uv[2] + 0.5)
    rig_back = load_rig(tmp_path)
    for a, b in zip(rig, rig_back, strict=True):
        np.testing.assert_allclose(b.K, a.K, atol=1e-12)
        np.testing.assert_allclose(b.R, a.R, atol=1e-14)
        np.testing.assert_allclose(b.t, a.t, atol=1e-14)
        np.testing.assert_array_equal(b.dist, a.dist)


def test_pycolmap_reads_our_models_and_we_read_its(tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    rig = ring_rig(4)
    model, xyz, _ = _model_with_points(rig)
    for binary in (False, True):
        folder = tmp_path / ("bin" if binary else "txt")
        write_colmap_model(folder, model, binary=binary)
        rec = pycolmap.Reconstruction(str(folder))
        assert rec.num_images() == 4 and rec.num_points3D() == 6
        p = rec.points3D[3]
        np.testing.assert_allclose(p.xyz, xyz[2], atol=1e-12)
        assert p.track.length() == 4
        image = rec.images[2]
        assert image.name == "cam1.png" and image.num_points3D == 6
        np.testing.assert_allclose(image.cam_from_world().rotation.matrix(), rig[1].R, atol=1e-12)
        np.testing.assert_allclose(image.cam_from_world().translation, rig[1].t, atol=1e-12)
        # A point reprojects where we put its observation (pixel conventions agree).
        cam = rec.cameras[image.camera_id]
        uv = cam.img_from_cam(image.cam_from_world() * xyz[4])
        np.testing.assert_allclose(uv, image.points2D[4].xy, atol=1e-9)
        # And what pycolmap writes, we read.
        again = tmp_path / f"pycolmap_{binary}"
        again.mkdir()
        (rec.write_binary if binary else rec.write_text)(str(again))
        back = read_colmap_model(again)
        np.testing.assert_allclose(back.points3D.xyz[np.argsort(back.points3D.ids)], xyz)
        rig_back = load_rig(again)
        np.testing.assert_allclose(rig_back[3].center, rig[3].center, atol=1e-12)


def _many_images_model(rig, frames=5, folders=True, shared_camera=False, noise=0.0, seed=1):
    """Images ``camK/00000i.png`` (or ``camK_00000i.png``) of each rig camera."""
    rng = np.random.default_rng(seed)
    cameras, images = {}, {}
    base = rig_to_colmap(rig)
    for k in range(1, len(rig) + 1):
        cameras[k] = base.cameras[1 if shared_camera else k]
        cameras[k] = ColmapCamera(
            camera_id=k,
            model=cameras[k].model,
            width=cameras[k].width,
            height=cameras[k].height,
            params=cameras[k].params,
        )
    image_id = 1
    for f in range(frames):
        for k, cam in enumerate(rig, start=1):
            angle = noise * rng.normal(size=3)
            import cv2

            dR = cv2.Rodrigues(angle.reshape(3, 1))[0]
            R = dR @ cam.R
            C = cam.center + noise * rng.normal(size=3)
            name = f"{cam.name}/{f:06d}.png" if folders else f"{cam.name}_{f:06d}.png"
            images[image_id] = ColmapImage(
                image_id=image_id,
                qvec=rotation_to_quaternion(R),
                tvec=-R @ C,
                camera_id=1 if shared_camera else k,
                name=name,
            )
            image_id += 1
    if shared_camera:
        cameras = {1: cameras[1]}
    return ColmapModel(cameras=cameras, images=images)


@pytest.mark.parametrize(
    ("folders", "shared", "grouping"),
    [(True, False, "folder"), (False, False, "camera_id"), (False, True, "pose")],
)
def test_many_images_per_camera_are_grouped(tmp_path, folders, shared, grouping):
    rig = ring_rig(4)
    model = _many_images_model(rig, folders=folders, shared_camera=shared, noise=1e-4)
    write_colmap_model(tmp_path, model, binary=True)
    got = rig_from_colmap(read_colmap_model(tmp_path))
    assert got.grouping == grouping
    assert len(got.rig) == 4
    if grouping == "folder":
        assert got.rig.names == rig.names
        assert got.frames["cam2"] == [f"cam2/{f:06d}.png" for f in range(5)]
    for a in rig:
        b = min(got.rig, key=lambda c: np.linalg.norm(c.center - a.center))
        # The mean of 5 poses with 1e-4 noise: within a few 1e-4 of the true pose.
        np.testing.assert_allclose(b.center, a.center, atol=3e-4)
        np.testing.assert_allclose(b.R, a.R, atol=3e-4)
    spread, angle = max(got.pose_spread.values())
    assert 0 < spread < 1e-3 and angle < 0.05


def test_moving_camera_is_not_a_rig_camera():
    rig = ring_rig(4)
    model = _many_images_model(rig)
    # cam2 moves between its frames: its folder cannot be one static camera.
    images = dict(model.images)
    for image_id, img in model.images.items():
        if img.name.startswith("cam2/") and not img.name.endswith("000000.png"):
            C = img.center + [0.2 * image_id, 0, 0]
            images[image_id] = ColmapImage(
                image_id=image_id, qvec=img.qvec, tvec=-img.R @ C, camera_id=3, name=img.name
            )
    with pytest.raises(CalibrationError, match=r"images of 'cam2'.*do not share one pose"):
        rig_from_colmap(ColmapModel(cameras=model.cameras, images=images))
    # Every image at its own pose (an SfM model of a static scene): one camera per image.
    moving = _many_images_model(rig, noise=0.2)
    got = rig_from_colmap(moving)
    assert got.grouping == "image" and len(got.rig) == 20


def test_different_intrinsics_in_one_camera_are_rejected():
    rig = ring_rig(3)
    model = _many_images_model(rig, frames=2)
    # Image names say camera cam0, but its two frames use two COLMAP cameras with
    # different focal lengths.
    cams = dict(model.cameras)
    cams[9] = ColmapCamera(
        camera_id=9, model="PINHOLE", width=640, height=480, params=np.array([400.0, 400, 320, 240])
    )
    images = dict(model.images)
    first = images[4]  # cam0, frame 1
    images[4] = ColmapImage(
        image_id=4, qvec=first.qvec, tvec=first.tvec, camera_id=9, name=first.name
    )
    with pytest.raises(CalibrationError, match="'cam0'.*different intrinsics"):
        rig_from_colmap(ColmapModel(cameras=cams, images=images))
