"""Fisheye cameras: a lens's frames rectified to a pinhole camera as they are read; the
calibrations that record fisheye lenses (nerfstudio OPENCV_FISHEYE, Kalibr equidistant,
Ego-Exo4D's gopro_calibs.csv) imported with fisheye frames and reconstructed."""

from __future__ import annotations

import csv
import json

import cv2
import numpy as np
import pytest

from edgerecon.cli import main
from edgerecon.geometry.lens import FisheyeLens, Rectification
from edgerecon.io import FrameSpec, load_rig, open_dataset, read_ply
from edgerecon.io.calib_egoexo import egoexo_calibration
from edgerecon.io.calibration import detect_calibration_format, load_calibration
from edgerecon.quality import evaluate_clouds
from edgerecon.synth import GroundTruth
from edgerecon.types import CalibrationError
from tests.io.test_importer import reconstruct_score

D = np.array([0.03, -0.01, 0.004, -0.001])  # k1..k4: a mild action-camera lens


@pytest.fixture(scope="module")
def scene(tiny_dataset):
    ds = open_dataset(tiny_dataset)
    return ds, GroundTruth.open(tiny_dataset)


def _lens(cam, scale: float = 1.0) -> FisheyeLens:
    """A fisheye lens whose rectified pinhole view lies inside the camera's own view (the
    synthetic frames have nothing outside it)."""
    K = cam.K.copy()
    K[0, 0] *= 1.15
    K[1, 1] *= 1.15
    return FisheyeLens(width=cam.width, height=cam.height, K=K, D=D).resized(
        round(cam.width * scale), round(cam.height * scale)
    )


def _fisheye_frame(image: np.ndarray, cam, lens: FisheyeLens) -> np.ndarray:
    """What the lens would have seen: each fisheye pixel's ray looked up in the pinhole view."""
    pinhole = cam.undistorted()
    ys, xs = np.mgrid[0 : lens.height, 0 : lens.width].astype(np.float64)
    pts = np.stack([xs.ravel(), ys.ravel()], axis=1).reshape(-1, 1, 2)
    rays = cv2.fisheye.undistortPoints(pts, lens.K, lens.D).reshape(-1, 2)
    u = pinhole.K[0, 0] * rays[:, 0] + pinhole.K[0, 2]
    v = pinhole.K[1, 1] * rays[:, 1] + pinhole.K[1, 2]
    shape = (lens.height, lens.width)
    return cv2.remap(
        cam.prepare_image(image),
        u.reshape(shape).astype(np.float32),
        v.reshape(shape).astype(np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
    )


def _fisheye_frames(ds, tmp_path, scale: float = 1.0) -> dict[str, str]:
    """Every camera's frames as its fisheye lens would have filmed them (image folders)."""
    folders = {}
    with ds.open_frames() as src:
        for t in range(ds.num_frames):
            fs = src.read(t)
            for cam, image in zip(ds.rig, fs.images, strict=True):
                folder = tmp_path / "fisheye" / cam.name
                folder.mkdir(parents=True, exist_ok=True)
                lens = _lens(cam)
                cv2.imwrite(str(folder / f"{t:06d}.png"), _fisheye_frame(image, cam, lens))
                folders[cam.name] = str(folder)
    return folders


def test_lens_resized_projects_like_the_image_resized():
    lens = FisheyeLens(width=640, height=480, K=[[300, 0, 320.5], [0, 301, 239], [0, 0, 1]], D=D)
    half = lens.resized(320, 240)
    pts = np.array([[[0.3, -0.2, 1.0]], [[-0.8, 0.5, 1.0]]])
    a, _ = cv2.fisheye.projectPoints(pts, np.zeros(3), np.zeros(3), lens.K, lens.D)
    b, _ = cv2.fisheye.projectPoints(pts, np.zeros(3), np.zeros(3), half.K, half.D)
    np.testing.assert_allclose((a.reshape(-1, 2) + 0.5) * 0.5 - 0.5, b.reshape(-1, 2), atol=1e-9)
    with pytest.raises(CalibrationError, match="4 coefficients"):
        FisheyeLens(width=10, height=10, K=np.eye(3), D=[0.1, 0.2])


def test_rectified_frames_are_the_pinhole_view(scene, tmp_path):
    ds, _ = scene
    cam = ds.rig.cameras[1]
    lens = _lens(cam)
    with ds.open_frames() as src:
        image = src.read(4).images[1]
    fisheye = _fisheye_frame(image, cam, lens)
    rect = Rectification(lens=lens, K=lens.pinhole_K())
    got = rect(fisheye)
    # The same view by a homography from the original pinhole frame (both cameras are pinhole
    # with one centre): x_pinhole = K_pin K_rect^-1 x_rect.
    H = cam.undistorted().K @ np.linalg.inv(rect.K)
    want = cv2.warpPerspective(
        cam.prepare_image(image), H, cam.size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    )
    inner = (slice(12, -12), slice(12, -12))
    diff = np.abs(got[inner].astype(float) - want[inner].astype(float))
    assert np.median(diff) < 4 and np.mean(diff) < 8, (np.median(diff), np.mean(diff))
    # The frame source applies it; the spec round-trips through dataset.json.
    cv2.imwrite(str(tmp_path / "f.png"), fisheye)
    spec = FrameSpec(
        kind="images", cameras=(("c", str(tmp_path / "f.png")),), rectify=(("c", rect),)
    )
    with spec.open() as src:
        assert np.abs(src.read(0).images[0].astype(int) - got.astype(int)).max() <= 1


def test_live_fisheye_streams_are_rectified(scene):
    from edgerecon.io.mjpeg import MjpegServer
    from edgerecon.io.streams import StreamConfig

    ds, _ = scene
    cams = list(ds.rig)[:3]
    with ds.open_frames() as src:
        pinhole = src.read(2).images[:3]
    lenses = [_lens(c) for c in cams]
    frames = [
        _fisheye_frame(im, c, lens) for im, c, lens in zip(pinhole, cams, lenses, strict=True)
    ]
    rects = {
        c.name: Rectification(lens=lens, K=lens.pinhole_K())
        for c, lens in zip(cams, lenses, strict=True)
    }
    names = [c.name for c in cams]

    def still(camera: int, tick: int) -> np.ndarray:
        return frames[camera]

    server = MjpegServer(still, names, fps=10.0).start()
    try:
        spec = FrameSpec(
            kind="stream",
            cameras=tuple((n, server.url(n)) for n in names),
            stream=StreamConfig(sync_tolerance_s=0.2, max_wait_s=2.0),
            fps=10.0,
            rectify=tuple(rects.items()),
        )
        with spec.open() as live:
            got = live.read(0).images
    finally:
        server.stop()
    for name, image, fisheye in zip(names, got, frames, strict=True):
        want = rects[name](fisheye)
        assert image is not None and image.shape == want.shape
        # Through JPEG: within a few grey levels of the rectified frame.
        assert np.median(np.abs(image.astype(int) - want.astype(int))) <= 4


def _write_egoexo_csv(path, rig, lenses) -> None:
    """gopro_calibs.csv as Ego-Exo4D ships it (camera -> world pose, KB3 intrinsics)."""
    header = [
        "cam_uid", "source", "tx_world_cam", "ty_world_cam", "tz_world_cam", "qx_world_cam",
        "qy_world_cam", "qz_world_cam", "qw_world_cam", "image_width", "image_height",
        "intrinsics_type", *[f"intrinsics_{k}" for k in range(8)], "quality",
    ]  # fmt: skip
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        for cam in rig:
            lens = lenses[cam.name]
            R_wc = cam.R.T
            qw = np.sqrt(max(0.0, 1 + np.trace(R_wc))) / 2
            qx = (R_wc[2, 1] - R_wc[1, 2]) / (4 * qw)
            qy = (R_wc[0, 2] - R_wc[2, 0]) / (4 * qw)
            qz = (R_wc[1, 0] - R_wc[0, 1]) / (4 * qw)
            K = lens.K
            w.writerow(
                [cam.name, "hand_eye", *cam.center, qx, qy, qz, qw, lens.width, lens.height,
                 "KANNALABRANDTK3", K[0, 0], K[1, 1], K[0, 2], K[1, 2], *lens.D, 1.0]
            )  # fmt: skip


def test_import_egoexo_fisheye_calibrated_at_twice_the_size(scene, tmp_path, capsys):
    # Ego-Exo4D calibrates at the native 4K and ships downscaled copies too: here the lens
    # is calibrated at 2x the frames' size, the import rescales it.
    ds, gt = scene
    lenses = {c.name: _lens(c, scale=2.0) for c in ds.rig}
    take = tmp_path / "take" / "trajectory"
    take.mkdir(parents=True)
    _write_egoexo_csv(take / "gopro_calibs.csv", ds.rig, lenses)
    assert detect_calibration_format(take.parent) == "egoexo"
    cal = egoexo_calibration(take.parent)
    assert sorted(cal.lenses) == sorted(ds.rig.names)
    with pytest.raises(CalibrationError, match="have fisheye lenses"):
        load_rig(take / "gopro_calibs.csv")
    frames = _fisheye_frames(ds, tmp_path)
    out = tmp_path / "ds"
    sources = [f"{n}={p}" for n, p in frames.items()]
    assert main(["import", str(take / "gopro_calibs.csv"), *sources, "-o", str(out), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["calibration_format"] == "egoexo"
    assert any("fisheye lenses" in n for n in report["notes"])
    assert any("the fisheye lens rescaled" in n for n in report["notes"])
    descriptor = json.loads((out / "dataset.json").read_text())
    assert sorted(descriptor["frames"]["rectify"]) == sorted(ds.rig.names)
    imported = open_dataset(out)
    for cam in imported.rig:
        assert not cam.has_distortion
        want = _lens(ds.rig.cameras[ds.rig.index(cam.name)]).pinhole_K()
        np.testing.assert_allclose(cam.K, want, rtol=1e-6, atol=1e-6)
    assert main(["info", "--dataset", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert sorted(info["lenses"]) == sorted(ds.rig.names)
    np.testing.assert_allclose(info["lenses"]["cam0"]["D"], D)
    score = reconstruct_score(out, tmp_path, gt)
    assert score.precision > 0.85 and score.num_pred > 150, score


def test_import_nerfstudio_fisheye(scene, tmp_path, capsys):
    ds, gt = scene
    frames = _fisheye_frames(ds, tmp_path)
    out_frames = []
    for cam in ds.rig:
        lens = _lens(cam)
        c2w = np.eye(4)
        c2w[:3, :3], c2w[:3, 3] = cam.R.T @ np.diag([1.0, -1.0, -1.0]), cam.center
        k1, k2, k3, k4 = lens.D
        out_frames.append(
            {"file_path": f"images/{cam.name}.png", "fl_x": lens.K[0, 0], "fl_y": lens.K[1, 1],
             "cx": lens.K[0, 2], "cy": lens.K[1, 2], "w": lens.width, "h": lens.height,
             "k1": k1, "k2": k2, "k3": k3, "k4": k4, "transform_matrix": c2w.tolist()}
        )  # fmt: skip
    root = tmp_path / "ns"
    root.mkdir()
    data = {"camera_model": "OPENCV_FISHEYE", "frames": out_frames}
    (root / "transforms.json").write_text(json.dumps(data))
    cal = load_calibration(root)
    assert sorted(cal.lenses) == sorted(ds.rig.names)
    out = tmp_path / "ds"
    sources = [f"{n}={p}" for n, p in frames.items()]
    assert main(["import", str(root), *sources, "-o", str(out), "--json"]) == 0
    capsys.readouterr()
    score = reconstruct_score(out, tmp_path, gt)
    assert score.precision > 0.85 and score.num_pred > 150, score


def test_kalibr_equidistant_cameras_come_with_their_lenses(scene, tmp_path):
    from edgerecon.io.calib_kalibr import kalibr_calibration
    from tests.io.test_calib_kalibr import _camchain

    ds, _ = scene
    text = _camchain(ds.rig, distortion="equidistant")
    path = tmp_path / "camchain.yaml"
    path.write_text(text)
    cal = kalibr_calibration(path)
    assert sorted(cal.lenses) == [f"cam{n}" for n in range(len(ds.rig))]
    for n, cam in enumerate(ds.rig):
        lens = cal.lenses[f"cam{n}"]
        np.testing.assert_allclose(lens.K, cam.K, atol=1e-9)
        np.testing.assert_allclose(lens.D, np.ravel(cam.dist)[:4], atol=1e-12)
        pin = cal.rig.cameras[n]
        np.testing.assert_allclose(pin.K, lens.pinhole_K(), atol=1e-9)
        assert not pin.has_distortion


def test_aniposelib_fisheye_camera_comes_with_its_lens(tmp_path):
    from edgerecon.io.calib_toml import toml_calibration
    from tests.conftest import ring_rig
    from tests.io.test_importer import anipose_toml

    rig = ring_rig(3)
    text = anipose_toml(rig)
    # aniposelib's FisheyeCamera: ``fisheye = true`` and 4 coefficients (k1..k4).
    text = text.replace("[cam_0]\n", "[cam_0]\nfisheye = true\n", 1)
    lines = text.splitlines()
    first = next(i for i, ln in enumerate(lines) if ln.startswith("distortions"))
    lines[first] = "distortions = [0.03, -0.01, 0.004, -0.001]"
    path = tmp_path / "calibration.toml"
    path.write_text("\n".join(lines) + "\n")
    cal = toml_calibration(path)
    assert list(cal.lenses) == [rig.names[0]]
    np.testing.assert_allclose(cal.lenses[rig.names[0]].D, D)
    assert not cal.rig.cameras[0].has_distortion
    np.testing.assert_allclose(cal.rig.cameras[1].K, rig.cameras[1].K)


def test_colmap_opencv_fisheye_comes_with_its_lens(scene, tmp_path, capsys):
    from edgerecon.io.colmap import rotation_to_quaternion

    ds, _ = scene
    cams, imgs = [], []
    for k, cam in enumerate(ds.rig, start=1):
        lens = _lens(cam)
        params = [lens.K[0, 0], lens.K[1, 1], lens.K[0, 2] + 0.5, lens.K[1, 2] + 0.5, *lens.D]
        cams.append(
            f"{k} OPENCV_FISHEYE {cam.width} {cam.height} "
            + " ".join(repr(float(v)) for v in params)
        )
        q = rotation_to_quaternion(cam.R)
        imgs += [f"{k} {' '.join(repr(float(v)) for v in (*q, *cam.t))} {k} {cam.name}.png", ""]
    (tmp_path / "cameras.txt").write_text("\n".join(cams) + "\n")
    (tmp_path / "images.txt").write_text("\n".join(imgs) + "\n")
    (tmp_path / "points3D.txt").write_text("")
    cal = load_calibration(tmp_path)
    assert sorted(cal.lenses) == sorted(ds.rig.names)
    for cam in ds.rig:
        np.testing.assert_allclose(cal.lenses[cam.name].K, _lens(cam).K, atol=1e-9)
        got = cal.rig.cameras[cal.rig.index(cam.name)]
        np.testing.assert_allclose(got.R, cam.R, atol=1e-9)
        assert not got.has_distortion
    # COLMAP's own images as the frames (one per camera: the fisheye frames of time 3).
    images = tmp_path / "images"
    images.mkdir()
    with ds.open_frames() as src:
        for cam, image in zip(ds.rig, src.read(3).images, strict=True):
            cv2.imwrite(str(images / f"{cam.name}.png"), _fisheye_frame(image, cam, _lens(cam)))
    out = tmp_path / "ds"
    args = ["import", str(tmp_path), "--images", str(images), "-o", str(out), "--json"]
    assert main(args) == 0
    capsys.readouterr()
    rec = tmp_path / "rec"
    assert (
        main(["reconstruct", "--dataset", str(out), "-t", "0", "--no-dense", "-o", str(rec)]) == 0
    )
    cloud = read_ply(rec / "sparse.ply")
    truth = scene[1].reference_cloud(3, "all", min_views=2)
    score = evaluate_clouds(cloud.points3D, truth, 0.03)[0]
    assert score.precision > 0.85 and score.num_pred > 150, score
    # Back to COLMAP with the frames as filmed: OPENCV_FISHEYE cameras, the points' pixels
    # where the lens put them.
    from edgerecon.io.colmap import quaternion_to_rotation, read_colmap_model

    ws = tmp_path / "ws"
    assert main(["export", str(rec), "--distorted", "--cloud", "sparse", "-o", str(ws)]) == 0
    model = read_colmap_model(ws / "sparse")
    assert {c.model for c in model.cameras.values()} == {"OPENCV_FISHEYE"}
    checked = 0
    for image in model.images.values():
        cam = model.cameras[image.camera_id]
        written = cv2.imread(str(ws / "images" / image.name))
        filmed = cv2.imread(str(images / image.name))
        assert np.array_equal(written, filmed)
        seen = image.point3D_ids >= 0
        index = {int(i): k for k, i in enumerate(model.points3D.ids)}
        xyz = model.points3D.xyz[[index[int(i)] for i in image.point3D_ids[seen]]]
        R = quaternion_to_rotation(image.qvec)
        fx, fy, cx, cy = cam.params[:4]
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
        proj, _ = cv2.fisheye.projectPoints(
            xyz.reshape(-1, 1, 3), cv2.Rodrigues(R)[0], image.tvec, K, cam.params[4:8]
        )
        np.testing.assert_allclose(proj.reshape(-1, 2), image.points2D[seen], atol=1e-3)
        checked += int(seen.sum())
    assert checked > 100


def test_malformed_lenses_are_calibration_errors(scene, tmp_path):
    ds, _ = scene
    good = {c.name: _lens(c) for c in ds.rig}
    path = tmp_path / "gopro_calibs.csv"
    _write_egoexo_csv(path, ds.rig, good)
    rows = list(csv.reader(open(path)))
    col = rows[0].index("image_width")
    for value, match in (("1e308", "between 1 and 65535"), ("x", "not a number"), ("0", "between")):
        bad = [list(r) for r in rows]
        bad[2][col] = value
        with open(path, "w", newline="") as f:
            csv.writer(f).writerows(bad)
        with pytest.raises(CalibrationError, match=match):
            load_calibration(path)
    with pytest.raises(CalibrationError, match="fold the image back|no pinhole view"):
        FisheyeLens(width=640, height=480, K=np.diag([300.0, 300, 1]), D=[-5, 0, 0, 0]).pinhole_K()
