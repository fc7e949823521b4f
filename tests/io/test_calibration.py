"""Calibration importers: known answers on real rigs, exact round trips, every error path."""

from __future__ import annotations

import dataclasses
import json
import logging

import cv2
import numpy as np
import pytest

from edgerecon.geometry import Camera, Rig, look_at
from edgerecon.io import (
    detect_calibration_format,
    load_rig,
    open_frame_source,
    read_colmap_text,
    read_middlebury_par,
    read_opencv_camera_xml,
    read_opencv_xml_rig,
    read_openmvg_sfm_data,
    read_rig_json,
    save_rig,
    write_colmap_text,
)
from edgerecon.io.colmap import quaternion_to_rotation, rotation_to_quaternion
from edgerecon.types import CalibrationError
from tests.conftest import ring_rig, shared_data


def _random_rig(seed: int = 0) -> Rig:
    """Cameras with awkward float values (full 53-bit mantissas) and every distortion shape."""
    rng = np.random.default_rng(seed)
    dists = [
        np.zeros(5),
        np.array([-0.2, 0.05, 0.0, 0.0, 0.0]) + rng.normal(0, 1e-3, 5) * [1, 1, 0, 0, 0],
        rng.normal(0, 0.05, 5),
        np.array([0.1, -0.01, 1e-4, -2e-4, 0.0]),
    ]
    cams = []
    for i, dist in enumerate(dists):
        a = 2 * np.pi * i / len(dists) + rng.uniform(0, 0.3)
        center = (4 * np.cos(a) + rng.normal(), 4 * np.sin(a), 1.5 + rng.normal(0, 0.1))
        R, t = look_at(center, rng.normal(0, 0.2, 3))
        K = np.array(
            [
                [rng.uniform(400, 900), 0.0, rng.uniform(300, 340)],
                [0.0, rng.uniform(400, 900), rng.uniform(230, 250)],
                [0.0, 0.0, 1.0],
            ]
        )
        cams.append(Camera(name=f"cam{i}", width=640, height=480, K=K, R=R, t=t, dist=dist))
    return Rig(cameras=tuple(cams), unit="mm", up=(0.0, 0.0, -1.0))


# ================================================================== edgerecon rig JSON
def test_rig_json_round_trip_is_bit_identical(tmp_path):
    rig = _random_rig()
    path = save_rig(tmp_path / "rig.json", rig)
    back = read_rig_json(path)
    assert back == rig  # Camera equality is np.array_equal: exact
    for a, b in zip(rig, back, strict=True):
        for field in ("K", "R", "t", "dist"):
            assert getattr(a, field).tobytes() == getattr(b, field).tobytes()
    assert back.unit == "mm" and back.up == (0.0, 0.0, -1.0)
    assert load_rig(tmp_path) == rig  # a folder with rig.json
    assert detect_calibration_format(path) == "edgerecon"


def test_rig_json_errors_name_file_and_camera(tmp_path):
    rig = ring_rig(3)
    path = save_rig(tmp_path / "rig.json", rig)
    data = json.loads(path.read_text())
    data["cameras"][1]["R"] = (np.array(data["cameras"][1]["R"]) * 1.01).tolist()
    path.write_text(json.dumps(data))
    with pytest.raises(CalibrationError, match=r"rig\.json.*'cam1'.*not orthonormal"):
        read_rig_json(path)
    data = json.loads(save_rig(path, rig).read_text())
    data["cameras"][2]["K"][0][0] = -5.0
    path.write_text(json.dumps(data))
    with pytest.raises(CalibrationError, match=r"rig\.json.*'cam2'.*focal"):
        read_rig_json(path)
    data = json.loads(save_rig(path, rig).read_text())
    del data["cameras"][0]["t"]
    path.write_text(json.dumps(data))
    with pytest.raises(CalibrationError, match=r"rig\.json.*'cam0'.*missing field 't'"):
        read_rig_json(path)
    data = json.loads(save_rig(path, rig).read_text())
    data["cameras"] = data["cameras"][:2]
    path.write_text(json.dumps(data))
    with pytest.raises(CalibrationError, match=r"rig\.json.*at least 3 cameras"):
        read_rig_json(path)
    path.write_text("{")
    with pytest.raises(CalibrationError, match=r"rig\.json.*not valid JSON"):
        read_rig_json(path)
    with pytest.raises(CalibrationError, match="not found"):
        read_rig_json(tmp_path / "absent.json")
    with pytest.raises(CalibrationError, match="not found"):
        load_rig(tmp_path / "absent")


def test_load_rig_checks_given_image_sizes(tmp_path):
    rig = ring_rig(3, width=640, height_px=480)
    save_rig(tmp_path / "rig.json", rig)
    assert load_rig(tmp_path / "rig.json", image_sizes=(640, 480)) == rig
    with pytest.raises(CalibrationError, match=r"rig\.json.*'cam1'.*640x480.*800x600"):
        load_rig(tmp_path / "rig.json", image_sizes={"cam1": (800, 600)})


# ================================================================== openMVG
def test_dance1_openmvg_known_values():
    rig = load_rig(shared_data("dance1_calibration") / "sfm_data_dance.json")
    assert len(rig) == 7
    assert rig.names == ["000", "001", "002", "003", "004", "005", "006"]
    cam = rig[0]
    assert (cam.width, cam.height) == (1920, 1080)
    assert cam.K[0, 0] == pytest.approx(1719.71, abs=0.01)
    assert cam.K[1, 1] == cam.K[0, 0]
    assert cam.K[0, 2] == pytest.approx(937.80, abs=0.01)
    assert cam.K[1, 2] == pytest.approx(550.22, abs=0.01)
    assert cam.dist[0] == pytest.approx(-0.2201, abs=1e-4)
    assert cam.dist[2] == 0 and cam.dist[3] == 0  # radial_k3: no tangential terms
    assert cam.dist[4] == pytest.approx(-0.03824, abs=1e-5)
    np.testing.assert_allclose(cam.center, [0.2713, -0.0131, 0.0541], atol=1e-4)
    # World -> camera: a point 2 units in front of the camera, slightly off axis, projects
    # where the radial_k3 model (computed here by hand) puts it.
    X = cam.center + cam.R.T @ np.array([0.5, 0.2, 2.0])
    x, y = 0.25, 0.1
    r2 = x * x + y * y
    k1, k2, k3 = -0.22012463848193117, 0.2721659929712592, -0.03824374956472778
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    uv, depth = cam.project(X[None])
    assert depth[0] == pytest.approx(2.0)
    np.testing.assert_allclose(
        uv[0],
        [
            1719.7149990133414 * x * radial + 937.7951606151249,
            1719.7149990133414 * y * radial + 550.2183173432093,
        ],
        atol=1e-9,
    )
    # The whole arc faces the same way: every centre is in front of camera 3.
    _, depths = rig[3].project(rig.centers[[0, 6]] + 5 * rig[3].R[2])
    assert np.all(depths > 0)


def _sfm_data(intrinsics, views, extrinsics):
    return {
        "sfm_data_version": "0.3",
        "root_path": "/x",
        "views": views,
        "intrinsics": intrinsics,
        "extrinsics": extrinsics,
        "structure": [],
        "control_points": [],
    }


def _view(key, filename, id_pose, id_intrinsic=0):
    return {
        "key": key,
        "value": {
            "polymorphic_id": 1073741824,
            "ptr_wrapper": {
                "id": 2147483649 + key,
                "data": {
                    "local_path": "",
                    "filename": filename,
                    "width": 800,
                    "height": 600,
                    "id_view": key,
                    "id_intrinsic": id_intrinsic,
                    "id_pose": id_pose,
                },
            },
        },
    }


def _pose(key, R, C):
    return {"key": key, "value": {"rotation": np.asarray(R).tolist(), "center": list(C)}}


def _brown_sfm(tmp_path, t1, t2, n_views=4, drop_pose=None):
    intrinsics = [
        {
            "key": 0,
            "value": {
                "polymorphic_id": 2147483649,
                "polymorphic_name": "pinhole_brown_t2",
                "ptr_wrapper": {
                    "id": 2147483700,
                    "data": {
                        "width": 800,
                        "height": 600,
                        "focal_length": 700.0,
                        "principal_point": [401.0, 299.0],
                        "disto_t2": [-0.1, 0.02, 0.001, t1, t2],
                    },
                },
            },
        },
        # Second use of the same polymorphic type: cereal writes no name, only the id.
        {
            "key": 1,
            "value": {
                "polymorphic_id": 1,
                "ptr_wrapper": {
                    "id": 2147483701,
                    "data": {
                        "width": 800,
                        "height": 600,
                        "focal_length": 650.0,
                        "principal_point": [400.0, 300.0],
                        "disto_t2": [0.0, 0.0, 0.0, 0.0, 0.0],
                    },
                },
            },
        },
    ]
    views, poses = [], []
    for k in range(n_views):
        a = 2 * np.pi * k / n_views
        R, t = look_at((3 * np.cos(a), 3 * np.sin(a), 1.0), (0, 0, 0))
        views.append(_view(k, f"view_{k}.jpg", k, id_intrinsic=k % 2))
        if k != drop_pose:
            poses.append(_pose(k, R, -R.T @ t))
    path = tmp_path / "sfm_data.json"
    path.write_text(json.dumps(_sfm_data(intrinsics, views, poses)))
    return path


def _openmvg_brown(x, y, k1, k2, k3, t1, t2):
    """openMVG's Pinhole_Intrinsic_Brown_T2 distortion, written out independently."""
    r2 = x * x + y * y
    kd = k1 * r2 + k2 * r2**2 + k3 * r2**3
    tx = t2 * (r2 + 2 * x * x) + 2 * t1 * x * y
    ty = t1 * (r2 + 2 * y * y) + 2 * t2 * x * y
    return x + x * kd + tx, y + y * kd + ty


def test_openmvg_brown_t2_matches_openmvg_model(tmp_path):
    t1, t2 = 0.004, -0.007
    rig = read_openmvg_sfm_data(_brown_sfm(tmp_path, t1, t2))
    assert rig.names == ["view_0", "view_1", "view_2", "view_3"]
    cam = rig[0]
    np.testing.assert_array_equal(cam.dist, [-0.1, 0.02, t1, t2, 0.001])
    assert rig[1].K[0, 0] == 650.0 and not rig[1].has_distortion
    xc = np.array([[0.3, -0.2, 1.0], [-0.4, 0.35, 2.0], [0.05, 0.1, 1.5]])
    X = (xc - cam.t) @ cam.R  # camera frame -> world
    uv, _ = cam.project(X)
    xd, yd = _openmvg_brown(xc[:, 0] / xc[:, 2], xc[:, 1] / xc[:, 2], -0.1, 0.02, 0.001, t1, t2)
    np.testing.assert_allclose(uv, np.stack([700 * xd + 401, 700 * yd + 299], 1), atol=1e-9)
    # And the swapped assignment would be wrong by many pixels (the test can fail).
    swapped = dataclasses.replace(cam, dist=cam.dist[[0, 1, 3, 2, 4]])
    assert np.abs(swapped.project(X)[0] - uv).max() > 1.0


def test_openmvg_views_without_pose_are_skipped(tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="edgerecon.io.calibration"):
        rig = read_openmvg_sfm_data(_brown_sfm(tmp_path, 0, 0, n_views=4, drop_pose=2))
    assert rig.names == ["view_0", "view_1", "view_3"]
    assert "view 2 (view_2.jpg) has no pose" in caplog.text
    with pytest.raises(CalibrationError, match=r"sfm_data\.json.*at least 3 cameras"):
        read_openmvg_sfm_data(_brown_sfm(tmp_path, 0, 0, n_views=3, drop_pose=0))


def test_openmvg_names_fall_back_to_view_keys(tmp_path):
    path = _brown_sfm(tmp_path, 0, 0)
    data = json.loads(path.read_text())
    for k, view in enumerate(data["views"]):
        view["value"]["ptr_wrapper"]["data"]["filename"] = f"take{k % 2}/frame.png"
    path.write_text(json.dumps(data))
    assert read_openmvg_sfm_data(path).names == ["cam0", "cam1", "cam2", "cam3"]


def test_openmvg_errors(tmp_path):
    path = _brown_sfm(tmp_path, 0, 0)
    data = json.loads(path.read_text())
    data["intrinsics"][0]["value"]["polymorphic_name"] = "fisheye"
    path.write_text(json.dumps(data))
    with pytest.raises(CalibrationError, match=r"sfm_data\.json.*unsupported openMVG.*'fisheye'"):
        read_openmvg_sfm_data(path)
    data = json.loads(_brown_sfm(tmp_path, 0, 0).read_text())
    del data["intrinsics"][0]["value"]["ptr_wrapper"]["data"]["focal_length"]
    path.write_text(json.dumps(data))
    with pytest.raises(CalibrationError, match="missing field 'focal_length'"):
        read_openmvg_sfm_data(path)
    data = json.loads(_brown_sfm(tmp_path, 0, 0).read_text())
    data["intrinsics"][0]["value"]["ptr_wrapper"]["data"]["focal_length"] = 0.0
    path.write_text(json.dumps(data))
    with pytest.raises(CalibrationError, match=r"sfm_data\.json.*'view_0'.*focal"):
        read_openmvg_sfm_data(path)
    data = json.loads(_brown_sfm(tmp_path, 0, 0).read_text())
    data["extrinsics"][1]["value"]["rotation"][0][0] += 0.1
    path.write_text(json.dumps(data))
    with pytest.raises(CalibrationError, match=r"sfm_data\.json.*'view_1'.*orthonormal"):
        read_openmvg_sfm_data(path)
    data = json.loads(_brown_sfm(tmp_path, 0, 0).read_text())
    data["views"][2]["value"]["ptr_wrapper"]["data"]["id_intrinsic"] = 7
    path.write_text(json.dumps(data))
    with pytest.raises(CalibrationError, match=r"'view_2'.*intrinsic 7"):
        read_openmvg_sfm_data(path)


# ================================================================== OpenCV XML (utrecht4cam)
UTRECHT_CENTERS_MM = {
    "cam1": (3485, 4446, -1803),
    "cam2": (314, 4607, -1683),
    "cam3": (-3480, 139, -2107),
    "cam4": (-3040, 4143, -1651),
}


def test_utrecht_rig_centres_and_conventions():
    root = shared_data("utrecht4cam")
    rig = load_rig(root)  # image sizes come from camN/video.avi
    assert detect_calibration_format(root) == "opencv-xml"
    assert rig.names == ["cam1", "cam2", "cam3", "cam4"]
    assert rig.unit == "mm" and rig.up == (0.0, 0.0, -1.0)
    for cam in rig:
        assert cam.size == (644, 486)
        np.testing.assert_allclose(cam.center, UTRECHT_CENTERS_MM[cam.name], atol=1.0)
        # Z points down: every camera hangs above the floor (negative z) and sees the board
        # origin on the floor in front of it, inside the image.
        assert cam.center[2] < -1500
        uv, depth = cam.project(np.zeros((1, 3)))
        assert depth[0] > 0 and cam.in_image(uv)[0]
    cam1 = rig[0]
    np.testing.assert_allclose(cam1.t, [289.02691777857865, 1008.0364772390549, 5836.3675632258164])
    np.testing.assert_allclose(
        cam1.R,
        cv2.Rodrigues(np.array([-1.3729877816020433, 0.49613357894194315, 0.61391054843037529]))[0],
    )
    np.testing.assert_allclose(cam1.K[0], [490.756439, 0, 334.690674], rtol=1e-7)
    np.testing.assert_allclose(
        cam1.dist,
        [-0.368704915, 0.203186616, 3.26540467e-04, 1.78072587e-05, -7.12014362e-02],
        rtol=1e-6,
    )


def _detect_board(gray):
    ok, corners = cv2.findChessboardCornersSB(gray, (8, 6))
    if not ok:
        ok, corners = cv2.findChessboardCorners(gray, (8, 6))
    if not ok:
        return None
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 0.001)
    return cv2.cornerSubPix(gray, corners, (3, 3), (-1, -1), crit).reshape(-1, 2)


def _triangulate(a, b, ua, ub):
    X = cv2.triangulatePoints(
        a.cam_from_world, b.cam_from_world, a.pixel_rays(ua)[:, :2].T, b.pixel_rays(ub)[:, :2].T
    )
    return (X[:3] / X[3]).T


def _board_ncc_shift(cam, gray, origin, ex, ey, max_shift=6):
    """Render the board (9x7 squares around the 8x6 inner corners origin + i ex + j ey) into
    ``cam`` by casting each pixel's ray onto the board plane, then find the pixel shift that
    best correlates the rendering with the image. Returns (|NCC|, dx, dy)."""
    normal = np.cross(ex, ey)
    normal /= np.linalg.norm(normal)
    outline = origin + np.array([[-1, -1], [8, -1], [8, 6], [-1, 6]]) @ np.stack([ex, ey])
    uv, _ = cam.project(outline)
    lo = np.floor(uv.min(0)).astype(int) - max_shift
    hi = np.ceil(uv.max(0)).astype(int) + max_shift
    xs, ys = np.meshgrid(np.arange(lo[0], hi[0]), np.arange(lo[1], hi[1]))
    rays = cam.pixel_rays(np.stack([xs.ravel(), ys.ravel()], 1).astype(float)) @ cam.R
    lam = ((origin - cam.center) @ normal) / (rays @ normal)
    hit = cam.center + lam[:, None] * rays - origin
    bc = np.linalg.lstsq(np.stack([ex, ey], 1), hit.T, rcond=None)[0].T
    inside = ((bc[:, 0] > -0.8) & (bc[:, 0] < 7.8) & (bc[:, 1] > -0.8) & (bc[:, 1] < 5.8)).reshape(
        xs.shape
    )
    pattern = (np.floor(bc[:, 0]) + np.floor(bc[:, 1])) % 2
    pattern = pattern.reshape(xs.shape)[inside]
    best = (-1.0, 0, 0)
    for dy in range(-max_shift, max_shift + 1):
        for dx in range(-max_shift, max_shift + 1):
            yy = np.clip(ys + dy, 0, gray.shape[0] - 1)
            xx = np.clip(xs + dx, 0, gray.shape[1] - 1)
            ncc = abs(np.corrcoef(pattern, gray[yy, xx][inside].astype(float))[0, 1])
            best = max(best, (ncc, dx, dy))
    return best


def test_utrecht_board_reprojects_in_all_cameras():
    """The calibration puts the checkerboard of checkerboard.avi where every camera sees it.

    cam2 and cam3 detect the 8x6 inner corners; triangulated with the calibration they must
    agree (sub-pixel reprojection) and lie on the floor z = 0. cam1 and cam4 see the board too
    obliquely for the corner detector: there the board triangulated from cam2 + cam3 is
    rendered into the image and must line up with the real one within a pixel or two
    (normalised cross-correlation peak). A wrong convention (R transposed, t off by 50 mm,
    distortion dropped) moves that peak or destroys it.
    """
    root = shared_data("utrecht4cam")
    rig = load_rig(root)
    with open_frame_source(
        "video", {c.name: root / c.name / "checkerboard.avi" for c in rig}, rig=rig
    ) as src:
        frames = src.read(0)
    gray = [cv2.cvtColor(im, cv2.COLOR_BGR2GRAY) for im in frames.images]
    u2, u3 = _detect_board(gray[1]), _detect_board(gray[2])
    assert u2 is not None and u3 is not None
    # Corner order is ambiguous up to a 180 degree turn: keep the consistent pairing.
    candidates = []
    for u3o in (u3, u3[::-1]):
        X = _triangulate(rig[1], rig[2], u2, u3o)
        err = max(
            np.linalg.norm(c.project(X)[0] - u, axis=1).mean()
            for c, u in ((rig[1], u2), (rig[2], u3o))
        )
        candidates.append((err, X))
    err, X = min(candidates, key=lambda c: c[0])
    assert err < 1.0
    assert np.abs(X[:, 2]).max() < 30.0  # on the floor plane (mm)
    # The calibration's own 115 mm board frame projects onto the detected board.
    grid = np.array([[115.0 * i, 115.0 * j, 0.0] for j in range(6) for i in range(8)])
    for k, corners in ((1, u2), (2, u3)):
        hull = cv2.convexHull(corners.astype(np.float32))
        uv, _ = rig[k].project(grid)
        assert all(cv2.pointPolygonTest(hull, (float(u), float(v)), False) >= 0 for u, v in uv)
    # Board model: origin + i * ex + j * ey fitted to the triangulated corners.
    ij = np.array([[1.0, i, j] for j in range(6) for i in range(8)])
    origin, ex, ey = np.linalg.lstsq(ij, X, rcond=None)[0]
    for k in range(4):
        ncc, dx, dy = _board_ncc_shift(rig[k], gray[k], origin, ex, ey)
        assert ncc > 0.6, rig[k].name
        assert abs(dx) <= 2 and abs(dy) <= 2, (rig[k].name, dx, dy)
    # The same check rejects a camera moved by 50 mm or with a transposed rotation.
    cam1 = rig[0]
    moved = dataclasses.replace(cam1, t=cam1.t + [50.0, 0.0, 0.0])
    _, dx, dy = _board_ncc_shift(moved, gray[0], origin, ex, ey)
    assert max(abs(dx), abs(dy)) >= 3
    flipped = dataclasses.replace(rig[3], R=rig[3].R.T)
    assert _board_ncc_shift(flipped, gray[3], origin, ex, ey)[0] < 0.3


def _write_xml(path, K, dist, rvec, tvec):
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for key, value in (
        ("CameraMatrix", K),
        ("DistortionCoeffs", dist),
        ("Rotation", rvec),
        ("Translation", tvec),
    ):
        if value is not None:
            fs.write(key, np.asarray(value, dtype=np.float64))
    fs.release()


def _xml_rig_folder(tmp_path, n=3):
    rig = ring_rig(
        n, width=64, height_px=48, focal_px=60.0, dist=(-0.1, 0.01, 0.001, -0.002, 0.003)
    )
    for cam in rig:
        d = tmp_path / cam.name
        d.mkdir()
        _write_xml(d / "config.xml", cam.K, cam.dist[None], cv2.Rodrigues(cam.R)[0], cam.t[:, None])
    return rig


def test_opencv_xml_rig_needs_and_takes_image_sizes(tmp_path):
    rig = _xml_rig_folder(tmp_path)
    with pytest.raises(
        CalibrationError, match=r"'cam0'.*config\.xml has no image size.*image_sizes"
    ):
        read_opencv_xml_rig(tmp_path)
    back = read_opencv_xml_rig(tmp_path, (64, 48), unit="m", up=(0, 0, 1))
    for a, b in zip(rig, back, strict=True):
        assert a.name == b.name and a.size == b.size
        np.testing.assert_allclose(b.R, a.R, atol=1e-12)
        np.testing.assert_allclose(b.t, a.t, atol=1e-12)
        np.testing.assert_array_equal(b.K, a.K)
        np.testing.assert_array_equal(b.dist, a.dist)
    # A 3x3 rotation is accepted as well as a Rodrigues vector.
    cam = rig[0]
    _write_xml(tmp_path / "cam0" / "config.xml", cam.K, None, cam.R, cam.t)
    one = read_opencv_camera_xml(tmp_path / "cam0" / "config.xml", name="cam0", image_size=(64, 48))
    np.testing.assert_array_equal(one.R, cam.R)
    assert not one.has_distortion
    # An image next to each config.xml gives the size.
    for c in rig:
        cv2.imwrite(str(tmp_path / c.name / "000.png"), np.zeros((48, 64, 3), np.uint8))
    assert [c.size for c in load_rig(tmp_path)] == [(64, 48)] * 3


def test_opencv_xml_errors(tmp_path):
    rig = _xml_rig_folder(tmp_path)
    path = tmp_path / "cam1" / "config.xml"
    cam = rig[1]
    _write_xml(path, cam.K, cam.dist, None, cam.t)
    with pytest.raises(CalibrationError, match=r"'cam1'.*config\.xml.*no 'Rotation'"):
        read_opencv_xml_rig(tmp_path, (64, 48))
    K = cam.K.copy()
    K[1, 1] = -1.0
    _write_xml(path, K, cam.dist, cv2.Rodrigues(cam.R)[0], cam.t)
    with pytest.raises(CalibrationError, match=r"config\.xml.*'cam1'.*focal"):
        read_opencv_xml_rig(tmp_path, (64, 48))
    _write_xml(path, cam.K, cam.dist, np.eye(3) * 2, cam.t)
    with pytest.raises(CalibrationError, match=r"config\.xml.*'cam1'.*orthonormal"):
        read_opencv_xml_rig(tmp_path, (64, 48))
    _write_xml(path, cam.K, cam.dist, np.ones(4), cam.t)
    with pytest.raises(CalibrationError, match=r"'cam1'.*Rodrigues"):
        read_opencv_xml_rig(tmp_path, (64, 48))
    path.write_text("<?xml version='1.0'?><opencv_storage><CameraMatrix type_id=")
    with pytest.raises(CalibrationError, match=r"'cam1'.*config\.xml"):
        read_opencv_xml_rig(tmp_path, (64, 48))
    path.unlink()
    (tmp_path / "cam1").rmdir()
    with pytest.raises(CalibrationError, match="at least 3 cameras"):
        read_opencv_xml_rig(tmp_path, (64, 48))
    with pytest.raises(CalibrationError, match="no camera folders"):
        read_opencv_xml_rig(tmp_path / "cam0", (64, 48))


# ================================================================== Middlebury
TEMPLE_BBOX = np.array([[-0.073568, 0.021728, -0.012445], [0.028855, 0.181892, 0.062736]])


def test_middlebury_temple_known_values_and_bbox():
    root = shared_data("middlebury_templeSparseRing")
    rig = load_rig(root)
    assert detect_calibration_format(root) == "middlebury"
    assert len(rig) == 16 and rig.unit == "m"
    cam = rig[0]
    assert cam.name == "templeSR0001" and cam.size == (640, 480)
    np.testing.assert_array_equal(cam.K, [[1520.4, 0, 302.32], [0, 1525.9, 246.87], [0, 0, 1]])
    np.testing.assert_array_equal(
        cam.R[0], [0.02187598221295043, 0.98329680886213122, -0.18068986436368856]
    )
    np.testing.assert_array_equal(
        cam.R[2], [0.04883878372068499500, -0.18156839221560722, -0.98216479887691122]
    )
    np.testing.assert_array_equal(cam.t, [-0.0726637729648, 0.0223360353405, 0.614604845959])
    lo, hi = TEMPLE_BBOX
    corners = np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    )
    for c in rig:
        uv, depth = c.project(corners)
        assert np.all(depth > 0), c.name
        assert np.all(c.in_image(uv)), c.name


def test_middlebury_errors(tmp_path):
    line = "a.png 100 0 32 0 100 24 0 0 1 1 0 0 0 1 0 0 0 1 0 0 {}"
    rows = [line.format(z) for z in (1, 2, 3)]
    par = tmp_path / "x_par.txt"
    par.write_text("3\n" + "\n".join(r.replace("a.png", f"v{i}.png") for i, r in enumerate(rows)))
    with pytest.raises(CalibrationError, match=r"'v0'.*image size unknown.*v0\.png"):
        read_middlebury_par(par)
    rig = read_middlebury_par(par, (64, 48))
    assert rig.names == ["v0", "v1", "v2"] and rig[2].t[2] == 3.0
    par.write_text("4\n" + "\n".join(rows))
    with pytest.raises(CalibrationError, match=r"x_par\.txt.*declares 4 images but lists 3"):
        read_middlebury_par(par, (64, 48))
    par.write_text("3\n" + "\n".join(rows[:2]) + "\nb.png 1 2 3")
    with pytest.raises(CalibrationError, match=r"x_par\.txt.*line 4.*21 numbers"):
        read_middlebury_par(par, (64, 48))
    par.write_text("3\n" + "\n".join(rows[:2]) + "\n" + rows[2].replace(" 100 ", " x ", 1))
    with pytest.raises(CalibrationError, match=r"x_par\.txt.*'a'.*line 4"):
        read_middlebury_par(par, (64, 48))
    par.write_text(
        "3\n"
        + "\n".join(r.replace("a.png", f"v{i}.png") for i, r in enumerate(rows)).replace(
            " 0 0 1 1 0 0", " 0 0 1 2 0 0", 1
        )
    )
    with pytest.raises(CalibrationError, match=r"x_par\.txt.*'v0'.*orthonormal"):
        read_middlebury_par(par, (64, 48))
    par.write_text("three\n")
    with pytest.raises(CalibrationError, match="number of images"):
        read_middlebury_par(par, (64, 48))


# ================================================================== COLMAP
def test_colmap_round_trip(tmp_path):
    rig = _random_rig(3)
    write_colmap_text(tmp_path / "model", rig)
    assert detect_calibration_format(tmp_path / "model") == "colmap"
    back = load_rig(tmp_path / "model")
    assert back.names == rig.names and back.unit == "mm" and back.up == rig.up
    models = [
        ln.split()[1]
        for ln in (tmp_path / "model" / "cameras.txt").read_text().splitlines()
        if ln and ln[0] != "#"
    ]
    assert models == ["PINHOLE", "OPENCV", "FULL_OPENCV", "OPENCV"]
    for a, b in zip(rig, back, strict=True):
        assert a.size == b.size
        np.testing.assert_allclose(b.K, a.K, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(b.dist, a.dist)
        np.testing.assert_allclose(b.R, a.R, rtol=0, atol=1e-15)
        np.testing.assert_array_equal(b.t, a.t)
    # Writing the read-back rig again gives the same files (a fixed point).
    write_colmap_text(tmp_path / "again", back)
    for name in ("cameras.txt", "images.txt"):
        first = (tmp_path / "model" / name).read_text()
        again = (tmp_path / "again" / name).read_text()
        assert np.allclose(
            [float(w) for w in first.split() if _is_float(w)],
            [float(w) for w in again.split() if _is_float(w)],
            rtol=1e-15,
            atol=1e-15,
        )


def _is_float(word):
    try:
        float(word)
    except ValueError:
        return False
    return True


def _write_colmap(folder, cameras, images):
    folder.mkdir(exist_ok=True)
    (folder / "cameras.txt").write_text("# header\n" + "\n".join(cameras) + "\n")
    (folder / "images.txt").write_text("# header\n" + "\n".join(images) + "\n")


def _colmap_images(n=3, cam_ids=(1, 2, 3)):
    lines = []
    for i in range(n):
        a = 2 * np.pi * i / n
        R, t = look_at((3 * np.cos(a), 3 * np.sin(a), 1.0), (0, 0, 0))
        q = rotation_to_quaternion(R)
        lines.append(
            f"{i + 1} {' '.join(repr(float(v)) for v in [*q, *t])} {cam_ids[i]} img{i}.jpg"
        )
        lines.append("")  # no 2D points
    return lines


def test_colmap_known_answer_models(tmp_path):
    _write_colmap(
        tmp_path,
        [
            "1 SIMPLE_PINHOLE 640 480 500 320.5 240.5",
            "2 SIMPLE_RADIAL 640 480 510 321 241 -0.05",
            "3 RADIAL 640 480 520 322 242 -0.05 0.01",
        ],
        _colmap_images(),
    )
    rig = read_colmap_text(tmp_path / "images.txt")
    assert rig.names == ["img0", "img1", "img2"] and rig.unit == "m"
    # COLMAP's (0.5, 0.5) pixel centre becomes (0, 0).
    np.testing.assert_array_equal(rig[0].K, [[500, 0, 320], [0, 500, 240], [0, 0, 1]])
    np.testing.assert_array_equal(rig[1].dist, [-0.05, 0, 0, 0, 0])
    np.testing.assert_array_equal(rig[2].dist, [-0.05, 0.01, 0, 0, 0])
    np.testing.assert_allclose(
        rig[1].center, [3 * np.cos(2 * np.pi / 3), 3 * np.sin(2 * np.pi / 3), 1.0], atol=1e-12
    )
    # Points lines may be missing (hand-written files) or hold observations.
    lines = _colmap_images()
    lines[1] = "12.5 30.25 -1 100.0 40.0 7"
    cameras = (tmp_path / "cameras.txt").read_text().splitlines()[1:]
    _write_colmap(tmp_path, cameras, [lines[0], lines[1], lines[2], lines[4]])
    again = read_colmap_text(tmp_path)
    assert again.names == ["img0", "img1", "img2"]
    np.testing.assert_array_equal(again[2].R, rig[2].R)
    # Quaternion convention: (w, x, y, z), a 90 degree turn about z.
    q = np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])
    np.testing.assert_allclose(
        quaternion_to_rotation(q), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15
    )


def test_colmap_errors(tmp_path):
    good_cams = [
        "1 PINHOLE 64 48 50 50 32 24",
        "2 PINHOLE 64 48 50 50 32 24",
        "3 PINHOLE 64 48 50 50 32 24",
    ]
    images = _colmap_images()
    _write_colmap(tmp_path, ["1 OPENCV_FISHEYE 64 48 50 50 32 24 0 0 0 0", *good_cams[1:]], images)
    with pytest.raises(CalibrationError, match=r"cameras img0 have fisheye lenses: import"):
        read_colmap_text(tmp_path)  # read with its lens by load_calibration (test_fisheye.py)
    _write_colmap(tmp_path, ["1 SIMPLE_RADIAL_FISHEYE 64 48 50 32 24 0", *good_cams[1:]], images)
    with pytest.raises(
        CalibrationError,
        match=r"cameras\.txt:2.*unsupported COLMAP camera model 'SIMPLE_RADIAL_FISHEYE'",
    ):
        read_colmap_text(tmp_path)
    _write_colmap(tmp_path, ["1 PINHOLE 64 48 50 50 32", *good_cams[1:]], images)
    with pytest.raises(
        CalibrationError, match=r"cameras\.txt:2.*PINHOLE takes 4 parameters, got 3"
    ):
        read_colmap_text(tmp_path)
    _write_colmap(
        tmp_path, ["1 FULL_OPENCV 64 48 50 50 32 24 0 0 0 0 0 0.1 0 0", *good_cams[1:]], images
    )
    with pytest.raises(CalibrationError, match=r"cameras\.txt:2.*k4\.\.k6"):
        read_colmap_text(tmp_path)
    _write_colmap(tmp_path, ["1 PINHOLE 64 48 0 50 32 24", *good_cams[1:]], images)
    with pytest.raises(CalibrationError, match="img0.*focal"):
        read_colmap_text(tmp_path)
    _write_colmap(tmp_path, good_cams[:2], images)
    with pytest.raises(CalibrationError, match=r"'img2' uses CAMERA_ID 3"):
        read_colmap_text(tmp_path)
    bad_q = [images[0].replace(images[0].split()[1], "0.5", 1), *images[1:]]
    _write_colmap(tmp_path, good_cams, bad_q)
    with pytest.raises(CalibrationError, match=r"images\.txt:2: camera 'img0'.*quaternion norm"):
        read_colmap_text(tmp_path)
    _write_colmap(tmp_path, good_cams, ["1 1 0 0 0 0 0 0 1"])
    with pytest.raises(CalibrationError, match=r"images\.txt:2: expected 'IMAGE_ID"):
        read_colmap_text(tmp_path)
    _write_colmap(tmp_path, good_cams, images[:4])
    with pytest.raises(CalibrationError, match="at least 3 cameras"):
        read_colmap_text(tmp_path)
    (tmp_path / "images.txt").unlink()
    with pytest.raises(CalibrationError, match=r"images\.txt not found"):
        read_colmap_text(tmp_path)
    skewed = ring_rig(3)
    K = skewed[0].K.copy()
    K[0, 1] = 0.5
    skewed = dataclasses.replace(
        skewed, cameras=(dataclasses.replace(skewed[0], K=K), *skewed.cameras[1:])
    )
    with pytest.raises(CalibrationError, match="'cam0'.*skew"):
        write_colmap_text(tmp_path / "out", skewed)


def test_quaternion_conversions_are_inverse():
    rng = np.random.default_rng(1)
    for _ in range(50):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = q if q[0] >= 0 else -q
        R = quaternion_to_rotation(q)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-14)
        np.testing.assert_allclose(rotation_to_quaternion(R), q, atol=1e-14)
    # 180 degree turns (w = 0) take the non-trace branches.
    for R in (np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])):
        np.testing.assert_allclose(quaternion_to_rotation(rotation_to_quaternion(R)), R, atol=1e-15)


def test_detect_format_errors(tmp_path):
    (tmp_path / "foo.json").write_text('{"a": 1}')
    with pytest.raises(CalibrationError, match=r"foo\.json.*neither"):
        detect_calibration_format(tmp_path / "foo.json")
    (tmp_path / "foo.txt").write_text("")
    with pytest.raises(CalibrationError, match=r"foo\.txt.*unknown calibration format"):
        detect_calibration_format(tmp_path / "foo.txt")
    with pytest.raises(CalibrationError, match="no calibration found"):
        load_rig(tmp_path)


def test_a_folder_with_two_calibrations_of_one_format_asks_for_one(tmp_path):
    from tests.io.test_importer import anipose_toml

    text = anipose_toml(ring_rig(3))
    (tmp_path / "a.toml").write_text(text)
    (tmp_path / "b.toml").write_text(text)
    with pytest.raises(
        CalibrationError, match=r"2 files of an anipose .*\(a.toml, b.toml\); pass one"
    ):
        load_rig(tmp_path)
    (tmp_path / "b.toml").unlink()
    assert len(load_rig(tmp_path)) == 3
