"""Cross-view consistency and ground-plane completion on exact rendered depth maps."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from edgerecon.dense.consistency import support_and_conflicts, support_counts
from edgerecon.dense.planes import (
    Plane,
    below_plane,
    complete_with_plane,
    fit_ground_plane,
    plane_depth,
    support_region,
)
from tests.conftest import ring_rig
from tests.dense.scene import Rect, box_scene, render

RIG = ring_rig(12, radius=4.0, height=2.0, width=160, height_px=120, focal_px=125.0)
IDS = (11, 0, 1)


@pytest.fixture(scope="module")
def rendered():
    rects = box_scene()
    out = {i: render(RIG[i], rects) for i in IDS}
    return {i: o[0] for i, o in out.items()}, {i: o[1] for i, o in out.items()}


def test_exact_depths_support_each_other_and_outliers_do_not(rendered):
    _, depths = rendered
    cams = {i: RIG[i] for i in IDS}
    noisy = {i: d.copy() for i, d in depths.items()}
    noisy[0][90:110, 60:90] *= 1.08  # a wrong patch in the middle view (floor and cube)
    support, averaged = support_counts(noisy, cams, 0.01)
    s = support[0]
    has = depths[0] > 0
    patch = np.zeros_like(has)
    patch[90:110, 60:90] = True
    assert np.count_nonzero(patch & has) > 500  # the patch corrupts real depths
    # The injected outliers find no support; almost every correct depth finds both others
    # (except near occlusion boundaries and the image borders).
    assert np.all(s[patch & has] == 0)
    assert np.mean(s[~patch & has] >= 1) > 0.9
    assert np.mean(s[~patch & has] == 2) > 0.5
    # Averaging along the rays keeps exact depths exact (up to interpolation at edges).
    good = ~patch & (s > 0)
    rel = np.abs(averaged[0][good] - depths[0][good]) / depths[0][good]
    assert np.median(rel) < 1e-4 and np.mean(rel < 3e-3) > 0.99
    # Views without depth contribute nothing and get zero counts.
    empty = {i: np.zeros_like(d) for i, d in depths.items()}
    assert all(np.all(c == 0) for c in support_counts(empty, cams, 0.01)[0].values())


def test_ground_plane_prefers_points_confirmed_by_three_views():
    rng = np.random.default_rng(1)
    floor = np.c_[rng.uniform(-2, 2, (400, 2)), rng.normal(0.0, 0.005, 400)]
    ghost = np.c_[rng.uniform(-2, 2, (900, 2)), rng.normal(-1.1, 0.001, 900)]
    pts = np.vstack([floor, ghost])
    normals = np.tile(np.float32([0, 0, 1]), (len(pts), 1))
    views = np.r_[np.full(400, 3), np.full(900, 2)]
    plane = fit_ground_plane(pts, normals, views, np.array([0, 0, 1.0]), 0.03, 100)
    assert plane is not None
    assert abs(plane.offset) < 0.005 and plane.normal == (0.0, 0.0, 1.0)
    # Without 3-view points the tighter ghost cluster would win: the vote needs them.
    plane2 = fit_ground_plane(pts, normals, np.full(len(pts), 2), np.array([0, 0, 1.0]), 0.03, 100)
    assert plane2 is not None and abs(plane2.offset + 1.1) < 0.005
    assert np.all(below_plane(ghost, plane, 0.05))
    assert not np.any(below_plane(floor, plane, 0.05))
    # Too few horizontal points: no plane.
    tilted = np.tile(np.float32([1, 0, 0]), (len(pts), 1))
    assert fit_ground_plane(pts, tilted, views, np.array([0, 0, 1.0]), 0.03, 100) is None


def test_plane_depth_is_exact():
    floor_only = render(RIG[0], box_scene()[:1])[1]
    zp = plane_depth(RIG[0], Plane(normal=(0.0, 0.0, 1.0), offset=0.0, support=1, rms=0.0))
    hit = floor_only > 0
    assert np.allclose(zp[hit], floor_only[hit], rtol=1e-5)


def test_completion_fills_a_blank_floor_but_not_behind_the_cube():
    rects = box_scene()
    blank = np.full_like(rects[0].texture, 90)  # a textureless grey floor
    rects[0] = Rect(rects[0].origin, rects[0].u, rects[0].v, blank)
    images, depths = {}, {}
    for i in IDS:
        images[i], depths[i] = render(RIG[i], rects)
    # Stereo knows only the cube (its depths exact); the floor is blank.
    cube = {i: np.where(np.abs(_world_z(RIG[i], d)) > 1e-4, d, 0) for i, d in depths.items()}
    plane = Plane(normal=(0.0, 0.0, 1.0), offset=0.0, support=1000, rms=0.0)
    regions = {i: np.ones(d.shape, bool) for i, d in depths.items()}
    out = complete_with_plane(
        plane, cube, {i: RIG[i] for i in IDS}, images, regions, {i: 20.0 for i in IDS},
        0.01, 20.0, 1,
    )  # fmt: skip
    d, sup = out[0]
    floor_px = (depths[0] > 0) & (cube[0] == 0)
    filled = d > 0
    assert filled[floor_px].mean() > 0.8
    on_floor = filled & floor_px
    assert np.allclose(d[on_floor], depths[0][on_floor], rtol=1e-4)
    assert np.all(sup[filled] >= 1)
    # Never behind the cube; into the black void only within the 5x5 colour blur of the
    # floor's edge.
    assert not (filled & (cube[0] > 0)).any()
    near_floor = cv2.dilate(floor_px.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    assert not (filled & ~near_floor).any()


def test_textured_floor_is_completed_where_its_pattern_matches_not_behind_the_cube():
    """With no stereo depth at all (the worst case), textured floor pixels are completed
    where the other views' images, warped through the plane, match their pattern; the
    cube's textured sides are not put onto the floor behind them, which the colour test
    alone would do (random textures share their mean colour)."""
    rects = box_scene()
    images, depths = {}, {}
    for i in IDS:
        images[i], depths[i] = render(RIG[i], rects)
    none = {i: np.zeros(d.shape, np.float32) for i, d in depths.items()}
    plane = Plane(normal=(0.0, 0.0, 1.0), offset=0.0, support=1000, rms=0.0)
    regions = {i: np.ones(d.shape, bool) for i, d in depths.items()}
    textured = {i: np.ones(d.shape, bool) for i, d in depths.items()}
    cams = {i: RIG[i] for i in IDS}
    far = {i: 20.0 for i in IDS}

    def run(min_ncc: float) -> np.ndarray:
        out = complete_with_plane(
            plane, none, cams, images, regions, far, 0.01, 20.0, 1,
            textured=textured, min_ncc=min_ncc,
        )  # fmt: skip
        return out[0][0]

    z = _world_z(RIG[0], depths[0])
    floor_px = (depths[0] > 0) & (np.abs(z) < 1e-4)
    cube_px = (depths[0] > 0) & (np.abs(z) >= 1e-4)
    d = run(0.5)
    filled = d > 0
    assert filled[floor_px].mean() > 0.5
    assert np.allclose(d[filled & floor_px], depths[0][filled & floor_px], rtol=1e-4)
    # (A few pixels at the cube's foot, whose windows hold the floor too, measured: 0.5 %.)
    assert (filled & cube_px).sum() < 0.01 * cube_px.sum()
    # The colour test alone (any NCC passes) puts most of the cube onto the floor (89 %).
    assert (run(-1.0) > 0)[cube_px].mean() > 0.5


def _world_z(cam, depth):
    rows, cols = np.indices(depth.shape)
    X = cam.backproject(np.c_[cols.ravel(), rows.ravel()], depth.ravel())
    return X[:, 2].reshape(depth.shape)


def test_support_region_is_the_convex_hull_of_the_inliers():
    rng = np.random.default_rng(2)
    plane = Plane(normal=(0.0, 0.0, 1.0), offset=0.5, support=500, rms=0.0)
    inliers = np.c_[rng.uniform(-1, 1, (500, 2)), np.full(500, 0.5)]
    inliers[0] = (30.0, 30.0, 0.5)  # an outlier far away is trimmed
    region = support_region(plane, inliers, trim=0.01)
    assert region is not None
    probe = np.array([[0.0, 0.0, 0.5], [0.9, -0.9, 0.5], [1.2, 0.0, 0.5], [5.0, 5.0, 0.5]])
    assert region.inside(probe).tolist() == [True, True, False, False]
    # Degenerate supports (collinear, too few points) give no region.
    line = np.c_[np.linspace(-1, 1, 50), np.zeros(50), np.full(50, 0.5)]
    assert support_region(plane, line) is None
    assert support_region(plane, inliers[:2]) is None


def test_support_region_inside_agrees_with_a_triangulation_of_the_hull():
    """The wedge test (one edge per point) gives what testing every edge gives."""
    from scipy.spatial import Delaunay

    rng = np.random.default_rng(5)
    plane = Plane(normal=(0.0, 0.0, 1.0), offset=-0.2, support=400, rms=0.0)
    inliers = np.c_[rng.normal(0.0, [2.0, 0.5], (400, 2)), np.full(400, -0.2)]
    region = support_region(plane, inliers, trim=0.0)
    assert region is not None and len(region.vertices) >= 8
    probe = np.c_[rng.uniform(-8, 8, (20000, 2)), np.full(20000, -0.2)]
    uv = probe @ region.basis
    expected = Delaunay(region.vertices).find_simplex(uv) >= 0
    assert 0.05 < expected.mean() < 0.5
    assert np.array_equal(region.inside(probe), expected)


def test_ground_plane_is_never_above_most_of_the_scene():
    # A foreground-only cloud: two standing people, the tops of their heads the largest
    # horizontal patch. A plane there would cut away everything below it.
    rng = np.random.default_rng(3)
    bodies = []
    for cx in (-0.5, 0.6):
        a = rng.uniform(0, 2 * np.pi, 3000)
        z = rng.uniform(0.0, 1.6, 3000)
        bodies.append(np.c_[cx + 0.2 * np.cos(a), 0.2 * np.sin(a), z])
    side = np.vstack(bodies)
    side_n = np.c_[side[:, 0] - np.repeat([-0.5, 0.6], 3000), side[:, 1], np.zeros(len(side))]
    heads = np.c_[rng.uniform(-0.6, -0.4, 800), rng.uniform(-0.1, 0.1, 800), np.full(800, 1.7)]
    pts = np.vstack([side, heads])
    normals = np.vstack([side_n, np.tile([0.0, 0.0, 1.0], (800, 1))]).astype(np.float32)
    views = np.full(len(pts), 3)
    assert fit_ground_plane(pts, normals, views, np.array([0, 0, 1.0]), 0.03, 100) is None
    # With a floor under them, the floor is found.
    floor = np.c_[rng.uniform(-2, 2, (600, 2)), rng.normal(0.0, 0.004, 600)]
    pts2 = np.vstack([pts, floor])
    normals2 = np.vstack([normals, np.tile(np.float32([0, 0, 1]), (600, 1))])
    plane = fit_ground_plane(
        pts2, normals2, np.full(len(pts2), 3), np.array([0, 0, 1.0]), 0.03, 100
    )
    assert plane is not None and abs(plane.offset) < 0.01


def test_reprojection_test_rejects_depths_the_relative_tolerance_lets_through(rendered):
    _, depths = rendered
    cams = {i: RIG[i] for i in IDS}
    off = {i: d.copy() for i, d in depths.items()}
    off[0][90:110, 60:90] *= 1.04  # within a 5 % depth tolerance, pixels off in the others
    has = depths[0] > 0
    patch = np.zeros_like(has)
    patch[90:110, 60:90] = True
    loose = support_and_conflicts(off, cams, 0.05)[0][0]
    strict = support_and_conflicts(off, cams, 0.05, max_reproj_px=1.0)[0][0]
    # The depth test alone supports the shifted patch; one pixel of reprojection does not
    # (4 % of ~4 m moves the point about 2.5 pixels in views 30 degrees away).
    assert np.mean(loose[patch & has] >= 1) > 0.95
    assert np.mean(strict[patch & has] >= 1) < 0.05
    # Exact depths keep their support under the reprojection test.
    assert np.mean(strict[~patch & has] >= 1) > 0.9
