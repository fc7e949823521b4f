import dataclasses

import numpy as np
import pytest

from edgerecon.geometry import Camera, Rig, fundamental_matrix, look_at, triangulation_angle_deg
from edgerecon.types import CalibrationError
from tests.conftest import ring_rig


def test_project_backproject_roundtrip_with_distortion():
    rig = ring_rig(3, dist=(-0.2, 0.05, 1e-3, -5e-4, 0.01))
    cam = rig[0]
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, (200, 3)) + [0, 0, 1]
    uv, depth = cam.project(pts)
    assert np.all(depth > 0)
    back = cam.backproject(uv, depth)
    np.testing.assert_allclose(back, pts, atol=1e-7)


def test_project_behind_camera_is_nan():
    cam = ring_rig(3)[0]
    behind = cam.center - 2 * cam.viewing_direction
    uv, depth = cam.project(behind[None])
    assert depth[0] < 0 and np.isnan(uv).all()


def test_scaled_camera_maps_pixel_grid():
    cam = ring_rig(3, width=640, height_px=480)[1]
    half = cam.scaled(0.5)
    assert half.size == (320, 240)
    pts = np.array([[0.3, -0.2, 1.1], [0.0, 0.0, 1.0]])
    uv, _ = cam.project(pts)
    uvh, _ = half.project(pts)
    np.testing.assert_allclose(uvh, (uv + 0.5) * 0.5 - 0.5, atol=1e-9)
    # Image borders map onto each other.
    assert half.scaled(2.0) == cam


def test_undistort_maps_produce_pinhole_image():
    cam = ring_rig(3, dist=(-0.25, 0.08, 0, 0, 0))[0]
    target = cam.scaled(0.5).undistorted()
    mx, my = cam.undistort_maps(0.5)
    assert mx.shape == (target.height, target.width)
    # A pixel of the target maps to where the distorted camera sees the same ray.
    pts = cam.backproject(np.array([[100.0, 80.0]]), np.array([2.0]))
    uv_t, _ = target.project(pts)
    uv_d, _ = cam.project(pts)
    x, y = np.rint(uv_t[0]).astype(int)
    # Evaluate the map at the exact target pixel by projecting the pixel centre.
    ray_pt = target.backproject(np.array([[x, y]], float), np.array([1.0]))
    uv_expected, _ = cam.project(ray_pt)
    np.testing.assert_allclose([mx[y, x], my[y, x]], uv_expected[0], atol=0.02)
    assert cam.undistort_maps(0.5) is cam.undistort_maps(0.5)  # cached
    assert np.isfinite(uv_d).all()


def test_prepare_image_rejects_wrong_size():
    cam = ring_rig(3)[0]
    with pytest.raises(CalibrationError, match="cam0.*frame is 100x50"):
        cam.prepare_image(np.zeros((50, 100, 3), np.uint8))


def test_validation_messages_name_camera():
    cam = ring_rig(3)[0]
    with pytest.raises(CalibrationError, match="cam0.*not orthonormal"):
        dataclasses.replace(cam, R=cam.R * 1.01)
    with pytest.raises(CalibrationError, match="cam0.*focal"):
        dataclasses.replace(cam, K=np.diag([-1.0, 1.0, 1.0]))
    with pytest.raises(CalibrationError, match="at least 3 cameras"):
        Rig(cameras=(cam, dataclasses.replace(cam, name="b", t=cam.t + 1)))


def test_fundamental_matrix_epipolar_constraint():
    rig = ring_rig(4)
    pts = np.random.default_rng(1).uniform(-0.5, 0.5, (50, 3)) + [0, 0, 1]
    a, b = rig[0], rig[1]
    F = fundamental_matrix(a, b)
    ua, _ = a.project(pts)
    ub, _ = b.project(pts)
    ha = np.hstack([ua, np.ones((50, 1))])
    hb = np.hstack([ub, np.ones((50, 1))])
    lines = ha @ F.T
    dist = np.abs(np.einsum("ij,ij->i", hb, lines)) / np.linalg.norm(lines[:, :2], axis=1)
    assert dist.max() < 1e-8
    assert triangulation_angle_deg(a, b, pts).min() > 30


def test_rig_json_roundtrip_is_exact():
    rig = ring_rig(5, dist=(-0.1, 0.01, 0.001, 0.002, 0.0))
    again = Rig.from_dict(rig.to_dict())
    assert all(x == y for x, y in zip(rig, again, strict=True))
    assert rig.subset([4, 0, 2]).names == ["cam4", "cam0", "cam2"]
    assert rig.index("cam3") == 3 and rig.index("2") == 2


def test_look_at_points_optical_axis_at_target():
    R, t = look_at((3, 0, 1), (0, 0, 1))
    cam = Camera(name="c", width=10, height=10, K=np.eye(3), R=R, t=t)
    np.testing.assert_allclose(cam.viewing_direction, [-1, 0, 0], atol=1e-12)
    # image 'down' (+y) points to world -z
    np.testing.assert_allclose(R[1], [0, 0, -1], atol=1e-12)


@pytest.mark.parametrize("dist", [np.zeros(5), np.array([-0.31, 0.12, 0.002, -0.003, -0.02])])
def test_the_compiled_projection_is_the_numpy_arithmetic_bit_for_bit(dist):
    from edgerecon.geometry.camera import _distort

    cam = dataclasses.replace(ring_rig(3)[0], dist=dist)
    rng = np.random.default_rng(5)
    # Points all around the camera: in front, behind, near its plane (huge normalised
    # coordinates, overflowing the polynomial), on it (depth 0).
    Xc = rng.normal(0, 3, (20000, 3))
    Xc[:500, 2] = rng.normal(0, 1e-6, 500)
    Xc[500:510, 2] = 0.0
    pts = (Xc - cam.t) @ cam.R  # camera frame -> world
    uv, depth = cam.project(pts)
    xc = cam.world_to_cam(pts)
    # The rigid transform, compiled: NumPy's row sums left to right, not BLAS's product.
    R, t = cam.R, cam.t
    ref_xc = np.stack(
        [R[r, 0] * pts[:, 0] + R[r, 1] * pts[:, 1] + R[r, 2] * pts[:, 2] + t[r] for r in range(3)],
        axis=1,
    )
    np.testing.assert_array_equal(xc, ref_xc)
    np.testing.assert_allclose(xc, pts @ R.T + t, rtol=1e-12, atol=1e-12)
    with np.errstate(all="ignore"):
        xn, yn = xc[:, 0] / xc[:, 2], xc[:, 1] / xc[:, 2]
        if cam.has_distortion:
            xn, yn = _distort(xn, yn, cam.dist)
        K = cam.K
        ref = np.stack([K[0, 0] * xn + K[0, 1] * yn + K[0, 2], K[1, 1] * yn + K[1, 2]], axis=1)
    ref[~(xc[:, 2] > 0)] = np.nan
    np.testing.assert_array_equal(uv, ref)
    np.testing.assert_array_equal(depth, xc[:, 2])
    assert np.isnan(uv).any() and np.isfinite(uv).any()
    # Back to the world from the pixels in front of the camera, near its axis (where the
    # distortion is invertible).
    near_axis = np.abs(xc[:, :2]).max(axis=1) < 0.4 * np.abs(xc[:, 2])
    front = np.flatnonzero((depth > 0.5) & near_axis)[:2000]
    back = cam.backproject(uv[front], depth[front])
    np.testing.assert_allclose(back, pts[front], rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(cam.world_to_cam(pts.T.copy().T), xc)  # not C-contiguous


@pytest.mark.parametrize("dist", [np.zeros(5), np.array([-0.31, 0.12, 0.002, -0.003, -0.02])])
def test_nearest_pixels_are_project_in_image_and_rounding(dist):
    """The compiled pass against its NumPy composition: ``project``, ``in_image``, rounding
    half to even and clipping (points behind, on the image's edges and halfway between)."""
    cam = dataclasses.replace(ring_rig(3)[0], dist=dist)
    rng = np.random.default_rng(7)
    Xc = rng.normal(0, 2, (20000, 3))
    Xc[:2000, 2] = np.abs(Xc[:2000, 2]) + 0.1
    pts = (Xc - cam.t) @ cam.R
    # Points exactly on pixel halves and on the image's borders (in front of the camera).
    uv0 = np.array(
        [[-0.5, 3.0], [cam.width - 0.5, 2.5], [4.5, cam.height - 0.5], [10.5, 11.5], [0, 0]]
    )
    on_edges = cam.backproject(uv0, np.full(len(uv0), 2.0))
    pts = np.vstack([pts, on_edges])
    uv, depth, u, v, inside = cam.nearest_pixels(pts)
    ref_uv, ref_depth = cam.project(pts)
    np.testing.assert_array_equal(uv, ref_uv)
    np.testing.assert_array_equal(depth, ref_depth)
    ref_inside = (ref_depth > 0) & cam.in_image(ref_uv)
    np.testing.assert_array_equal(inside, ref_inside)
    safe = np.where(ref_inside[:, None], ref_uv, 0.0)
    np.testing.assert_array_equal(u, np.clip(np.rint(safe[:, 0]), 0, cam.width - 1).astype(np.intp))
    np.testing.assert_array_equal(
        v, np.clip(np.rint(safe[:, 1]), 0, cam.height - 1).astype(np.intp)
    )
    assert inside.any() and not inside.all()


def test_undistortion_maps_are_cached_within_a_byte_budget(monkeypatch):
    from edgerecon.geometry import camera as camera_module

    cam = ring_rig(3, dist=(-0.2, 0.05, 0, 0, 0))[0]
    monkeypatch.setattr(camera_module, "_maps_cache", camera_module.OrderedDict())
    first = cam.undistort_maps(0.5)
    assert cam.undistort_maps(0.5)[0] is first[0]  # a hit
    assert not first[0].flags.writeable  # shared by every caller
    one = first[0].nbytes + first[1].nbytes
    monkeypatch.setattr(camera_module, "UNDISTORT_CACHE_BYTES", 3 * one)
    for k in range(10):  # the controller's r in small steps: never more than the budget
        cam.undistort_maps(0.5 + 0.001 * (k + 1))
        held = sum(a.nbytes + b.nbytes for a, b in camera_module._maps_cache.values())
        assert held <= 3 * one + 2 * one // 10
    assert (cam, 0.5) not in camera_module._maps_cache  # the least recently used went
    again = cam.undistort_maps(0.5)
    np.testing.assert_array_equal(again[0], first[0])
