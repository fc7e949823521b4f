"""``edgerecon export``: COLMAP workspaces (read back by our reader, pycolmap and, where
installed, COLMAP itself), visibility tracks, Z-up metres, viewer PLY."""

from __future__ import annotations

import json
import shutil
import subprocess

import numpy as np
import pytest

from edgerecon.cli import main
from edgerecon.geometry import Camera, Rig, look_at
from edgerecon.io import load_rig, open_dataset, read_ply
from edgerecon.io.colmap import read_colmap_model
from edgerecon.io.export import (
    export_colmap,
    rotation_between,
    visibility_tracks,
    z_up_metres,
)
from edgerecon.io.ply import read_ply_meta
from edgerecon.types import FrameSet, PointCloud


@pytest.fixture(scope="module")
def reconstruction(tiny_dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("rec") / "t3"
    args = ["reconstruct", "--dataset", str(tiny_dataset), "-t", "3", "-r", "0.6", "-o", str(out)]
    assert main(args) == 0
    return out


def test_export_colmap_workspace(reconstruction, tiny_dataset, tmp_path, capsys):
    out = tmp_path / "ws"
    assert main(["export", str(reconstruction), "--out", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["time"] == 3 and report["cloud"].endswith("sparse.ply")
    sparse = read_ply(reconstruction / "sparse.ply")
    assert 0.8 * len(sparse) <= report["num_points"] <= len(sparse)
    assert sorted(p.name for p in (out / "images").iterdir()) == [f"cam{k}.png" for k in range(5)]
    model = read_colmap_model(out / "sparse")
    assert {c.model for c in model.cameras.values()} == {"PINHOLE"}
    assert len(model.points3D) == report["num_points"] and model.points3D.track_lengths.min() >= 2
    # Every observation is the point's projection (COLMAP pixel convention).
    rig = open_dataset(tiny_dataset).rig
    img = model.images[2]
    ids = img.point3D_ids
    xyz = model.points3D.xyz[np.searchsorted(model.points3D.ids, ids)]
    uv, _ = rig[1].undistorted().project(xyz)
    np.testing.assert_allclose(img.points2D, uv + 0.5, atol=1e-9)
    # The model's rig is the dataset's (undistorted) rig.
    back = load_rig(out / "sparse")
    np.testing.assert_allclose(back[4].center, rig[4].center, atol=1e-12)


def test_export_model_dir_for_gaussian_splatting(reconstruction, tmp_path, capsys):
    """3D Gaussian Splatting and nerfstudio read ``<workspace>/sparse/0`` + ``images``."""
    out = tmp_path / "gs"
    args = ["export", str(reconstruction), "--out", str(out), "--cloud", "dense", "--binary"]
    assert main([*args, "--model-dir", "sparse/0", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["model"] == str(out / "sparse" / "0")
    assert {p.name for p in (out / "sparse" / "0").iterdir()} == {
        "cameras.bin",
        "images.bin",
        "points3D.bin",
    }
    assert len(read_colmap_model(out / "sparse" / "0").points3D) == report["num_points"] > 1000
    assert main([*args, "--model-dir", "../x"]) == 2
    assert "inside the workspace" in capsys.readouterr().err


def test_export_is_read_by_pycolmap(reconstruction, tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    assert main(["export", str(reconstruction), "--out", str(tmp_path / "b"), "--binary"]) == 0
    rec = pycolmap.Reconstruction(str(tmp_path / "b" / "sparse"))
    assert rec.num_reg_images() == 5 and rec.num_points3D() > 100
    # pycolmap's own projection of its points lands on the stored observations.
    for image in rec.images.values():
        cam = rec.cameras[image.camera_id]
        for p2d in image.points2D[:20]:
            if p2d.has_point3D():
                xyz = rec.points3D[p2d.point3D_id].xyz
                uv = cam.img_from_cam(image.cam_from_world() * xyz)
                np.testing.assert_allclose(uv, p2d.xy, atol=1e-6)


@pytest.mark.skipif(shutil.which("colmap") is None, reason="COLMAP is not installed")
def test_export_is_read_by_colmap(reconstruction, tmp_path):
    for flag in ([], ["--binary"]):
        out = tmp_path / ("bin" if flag else "txt")
        assert main(["export", str(reconstruction), "--out", str(out), "--no-images", *flag]) == 0
        proc = subprocess.run(
            ["colmap", "model_analyzer", "--path", str(out / "sparse")],
            capture_output=True,
            text=True,
            env={"QT_QPA_PLATFORM": "offscreen", "PATH": "/usr/bin:/bin"},
            check=False,
        )
        text = proc.stdout + proc.stderr
        assert proc.returncode == 0, text
        assert "Registered images: 5" in text
        n = len(read_colmap_model(out / "sparse").points3D)
        assert f"Points: {n}" in text


def _rig_mm_z_down():
    """Three cameras 4 m around the origin in millimetres, world Z pointing down, with
    distortion (a utrecht4cam-like frame)."""
    cams = []
    for k in range(3):
        a = 2 * np.pi * k / 3
        R, t = look_at((4000 * np.cos(a), 4000 * np.sin(a), -1500.0), (0, 0, -800.0), (0, 0, -1))
        K = np.array([[400.0, 0, 159.5], [0, 400.0, 119.5], [0, 0, 1]])
        dist = (-0.1, 0.01, 0, 0, 0)
        cams.append(Camera(name=f"c{k}", width=320, height=240, K=K, R=R, t=t, dist=dist))
    return Rig(cameras=tuple(cams), unit="mm", up=(0.0, 0.0, -1.0))


def test_z_up_metres_keeps_the_model_consistent(tmp_path):
    rig = _rig_mm_z_down()
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(200, 3)) * 200 + [0, 0, -800]
    cloud = PointCloud(points3D=pts, colors=np.full((200, 3), 200, np.uint8))
    sim = z_up_metres(rig.unit, rig.up)
    assert sim.scale == 0.001
    np.testing.assert_allclose(sim.R @ [0, 0, -1.0], [0, 0, 1.0], atol=1e-15)
    # Pixels do not change: every camera sees every point where it did.
    for cam in rig:
        uv0, d0 = cam.project(pts)
        uv1, d1 = sim.camera(cam).project(sim.points(pts))
        np.testing.assert_allclose(uv1, uv0, atol=1e-9)
        np.testing.assert_allclose(d1, d0 * 0.001)
    frames = FrameSet(time_index=0, images=tuple(np.zeros((240, 320, 3), np.uint8) for _ in rig))
    report = export_colmap(tmp_path, rig, cloud, frames=frames, transform=sim, distorted=True)
    # A blob of points hides a few of its own points from some cameras.
    assert 190 <= report.num_points <= 200 and report.transform.startswith("scaled by 0.001")
    model = read_colmap_model(tmp_path / "sparse")
    assert {c.model for c in model.cameras.values()} == {"OPENCV"}
    kept = np.isin(np.arange(200), np.flatnonzero(report_mask(rig, pts, sim)))
    np.testing.assert_allclose(model.points3D.xyz, sim.points(pts)[kept])
    assert model.meta["unit"] == "m" and model.meta["up"] == "0.0,0.0,1.0"
    assert rotation_between((0, 0, 1), (0, 0, -1)) @ [0, 0, 1] == pytest.approx([0, 0, -1])


def report_mask(rig, pts, sim):
    """Which points export_colmap keeps (seen by >= 2 of the transformed cameras)."""
    cams = [sim.camera(c) for c in rig]
    return visibility_tracks(sim.points(pts), cams).lengths(len(pts)) >= 2


def test_visibility_tracks_hide_points_behind_a_wall():
    rig = _rig_mm_z_down()
    cam = rig[0]
    # A point 3 m in front of camera 0 and a wall of points 1 m in front of it, in between.
    axis = cam.viewing_direction
    target = cam.center + 3000 * axis
    u = np.cross(axis, [0, 0, 1.0])
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    g = np.linspace(-300, 300, 61)
    wall = cam.center + 1000 * axis + (g[:, None, None] * u + g[None, :, None] * v).reshape(-1, 3)
    tracks = visibility_tracks(np.array([target]), [cam], occluders=wall)
    assert len(tracks.point_ids[0]) == 0
    tracks = visibility_tracks(np.array([target]), [cam], occluders=wall + 2500 * axis)
    assert list(tracks.point_ids[0]) == [0]
    np.testing.assert_allclose(tracks.points2D[0][0], cam.project(target[None])[0][0])


def test_export_ply_z_up_metres(reconstruction, tmp_path, capsys):
    out = tmp_path / "view.ply"
    assert (
        main(["export", str(reconstruction), "--to", "ply", "--z-up-metres", "-o", str(out)]) == 0
    )
    meta = read_ply_meta(out)
    assert meta.unit == "m" and meta.up == (0.0, 0.0, 1.0)
    assert any("exported by edgerecon from dense.ply" in c for c in meta.comments)
    assert len(read_ply(out)) == len(read_ply(reconstruction / "dense.ply"))
    # The clouds reconstruct writes record their unit and up too, and which points are
    # inferred; the export keeps that.
    assert read_ply_meta(reconstruction / "dense.ply").unit == "m"
    assert "inferred" in meta.vertex_properties
    assert "inferred" in read_ply_meta(reconstruction / "dense.ply").vertex_properties
    np.testing.assert_array_equal(
        read_ply(out).inferred, read_ply(reconstruction / "dense.ply").inferred
    )
    flagged = read_ply(reconstruction / "dense.ply").with_inferred(True)
    moved = z_up_metres("m", (0.0, 0.0, 1.0)).cloud(flagged)
    assert moved.inferred.all()
    assert main(["export", str(reconstruction), "--to", "colmap", "-o", str(tmp_path / "x"),
                 "--cloud", "nope"]) == 2  # fmt: skip
    assert "not found" in capsys.readouterr().err


def test_max_range_drops_stray_points():
    from edgerecon.cli.export import crop_range

    rig = _rig_mm_z_down()  # cameras 4.27 m from where they look
    pts = np.array([[0, 0, -800.0], [5000, 0, -800], [40000, 0, 0]])
    cloud, dropped = crop_range(PointCloud(points3D=pts), rig, "auto")
    assert dropped == 1 and len(cloud) == 2  # 3 x 4.27 m keeps the wall 5 m away
    assert crop_range(PointCloud(points3D=pts), rig, "2000")[1] == 2
    assert crop_range(PointCloud(points3D=pts), rig, "none")[1] == 0
