"""Known-answer ray intersections of the analytic primitives."""

import numpy as np
import pytest

from edgerecon.synth.primitives import Box, Cylinder, Ellipsoid, Room


def rays(*dirs_cam):
    """Normalised (xn, yn) arrays for camera-frame directions (x, y, z) with z > 0."""
    d = np.asarray(dirs_cam, float)
    return (d[:, 0] / d[:, 2]).astype(np.float32), (d[:, 1] / d[:, 2]).astype(np.float32)


# A camera at the origin whose world axes equal its camera axes (world_from_cam = I).
ORIGIN = np.zeros(3)
EYE = np.eye(3)


def test_ellipsoid_depth_normal_and_miss():
    e = Ellipsoid(
        center=np.array([0.0, 0.0, 5.0]),
        rotation=np.eye(3),
        radii=np.array([0.5, 1.0, 2.0]),
        material=0,
        u_period_m=1.0,
    )
    xn, yn = rays((0, 0, 1), (0, 0.1, 1), (1, 0, 1))
    s = e.intersect(ORIGIN, EYE, xn, yn)
    assert s[0] == pytest.approx(3.0, abs=1e-6)  # front pole at z = 5 - 2
    # Ray (0, 0.1 s, s): (0.1 s / 1)^2 + ((s - 5) / 2)^2 = 1, nearer root.
    a, b, c = 0.01 + 0.25, -2.5, 6.25 - 1
    expect = (-b - np.sqrt(b * b - 4 * a * c)) / (2 * a)
    assert s[1] == pytest.approx(expect, rel=1e-6)
    assert np.isinf(s[2])
    pts = np.array([[0.0, 0.0, 3.0], [0.5, 0.0, 5.0]], np.float32)
    surf = e.surface(pts)
    np.testing.assert_allclose(surf.normals, [[0, 0, -1], [1, 0, 0]], atol=1e-6)


def test_ellipsoid_is_accurate_in_float32_for_thin_far_parts():
    # A 4 cm limb 6 m away: the naive discriminant would lose it to cancellation.
    e = Ellipsoid(
        center=np.array([0.0, 0.0, 6.0]),
        rotation=np.eye(3),
        radii=np.array([0.04, 0.04, 0.2]),
        material=0,
        u_period_m=1.0,
    )
    x = np.linspace(-0.039, 0.039, 101) / 6.0
    s = e.intersect(ORIGIN, EYE, x.astype(np.float32), np.zeros(101, np.float32))
    assert np.all(np.isfinite(s))
    X = np.stack([x * s, np.zeros(101), s], axis=1)
    # Points satisfy the ellipsoid equation to ~1e-4 (float32 on 6 m).
    val = (X[:, 0] / 0.04) ** 2 + ((X[:, 2] - 6) / 0.2) ** 2
    np.testing.assert_allclose(val, 1.0, atol=2e-3)


def test_box_hits_the_near_face_and_reports_its_normal():
    box = Box(
        center=np.array([0.0, 0.0, 4.0]),
        half=np.array([1.0, 1.0, 0.5]),
        yaw=0.0,
        side_material=1,
        top_material=2,
    )
    xn, yn = rays((0, 0, 1), (0.2, 0, 1), (0.6, 0, 1))
    s = box.intersect(ORIGIN, EYE, xn, yn)
    assert s[0] == pytest.approx(3.5)
    assert s[1] == pytest.approx(3.5)
    assert np.isinf(s[2])  # passes beside it: x = 0.6 z > 1 before z reaches 3.5
    surf = box.surface(np.array([[0.0, 0.0, 3.5], [0.0, 0.0, 4.5]], np.float32))
    np.testing.assert_allclose(surf.normals, [[0, 0, -1], [0, 0, 1]], atol=1e-6)
    assert list(surf.material) == [1, 2]  # bottom face uses the side material, top the top
    # A box rotated by 90 degrees about z is the same box when its sides are swapped.
    rot = Box(
        center=box.center,
        half=np.array([0.5, 2.0, 0.5]),
        yaw=np.pi / 2,
        side_material=1,
        top_material=2,
    )
    xn, yn = rays((1.5, 0, 4.0))
    straight = Box(
        center=box.center, half=np.array([2.0, 0.5, 0.5]), yaw=0.0, side_material=1, top_material=2
    )
    assert rot.intersect(ORIGIN, EYE, xn, yn)[0] == pytest.approx(
        straight.intersect(ORIGIN, EYE, xn, yn)[0], rel=1e-6
    )


def test_cylinder_side_and_cap():
    # Upright cylinder (axis along world z); the camera looks along world x here.
    cyl = Cylinder(
        center_xy=(5.0, 0.0), radius=1.0, z0=-1.0, z1=1.0, side_material=0, top_material=1
    )
    R = np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]], float)  # cam z -> world x
    xn, yn = rays((0, 0, 1), (0, 0.5, 5))  # camera y -> world z
    s = cyl.intersect(ORIGIN, R, xn, yn)
    assert s[0] == pytest.approx(4.0)
    # Second ray reaches z = 0.5 at x = 5 -> enters the side at x = 4 with z = 0.4.
    assert s[1] == pytest.approx(4.0)
    cam_above = np.array([5.0, 0.0, 3.0])
    down = np.array([[1, 0, 0], [0, -1, 0], [0, 0, -1]], float)  # cam z -> world -z
    s = cyl.intersect(cam_above, down, *rays((0, 0, 1)))
    assert s[0] == pytest.approx(2.0)  # the top cap at z = 1
    surf = cyl.surface(np.array([[5.0, 0.0, 1.0], [4.0, 0.0, 0.0]], np.float32))
    np.testing.assert_allclose(surf.normals, [[0, 0, 1], [-1, 0, 0]], atol=1e-6)


def test_room_exit_face():
    room = Room(half_x=4.0, half_y=3.0, height=2.5, materials=(0, 1, 2, 3, 4, 5))
    c = np.array([1.0, 0.0, 1.0])
    s = room.intersect(c, EYE, *rays((0, 0, 1), (0, 0, -1e-9), (1, 0, 1e-9)))
    assert s[0] == pytest.approx(1.5)  # ceiling at 2.5
    surf = room.surface(np.array([[1.0, 0.0, 2.5], [1.0, 0.0, 0.0], [4.0, 0.5, 1.0]], np.float32))
    np.testing.assert_allclose(surf.normals, [[0, 0, -1], [0, 0, 1], [-1, 0, 0]])
    assert list(surf.material) == [1, 0, 3]
    assert room.contains(c) and not room.contains(np.array([5.0, 0, 1]))
