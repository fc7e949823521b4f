"""Visual hull of known boxes seen by synthetic rigs."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from edgerecon.geometry import Camera, Rig
from edgerecon.quality.masks import mask_iou
from edgerecon.scene.hull import (
    _FOOTPRINT_SLACK,
    HullConfig,
    _pair_geometry,
    _paired_shares,
    hull_cloud,
    hull_consistent_masks,
    hull_depth_range,
    hull_explained_masks,
    hull_filled_masks,
    hull_object_silhouettes,
    hull_rescued,
    hull_silhouette,
    phantom_explained_masks,
    phantom_silhouette,
    rig_region,
    visual_hull,
)
from tests.scene._scenes import box_silhouette, box_surface_points, ring_with_top

LO = np.array([-0.3, -0.2, 0.5])
HI = np.array([0.3, 0.2, 1.4])
VOXEL = 0.02


@pytest.fixture(scope="module")
def rig() -> Rig:
    return ring_with_top(6)


@pytest.fixture(scope="module")
def box_hull(rig: Rig):  # type: ignore[no-untyped-def]
    masks = [box_silhouette(c, LO, HI) for c in rig]
    return visual_hull(rig.cameras, masks, HullConfig(voxel_size=VOXEL)), masks


def _exact_hull_volume(rig: Rig, masks: list[np.ndarray], step: float) -> float:
    """Volume of {X : X projects inside every silhouette}, by dense sampling."""
    lo, hi = LO - 0.25, HI + 0.25
    axes = [np.arange(lo[i], hi[i], step) + step / 2 for i in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    inside = np.ones(len(pts), bool)
    for cam, m in zip(rig, masks, strict=True):
        uv, _ = cam.project(pts)
        u = np.clip(np.rint(uv[:, 0]).astype(int), 0, cam.width - 1)
        v = np.clip(np.rint(uv[:, 1]).astype(int), 0, cam.height - 1)
        inside &= m[v, u]
    return float(inside.sum() * step**3)


def test_hull_contains_the_box(box_hull) -> None:  # type: ignore[no-untyped-def]
    hull, _ = box_hull
    assert hull.status == "ok"
    assert hull.voxel_size == pytest.approx(VOXEL)
    assert hull.contains(box_surface_points(LO, HI, 25)).all()
    assert hull.num_objects == 1


def test_a_hull_over_its_voxel_budget_keeps_larger_voxels(rig: Rig, box_hull) -> None:  # type: ignore[no-untyped-def]
    hull, masks = box_hull
    n = hull.num_voxels
    budgeted = visual_hull(rig.cameras, masks, HullConfig(voxel_size=VOXEL, voxel_budget=n // 2))
    assert budgeted.status == "ok"  # quietly coarser, not "coarse"
    assert budgeted.voxel_size == pytest.approx(2 * VOXEL)
    assert budgeted.num_voxels <= n // 2
    assert budgeted.contains(box_surface_points(LO, HI, 25)).all()
    # The budget bounds the next level's candidates (8 per boundary voxel, before carving).
    same = visual_hull(rig.cameras, masks, HullConfig(voxel_size=VOXEL, voxel_budget=None))
    assert same.num_voxels == n and same.voxel_size == pytest.approx(VOXEL)
    with pytest.raises(ValueError, match="voxel_budget"):
        HullConfig(voxel_budget=4)


def test_hull_is_tight(rig: Rig, box_hull) -> None:  # type: ignore[no-untyped-def]
    hull, masks = box_hull
    # Every voxel centre projects within its footprint (+ tolerance) of every silhouette.
    for cam, m in zip(rig, masks, strict=True):
        uv, depth = cam.project(hull.centers)
        u = np.rint(uv[:, 0]).astype(int)
        v = np.rint(uv[:, 1]).astype(int)
        assert cam.in_image(uv).all()
        radius = int(np.ceil(0.87 * VOXEL * cam.focal_px * 1.1 / depth.min() + 1.0 + 0.71))
        near = cv2.dilate(m.astype(np.uint8), np.ones((2 * radius + 1,) * 2, np.uint8)) > 0
        assert near[v, u].all()
    # Volume: at least the box, at most the exact visual hull plus a one-voxel shell.
    exact = _exact_hull_volume(rig, masks, 0.015)
    box = float(np.prod(HI - LO))
    assert box <= exact
    extent = HI - LO
    shell = np.prod(extent + 2 * VOXEL) - np.prod(extent)
    assert exact <= hull.volume <= exact + 2.5 * shell, (hull.volume, exact, shell)


def test_surface_cloud_normals_and_colours(rig: Rig, box_hull) -> None:  # type: ignore[no-untyped-def]
    hull, _ = box_hull
    images = [np.full((c.height, c.width, 3), (10, 20, 200), np.uint8) for c in rig]  # BGR
    cloud = hull_cloud(hull, rig.cameras, images)
    assert len(cloud) == int(hull.surface.sum()) > 0
    np.testing.assert_array_equal(cloud.labels, 1)
    assert cloud.inferred.all()  # silhouettes bound the shape; no depth measured it
    assert cloud.colors is not None and cloud.normals is not None
    seen = cloud.attributes["num_views"] > 0
    assert seen.mean() > 0.9
    np.testing.assert_array_equal(cloud.colors[seen], [[200, 20, 10]] * int(seen.sum()))
    # Normals point away from the box centre.
    centre = (LO + HI) / 2
    outward = np.einsum("ij,ij->i", cloud.normals, cloud.points3D - centre)
    assert (outward > 0).mean() > 0.99


def test_depth_range_brackets_the_box_surface(rig: Rig, box_hull) -> None:  # type: ignore[no-untyped-def]
    hull, _ = box_hull
    cam = rig[1].scaled(0.5)  # any camera works, e.g. a view's rescaled camera
    dr = hull_depth_range(hull, cam)
    pts = box_surface_points(LO, HI, 40)
    uv, depth = cam.project(pts)
    u = np.rint(uv[:, 0]).astype(int)
    v = np.rint(uv[:, 1]).astype(int)
    near, far = dr.near[v, u], dr.far[v, u]
    assert np.isfinite(near).all()
    assert (near <= depth + 1e-6).all() and (depth <= far + 1e-6).all()
    # Tight: the interval is about the box's depth extent, not the whole scene.
    assert np.nanmax(dr.far - dr.near) < 1.5 * np.linalg.norm(HI - LO)
    ((k, (zmin, zmax)),) = dr.objects.items()
    assert k == 1 and zmin <= depth.min() and depth.max() <= zmax
    # Pixels that see no hull have no range.
    assert not dr.mask[0, 0]
    near_map, far_map = dr.maps()
    assert near_map[0, 0] == 0 and far_map[0, 0] == 0
    assert (near_map[v, u] == near).all() and (far_map[v, u] == far).all()


def test_depth_range_with_wide_discs_covers_the_exact_one(rig: Rig, box_hull) -> None:  # type: ignore[no-untyped-def]
    """A view 12x finer than the masks: the voxels' discs are wider than the exact radius and
    are drawn on a coarser grid. The ranges hold the exact ones (every exact pixel, nearer
    or equal near, farther or equal far) and add at most a thin rim."""
    import edgerecon.scene.hull as hull_module

    hull, _ = box_hull
    cam = rig[0].scaled(12.0)
    fast = hull_depth_range(hull, cam)
    exact_limit = hull_module._EXACT_RADIUS_PX
    try:
        hull_module._EXACT_RADIUS_PX = 10**6  # every disc exact
        exact = hull_depth_range(hull, cam)
    finally:
        hull_module._EXACT_RADIUS_PX = exact_limit
    radius = 0.5 * np.sqrt(3.0) * hull.voxel_size * cam.focal_px / np.nanmax(exact.far)
    assert radius > exact_limit  # the coarse path ran
    e, f = exact.mask, fast.mask
    assert f[e].all()
    assert (fast.near[e] <= exact.near[e] + 1e-6).all()
    assert (fast.far[e] >= exact.far[e] - 1e-6).all()
    assert (f & ~e).sum() < 0.1 * e.sum()


def test_hull_silhouette_matches_the_masks(rig: Rig, box_hull) -> None:  # type: ignore[no-untyped-def]
    hull, masks = box_hull
    for cam, m in zip(rig, masks, strict=True):
        sil = hull_silhouette(hull, cam)
        assert (sil | ~m).all()  # covers the silhouette
        # ... and exceeds it by at most the carving slack (voxel footprint + tolerance) plus
        # the splat radius.
        _, depth = cam.project(hull.centers)
        foot = 0.87 * VOXEL * cam.focal_px / depth.min()
        r = int(np.ceil(2 * 1.1 * foot + 1.0 + 0.71 + 1))
        grown = cv2.dilate(
            m.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1,) * 2)
        )
        assert not (sil & ~grown.astype(bool)).any()
        assert mask_iou(sil, m) > 0.6


def test_one_camera_false_blob_is_removed_by_consistency(rig: Rig, box_hull) -> None:  # type: ignore[no-untyped-def]
    _, masks = box_hull
    bad = [m.copy() for m in masks]
    bad[2][5:40, 5:40] = True  # a blob only camera 2 sees (e.g. a scene change)
    hull = visual_hull(rig.cameras, bad, HullConfig(voxel_size=VOXEL))
    fixed = hull_consistent_masks(hull, rig.cameras, bad)
    assert not fixed[2][5:40, 5:40].any()
    for m, f in zip(masks, fixed, strict=True):
        assert mask_iou(f, m) > 0.97


def test_missing_foreground_in_one_camera_needs_max_missing(rig: Rig, box_hull) -> None:  # type: ignore[no-untyped-def]
    _, masks = box_hull
    bad = list(masks)
    bad[0] = np.zeros_like(masks[0])  # camera 0 lost the object
    strict = visual_hull(rig.cameras, bad, HullConfig(voxel_size=VOXEL))
    assert strict.status == "empty" and strict.num_voxels == 0
    robust = visual_hull(rig.cameras, bad, HullConfig(voxel_size=VOXEL, max_missing=1))
    assert robust.contains(box_surface_points(LO, HI, 10)).all()


def test_two_boxes_are_two_objects(rig: Rig) -> None:
    lo2, hi2 = LO + np.array([1.2, 0.8, 0.0]), HI + np.array([1.2, 0.8, -0.4])
    masks = [box_silhouette(c, LO, HI) | box_silhouette(c, lo2, hi2) for c in rig]
    hull = visual_hull(rig.cameras, masks, HullConfig(voxel_size=0.03))
    assert hull.num_objects == 2
    labels = hull.label_points(np.array([(LO + HI) / 2, (lo2 + hi2) / 2, [3.0, 3.0, 3.0]]))
    assert labels.tolist() == [1, 2, 0]  # the larger box is object 1
    assert set(hull.object_bounds()) == {1, 2}
    for cam in rig:  # every object's silhouette at once, as one at a time
        stack = hull_object_silhouettes(hull, cam)
        assert stack.shape == (2, cam.height, cam.width)
        for k in (1, 2):
            assert stack[k - 1].any()
            np.testing.assert_array_equal(stack[k - 1], hull_silhouette(hull, cam, object_id=k))


def test_distorted_cameras(rig: Rig) -> None:
    # Masks of distorted cameras are carved through Camera.project (distortion applied).
    cams = [dataclasses.replace(c, dist=np.array([-0.2, 0.05, 0.001, -0.001, 0.0])) for c in rig]
    masks = []
    for c in cams:
        pts = box_surface_points(LO, HI, 60)
        uv, _ = c.project(pts)
        m = np.zeros((c.height, c.width), np.uint8)
        hull_pts = cv2.convexHull(uv.astype(np.float32))  # distortion keeps it near-convex
        cv2.fillConvexPoly(m, np.rint(hull_pts).astype(np.int32).reshape(-1, 2), 1)
        masks.append(m.astype(bool))
    hull = visual_hull(cams, masks, HullConfig(voxel_size=VOXEL, tolerance_px=1.5))
    assert hull.contains(box_surface_points(LO, HI, 15)).mean() > 0.99
    assert hull.volume < 2.0 * np.prod(HI - LO)


def test_empty_masks_give_empty_hull(rig: Rig) -> None:
    masks = [np.zeros((c.height, c.width), bool) for c in rig]
    hull = visual_hull(rig.cameras, masks)
    assert hull.status == "empty" and hull.num_voxels == 0 and hull.num_objects == 0
    assert hull_cloud(hull, rig.cameras, [None] * len(rig)).num_points == 0
    assert not hull_depth_range(hull, rig[0]).mask.any()
    assert not hull.contains(np.zeros((3, 3))).any()


def test_cameras_without_mask_do_not_carve(rig: Rig) -> None:
    masks: list[np.ndarray | None] = [box_silhouette(c, LO, HI) for c in rig]
    masks[3] = None
    hull = visual_hull(rig.cameras, masks, HullConfig(voxel_size=0.04))
    assert hull.contains(box_surface_points(LO, HI, 10)).all()


def test_bad_input(rig: Rig) -> None:
    from edgerecon.types import DataError

    with pytest.raises(DataError, match="cam0.*10x10"):
        visual_hull(rig.cameras, [np.zeros((10, 10), bool)] + [None] * 5)
    with pytest.raises(DataError, match="2 masks for 6 cameras"):
        visual_hull(rig.cameras, [None, None])
    with pytest.raises(ValueError, match="voxel_size"):
        HullConfig(voxel_size=-1.0)


def test_rig_region_contains_where_cameras_look(rig: Rig) -> None:
    box = rig_region(rig.cameras)
    assert (box[0] < [-4, -4, 0.6]).all() and (box[1] > [4, 4, 2.5]).all()
    # An arc of cameras looking at a point in front of them: the point is inside.
    from edgerecon.geometry import look_at

    cams = []
    for i, a in enumerate(np.radians([-30, -15, 0, 15, 30])):
        R, t = look_at((4 * np.sin(a), -4 * np.cos(a), 1.5), (0.0, 0.0, 1.0))
        K = np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]])
        cams.append(Camera(name=f"c{i}", width=320, height=240, K=K, R=R, t=t))
    box = rig_region(cams)
    assert (box[0] < [0, 1.5, 1.0]).all() and (box[1] > [0, 1.5, 1.0]).all()


def test_phantoms_of_two_objects_seen_by_three_cameras_are_removed() -> None:
    # Three cameras 90-100 degrees apart and two boxes: the silhouette cones also intersect
    # where there is no object (phantoms); they explain no pixel of their own.
    from edgerecon.geometry import look_at

    cams = []
    for i, a in enumerate(np.radians([10, 100, 200])):
        R, t = look_at((4 * np.cos(a), 4 * np.sin(a), 1.8), (0.0, 0.0, 0.8))
        K = np.array([[250.0, 0, 159.5], [0, 250, 119.5], [0, 0, 1]])
        cams.append(Camera(name=f"c{i}", width=320, height=240, K=K, R=R, t=t))
    boxes = [
        (np.array([0.6, 0.5, 0.0]), np.array([1.0, 0.9, 1.6])),
        (np.array([-1.0, -0.9, 0.0]), np.array([-0.6, -0.5, 1.6])),
    ]
    masks = [box_silhouette(c, *boxes[0]) | box_silhouette(c, *boxes[1]) for c in cams]
    centres = np.array([(lo + hi) / 2 for lo, hi in boxes])
    raw = visual_hull(cams, masks, HullConfig(voxel_size=0.04, remove_phantoms=False))
    assert raw.num_objects >= 4
    hull = visual_hull(cams, masks, HullConfig(voxel_size=0.04))
    assert hull.num_objects == 2
    assert sorted(hull.label_points(centres).tolist()) == [1, 2]
    for k, (lo, hi) in zip(hull.label_points(centres), boxes, strict=True):
        assert (hull.label_points(box_surface_points(lo, hi, 6)) == k).all()


def _facing_scene():  # type: ignore[no-untyped-def]
    """Four narrow (portrait-like) cameras 90 degrees apart. A box at the centre is seen by
    all; a second detection lies out of cameras 0 and 2's view, so only cameras 1 and 3,
    which face each other, see it (a ghost they share)."""
    from edgerecon.geometry import look_at

    cams = []
    for i, a in enumerate(np.radians([0, 90, 180, 270])):
        R, t = look_at((4 * np.cos(a), 4 * np.sin(a), 1.0), (0.0, 0.0, 0.8))
        K = np.array([[400.0, 0, 89.5], [0, 400, 159.5], [0, 0, 1]])
        cams.append(Camera(name=f"c{i}", width=180, height=320, K=K, R=R, t=t))
    centre = (np.array([-0.25, -0.25, 0.0]), np.array([0.25, 0.25, 1.6]))
    seen_by_two = (np.array([-0.2, 2.1, 0.4]), np.array([0.2, 2.5, 1.2]))
    masks = []
    for i, c in enumerate(cams):
        m = box_silhouette(c, *centre)
        if i in (1, 3):
            m |= box_silhouette(c, *seen_by_two)
        else:  # out of view of cameras 0 and 2
            uv, _ = c.project(box_surface_points(*seen_by_two, 6))
            assert not c.in_image(uv).any()
        masks.append(m)
    return cams, masks, centre, seen_by_two


def test_an_object_only_two_facing_cameras_see_is_a_phantom() -> None:
    # Cameras 1 and 3's cones through the second detection meet along their whole shared
    # line of sight, the volume explains pixels of its own (the old rule kept it), and no
    # pair of cameras could place it in depth.
    cams, masks, centre, seen_by_two = _facing_scene()
    middle = (centre[0] + centre[1]) / 2
    off = (seen_by_two[0] + seen_by_two[1]) / 2
    cfg = HullConfig(voxel_size=0.04)
    # Cameras 0 and 2 face each other too: their cones through the box meet along the x
    # axis out of cameras 1 and 3's view. Without the rule the two long volumes each hold
    # pixels of their own, and the box, covered by them in every camera and smaller, went.
    old = visual_hull(cams, masks, dataclasses.replace(cfg, phantom_pair_angle_deg=180.0))
    assert old.num_objects == 2 and old.contains(off[None])[0]
    assert not old.contains(middle[None])[0]
    hull = visual_hull(cams, masks, cfg)
    assert hull.num_objects == 1
    assert hull.contains(middle[None])[0] and not hull.contains(off[None])[0]
    assert (hull.label_points(box_surface_points(*centre, 6)) == 1).all()
    # What stereo pairs could measure of each object (the phantom ordering's key).
    raw = visual_hull(cams, masks, dataclasses.replace(cfg, remove_phantoms=False))
    shares = _paired_shares(raw, *_pair_geometry(raw, cams, masks, 130.0))
    k_mid = int(raw.label_points(middle[None])[0])
    assert raw.num_objects >= 3 and k_mid > 0
    assert shares[k_mid - 1] > 0.8
    assert (np.delete(shares, k_mid - 1) == 0.0).all()
    with pytest.raises(ValueError, match="phantom_pair_angle_deg"):
        HullConfig(phantom_pair_angle_deg=0.0)


def test_unexplained_pixels_leave_the_masks_only_where_allowed(rig: Rig, box_hull) -> None:  # type: ignore[no-untyped-def]
    hull, masks = box_hull
    ghost = np.zeros_like(masks[0])
    ghost[5:25, 5:25] = True  # far from the box's silhouette
    assert not (ghost & masks[0]).any()
    with_ghost = [masks[0] | ghost, *masks[1:]]
    everywhere = [np.ones_like(m) for m in masks]
    out = hull_explained_masks(hull, rig.cameras, with_ghost, everywhere, grow_px=2)
    assert not out[0][ghost].any()
    for got, m in zip(out, masks, strict=True):
        assert got is not None and (got & m).sum() >= 0.99 * m.sum()
    # Pixels outside ``allowed`` (settled ones) stay, and so does a camera without a mask.
    nowhere = [np.zeros_like(m) for m in masks]
    kept = hull_explained_masks(hull, rig.cameras, with_ghost, nowhere, grow_px=2)
    assert kept[0][ghost].all()
    partial = hull_explained_masks(hull, rig.cameras, [None, *with_ghost[1:]], everywhere)
    assert partial[0] is None


def test_pixels_only_a_phantom_explains_leave_the_masks(rig: Rig, box_hull) -> None:  # type: ignore[no-untyped-def]
    cams, masks, centre, seen_by_two = _facing_scene()
    hull = visual_hull(cams, masks, HullConfig(voxel_size=0.04))
    assert hull.num_objects == 1 and len(hull.phantom_surface) > 0
    # What survives the consistency test (no other camera contradicts a pixel): camera 1's
    # ghost along camera 3's line of sight (camera 3 sees the detection behind the box).
    consistent = hull_consistent_masks(hull, cams, masks)
    masks = [m & c for m, c in zip(masks, consistent, strict=True)]
    bodies = [box_silhouette(c, *centre) for c in cams]
    ghosts = [
        m & box_silhouette(c, *seen_by_two) & ~b
        for m, c, b in zip(masks, cams, bodies, strict=True)
    ]
    assert ghosts[1].sum() > 50 and not ghosts[3].any()
    # The models saw the background under the box (its pixels are settled), not under the
    # ghost.
    unsettled = [~b for b in bodies]
    out = phantom_explained_masks(hull, cams, masks, unsettled, grow_px=2)
    for i, (got, m, g, body) in enumerate(zip(out, masks, ghosts, bodies, strict=True)):
        assert got is not None
        assert (got & body).sum() >= 0.99 * (m & body).sum()  # the real object stays
        if i != 1:
            assert (got == m).all()
            continue
        # The ghost's pixels that the phantom explains are gone (the rest of it lies where
        # only camera 1 sees, which no hull holds either way); nothing else is.
        near = cv2.dilate(hull_silhouette(hull, cams[i]).astype(np.uint8), np.ones((5, 5)))
        explained = g & phantom_silhouette(hull, cams[i]) & ~near.astype(bool)
        assert explained.sum() > 0.3 * g.sum()
        assert not got[explained].any()
        assert not (m & ~got & ~g).any()
    # Settled pixels stay; a camera without a mask stays without one.
    nowhere = [np.zeros_like(m) for m in masks]
    kept = phantom_explained_masks(hull, cams, masks, nowhere, grow_px=2)
    assert all((k == m).all() for k, m in zip(kept, masks, strict=True))
    partial = phantom_explained_masks(hull, cams, [None, *masks[1:]], unsettled, grow_px=2)
    assert partial[0] is None and partial[1] is not None and (partial[1] == out[1]).all()
    # The first second of a stream: no mask pixel is settled yet, and an actor the models
    # learned, which only facing cameras still detect, looks like a phantom. Nothing goes.
    everywhere = [np.ones_like(m) for m in masks]
    first = phantom_explained_masks(hull, cams, masks, everywhere, grow_px=2)
    assert all((f == m).all() for f, m in zip(first, masks, strict=True))
    # A hull without phantoms (one box, every camera) explains its masks as they are.
    single, box_masks = box_hull
    assert len(single.phantom_surface) == 0
    same = phantom_explained_masks(single, rig.cameras, box_masks, [~m for m in box_masks])
    assert all((a == b).all() for a, b in zip(same, box_masks, strict=True))


def test_a_hole_in_one_camera_is_filled_from_the_others(rig: Rig, box_hull) -> None:  # type: ignore[no-untyped-def]
    _, masks = box_hull
    holed = [m.copy() for m in masks]
    ys, xs = np.nonzero(masks[1])
    cy, cx = int(ys.mean()), int(xs.mean())
    hole = np.zeros_like(masks[1])
    hole[cy - 6 : cy + 6, cx - 6 : cx + 6] = True  # a still actor's part the model holds
    holed[1] &= ~hole
    cfg = HullConfig(voxel_size=VOXEL)
    exact = visual_hull(rig.cameras, holed, cfg)
    filled = hull_filled_masks(exact, rig.cameras, holed, holed, cfg)
    assert filled[1][hole].mean() > 0.9
    for c, (m, f) in enumerate(zip(masks, filled, strict=True)):
        assert not (f & ~m).any(), f"camera {c} gained pixels outside its silhouette"
    assert mask_iou(filled[1], masks[1]) > mask_iou(holed[1], masks[1])
    # Only where allowed (the background model's unsettled pixels) ...
    none = [np.zeros_like(m) for m in masks]
    kept = hull_filled_masks(exact, rig.cameras, holed, holed, cfg, allowed=none)
    assert all(np.array_equal(k, h) for k, h in zip(kept, holed, strict=True))
    # ... and never from fewer than 4 cameras (a 2-of-3 hull is too loose to vouch).
    three = [holed[i] if i < 3 else None for i in range(len(holed))]
    exact3 = visual_hull(rig.cameras, three, cfg)
    same = hull_filled_masks(exact3, rig.cameras, three, three, cfg)
    assert np.array_equal(same[1], holed[1])


def test_an_object_one_unsettled_camera_carved_away_comes_back(rig: Rig) -> None:
    lo2, hi2 = LO + np.array([1.2, 0.8, 0.0]), HI + np.array([1.2, 0.8, -0.4])
    box1 = [box_silhouette(c, LO, HI) for c in rig]
    box2 = [box_silhouette(c, lo2, hi2) for c in rig]
    model = [a | b for a, b in zip(box1, box2, strict=True)]
    model[0] = box1[0].copy()  # camera 0's model learned box 2 while it stood there
    unsettled = [np.zeros_like(m) for m in model]
    unsettled[0] = cv2.dilate(box2[0].view(np.uint8), np.ones((9, 9), np.uint8)) > 0
    cfg = HullConfig(voxel_size=0.03)
    exact = visual_hull(rig.cameras, model, cfg)
    assert exact.num_objects == 1
    consistent = hull_consistent_masks(exact, rig.cameras, model)
    # ... and the hull consistency removes most of box 2 from the other cameras' masks.
    kept = sum(int(c[b].sum()) for c, b in zip(consistent[1:], box2[1:], strict=True))
    assert kept < 0.2 * sum(int(b.sum()) for b in box2[1:])

    hull, masks, rescue = hull_rescued(exact, rig.cameras, consistent, model, unsettled, cfg)
    assert rescue.objects == 1 and rescue.dissenters == (0,)
    assert hull.num_objects == 2
    assert hull.label_points(np.array([(lo2 + hi2) / 2, (LO + HI) / 2])).min() > 0
    # The exact hull's own voxels are all still there.
    assert hull.contains(exact.centers).all()
    for c in range(1, len(rig)):
        assert masks[c][box2[c]].mean() > 0.95
        assert not (masks[c] & ~model[c]).any()  # only the models' own pixels come back
    assert np.array_equal(masks[0], consistent[0])

    def unchanged(*args, **kwargs):  # type: ignore[no-untyped-def]
        h, m, r = hull_rescued(*args, **kwargs)
        return (
            h is exact
            and all(np.array_equal(a, b) for a, b in zip(m, consistent, strict=True))
            and r.objects == 0
        )

    # Where camera 0's model is settled, its veto stands.
    settled = [np.zeros_like(m) for m in model]
    assert unchanged(exact, rig.cameras, consistent, model, settled, cfg)
    # Two cameras against the object: not brought back.
    two = list(model)
    two[3] = box1[3].copy()
    exact2 = visual_hull(rig.cameras, two, cfg)
    consistent2 = hull_consistent_masks(exact2, rig.cameras, two)
    both = list(unsettled)
    both[3] = cv2.dilate(box2[3].view(np.uint8), np.ones((9, 9), np.uint8)) > 0
    _, _, r2 = hull_rescued(exact2, rig.cameras, consistent2, two, both, cfg)
    assert r2.objects == 0
    # A hull that already tolerates a camera, or fewer than 4 cameras with a mask: nothing.
    tolerant = dataclasses.replace(cfg, max_missing=1)
    assert unchanged(exact, rig.cameras, consistent, model, unsettled, tolerant)
    three = [m if i < 3 else None for i, m in enumerate(model)]
    three_c = [m if i < 3 else None for i, m in enumerate(consistent)]
    h3, _, r3 = hull_rescued(exact, rig.cameras, three_c, three, unsettled, cfg)
    assert h3 is exact and r3.objects == 0


# ---- the visual hull's per-level carving: the compiled kernel against its NumPy version


def _project_voxels_reference(
    cam: Camera, idx: NDArray[np.int64], origin: NDArray[np.float64], size: float
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
    """(u, v, depth) of voxel centres ``origin + (idx + 0.5) * size`` in ``cam`` (distortion
    applied), float32: the centres are an affine function of the integer indices, so this
    avoids an (N, 3) float64 matrix product per camera."""
    A = (cam.R * size).astype(np.float32)
    b = (cam.R @ (origin + 0.5 * size) + cam.t).astype(np.float32)
    f = idx.astype(np.float32)
    i, j, k = f[:, 0], f[:, 1], f[:, 2]
    xc = A[0, 0] * i + A[0, 1] * j + A[0, 2] * k + b[0]
    yc = A[1, 0] * i + A[1, 1] * j + A[1, 2] * k + b[1]
    zc = A[2, 0] * i + A[2, 1] * j + A[2, 2] * k + b[2]
    # Voxels in the camera's plane (zc = 0, beside a camera) get non-finite pixels, which no
    # image holds: the callers drop them with the voxels behind the camera.
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        xn = xc / zc
        yn = yc / zc
        if cam.has_distortion:
            k1, k2, p1, p2, k3 = (np.float32(x) for x in cam.dist)
            r2 = xn * xn + yn * yn
            radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            xd = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
            yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
            xn, yn = xd, yd
        K = cam.K.astype(np.float32)
        u = K[0, 0] * xn + K[0, 1] * yn + K[0, 2]
        v = K[1, 1] * yn + K[1, 2]
    return u, v, zc


def _carve_level_reference(
    idx: NDArray[np.int64],
    origin: NDArray[np.float64],
    size: float,
    cameras: Sequence[Camera],
    dists: Sequence[Any],
    walls: Sequence[NDArray[np.float32] | None],
    config: HullConfig,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """(keep, full) among voxels of edge ``size``: ``keep`` = survives; ``full`` = its whole
    footprint lies inside the silhouette in every camera that can see any part of it (then
    every child survives too and need not be tested)."""
    n = len(idx)
    agree = np.zeros(n, np.int32)
    missing = np.zeros(n, np.int32)
    full = np.ones(n, bool)
    half_diag = np.float32(0.5 * np.sqrt(3.0) * size)
    tol = np.float32(config.tolerance_px + 0.71)  # + 0.71: the centre is rounded to a pixel
    for cam, dist, wall in zip(cameras, dists, walls, strict=True):
        if dist is None:
            continue
        to_fg, to_fg_or_border, inside_dist = dist
        u, v, depth = _project_voxels_reference(cam, idx, origin, size)
        front = depth > half_diag
        with np.errstate(invalid="ignore", divide="ignore"):
            radius = np.where(
                front, half_diag * np.float32(cam.focal_px * _FOOTPRINT_SLACK) / depth, np.inf
            )
            ur = np.rint(u)
            vr = np.rint(v)
            inside = front & (ur >= 0) & (ur < cam.width) & (vr >= 0) & (vr < cam.height)
            # Any part of the footprint may reach into the image: children may be seen.
            near = (depth > -half_diag) & ~(
                (u < -radius - 1)
                | (u > cam.width + radius)
                | (v < -radius - 1)
                | (v > cam.height + radius)
            )
        if wall is not None:
            # Behind the static scene (by more than the voxel): hidden from this camera.
            uc = np.clip(np.nan_to_num(ur), 0, cam.width - 1).astype(np.intp)
            vc = np.clip(np.nan_to_num(vr), 0, cam.height - 1).astype(np.intp)
            hidden = inside & (depth - half_diag > wall[vc, uc])
            inside &= ~hidden
            near &= ~hidden
        ii = np.flatnonzero(inside)
        ui = ur[ii].astype(np.intp)
        vi = vr[ii].astype(np.intp)
        r = radius[ii]
        # A camera confirms a voxel whose footprint touches its silhouette, and carves one whose
        # footprint touches neither the silhouette nor the image border (beyond the border,
        # part of the voxel may be foreground that this camera does not see).
        agree[ii[to_fg[vi, ui] <= r + tol]] += 1
        missing[ii[to_fg_or_border[vi, ui] > r + tol]] += 1
        covered = np.zeros(n, bool)
        covered[ii] = inside_dist[vi, ui] >= r + np.float32(0.71)
        full &= ~near | covered
    num_masks = sum(d is not None for d in dists)
    # At least min_views cameras put the voxel in their foreground, at most max_missing not.
    keep = (agree >= max(min(config.min_views, num_masks), 1)) & (missing <= config.max_missing)
    return keep, keep & full


@pytest.mark.parametrize("distorted", [False, True])
@pytest.mark.parametrize("with_walls", [False, True])
def test_the_compiled_carving_is_the_numpy_carving_bit_for_bit(
    rig: Rig, distorted: bool, with_walls: bool
) -> None:
    from edgerecon.scene.hull import _carve_level, _distance_to_silhouette

    dist = np.array([-0.25, 0.08, 0.002, -0.001, 0.01]) if distorted else np.zeros(5)
    cams = [dataclasses.replace(c, dist=dist) for c in rig]
    masks = [box_silhouette(c, LO, HI) for c in rig]
    masks[1][:, : masks[1].shape[1] // 2] = False  # a camera that misses part of it
    dists = [_distance_to_silhouette(m) for m in masks]
    dists[2] = None  # a camera without a mask
    rng = np.random.default_rng(11)
    walls = [
        # Static depths around the box's: hiding it from a camera at some pixels only.
        (
            rng.uniform(0.9, 1.5, (c.height, c.width)) * np.linalg.norm(c.center - (LO + HI) / 2)
        ).astype(np.float32)
        if with_walls
        else None
        for c in cams
    ]
    config = HullConfig(voxel_size=VOXEL)
    region = rig_region(cams)
    kept, fulls = [], []
    for size in (0.16, 0.04):
        # Voxels over the whole region, beyond it and through the cameras' planes.
        lo = np.floor((region[0] - 1.0) / size).astype(np.int64)
        hi = np.ceil((region[1] + 1.0) / size).astype(np.int64)
        far = np.stack([rng.integers(a, b, 20000) for a, b in zip(lo, hi, strict=True)], 1)
        g = [
            np.arange(np.floor(a / size) - 2, np.ceil(b / size) + 2)
            for a, b in zip(LO, HI, strict=True)
        ]
        near = np.stack(np.meshgrid(*g, indexing="ij"), -1).reshape(-1, 3).astype(np.int64)
        idx = np.concatenate([near, far])
        origin = np.zeros(3)
        keep, full = _carve_level(idx, origin, size, cams, dists, walls, config)
        ref = _carve_level_reference(idx, origin, size, cams, dists, walls, config)
        np.testing.assert_array_equal(keep, ref[0])
        np.testing.assert_array_equal(full, ref[1])
        kept.append(keep.mean())
        fulls.append(full.mean())
    # Votes of every kind happened (the test is not vacuous).
    assert 0 < min(kept) and max(kept) < 1 and max(fulls) > 0


def test_the_compiled_surface_normals_are_numpy_s() -> None:
    """``_surface_normals`` through the compiled pass gives NumPy's surface flags and
    normals, to the bit (a random blob of voxels with holes and single cells)."""
    from edgerecon.scene.hull import _NEIGHBOURS6, _empty_neighbours, _surface_normals

    rng = np.random.default_rng(5)
    grid = rng.random((14, 11, 9)) < 0.55
    idx = np.argwhere(grid).astype(np.int64) + np.array([-40, 7, 1000])
    surface, normals = _surface_normals(idx)
    empty_nb = _empty_neighbours(idx)
    outward = empty_nb.astype(np.float64) @ _NEIGHBOURS6.astype(np.float64)
    norm = np.linalg.norm(outward, axis=1, keepdims=True)
    want = np.where(norm > 0, outward / np.maximum(norm, 1e-12), 0.0).astype(np.float32)
    np.testing.assert_array_equal(surface, empty_nb.any(axis=1))
    np.testing.assert_array_equal(normals, want)
    assert 0 < surface.mean() < 1 and normals.dtype == np.float32
