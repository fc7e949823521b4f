"""Still foreground (scene.still): what changed since the snapshot is densified, the rest kept."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from edgerecon.scene.still import (
    StillCache,
    StillConfig,
    changed_pixels,
    make_snapshot,
    plan_still,
    reference_of,
)
from edgerecon.types import PointCloud
from tests.conftest import ring_rig

CENTER = np.array([0.0, 0.0, 1.0])
RADIUS = 0.4


def _sphere(n: int = 6000, seed: int = 0) -> PointCloud:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pts = CENTER + RADIUS * d
    return PointCloud(points3D=pts, colors=np.full((n, 3), 128, np.uint8))


def _scene(seed: int = 1):
    """A 4-camera rig at 320x240, a textured frame per camera and the sphere's masks."""
    rig = ring_rig(4, width=320, height_px=240, focal_px=250.0)
    rng = np.random.default_rng(seed)
    sphere = _sphere()
    images, masks = [], []
    for cam in rig:
        # Texture a few pixels across, as on clothes and walls.
        coarse = rng.integers(40, 200, size=(cam.height // 4, cam.width // 4, 3)).astype(np.uint8)
        img = cv2.resize(coarse, (cam.width, cam.height), interpolation=cv2.INTER_LINEAR)
        uv, _ = cam.project(sphere.points3D)
        m = np.zeros((cam.height, cam.width), bool)
        u = np.clip(np.rint(uv[:, 0]).astype(int), 0, cam.width - 1)
        v = np.clip(np.rint(uv[:, 1]).astype(int), 0, cam.height - 1)
        m[v, u] = True
        m = cv2.dilate(m.view(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        images.append(img)
        masks.append(m)
    return rig, sphere, images, masks


def test_an_unchanged_foreground_is_kept_whole_and_densified_nowhere():
    rig, sphere, images, masks = _scene()
    cfg = StillConfig()
    snap = make_snapshot(5, sphere, images, masks, list(rig), cfg)
    # The points are seen by the cameras that face them (the cameras are above the
    # sphere's centre: its lowest cap by none), not by every camera.
    seen = snap.seen.any(axis=1)
    assert seen.mean() > 0.8
    assert seen[sphere.points3D[:, 2] > CENTER[2]].mean() > 0.9  # grazing ones at the limbs not
    assert snap.seen.sum(axis=1).mean() < 3.0
    current = reference_of(9, images, masks, cfg)
    plan = plan_still(masks, current, snap, cfg)
    assert plan is not None and plan.snapshot_time == 5
    assert plan.share > 0.99
    assert all(not d.any() for d in plan.dense_masks)
    assert len(plan.kept) > 0.98 * seen.sum()


def test_a_changed_part_is_densified_and_its_points_dropped():
    rig, sphere, images, masks = _scene()
    cfg = StillConfig()
    snap = make_snapshot(0, sphere, images, masks, list(rig), cfg)
    # The sphere's upper half changes in every camera (an arm raised over it).
    changed_images = []
    upper = sphere.points3D[:, 2] > CENTER[2] + 0.1
    for cam, img in zip(rig, images, strict=True):
        uv, _ = cam.project(sphere.points3D[upper])
        top = int(np.floor(uv[:, 1].min())) - 2
        bottom = int(np.ceil(uv[:, 1].max())) + 2
        out = img.copy()
        out[max(0, top) : bottom] = np.clip(out[max(0, top) : bottom].astype(int) + 60, 0, 255)
        changed_images.append(out.astype(np.uint8))
    current = reference_of(1, changed_images, masks, cfg)
    plan = plan_still(masks, current, snap, cfg)
    assert plan is not None
    assert 0.25 < plan.share < 0.8
    for m, d in zip(masks, plan.dense_masks, strict=True):
        assert d.any() and d.sum() < m.sum()
        assert not (d & ~m).any()  # only mask pixels are densified
    kept_z = plan.kept.points3D[:, 2]
    # The upper half's points are dropped, the lower half's kept.
    assert (kept_z > CENTER[2] + 0.2).sum() < 0.05 * (sphere.points3D[:, 2] > CENTER[2] + 0.2).sum()
    seen = snap.seen.any(axis=1)
    lower = (seen & (sphere.points3D[:, 2] < CENTER[2] - 0.15)).sum()
    assert (kept_z < CENTER[2] - 0.15).sum() > 0.8 * lower


def test_an_exposure_change_is_not_a_change():
    rig, sphere, images, masks = _scene()
    cfg = StillConfig()
    snap = make_snapshot(0, sphere, images, masks, list(rig), cfg)
    brighter = [np.clip(im.astype(np.float32) * 1.25, 0, 255).astype(np.uint8) for im in images]
    plan = plan_still(masks, reference_of(1, brighter, masks, cfg), snap, cfg)
    assert plan is not None and plan.share > 0.9
    # Without the exposure's compensation, most pixels would have changed.
    ref = snap.reference
    cur = reference_of(1, brighter, masks, cfg)
    assert changed_pixels(cur.greys[0], ref.greys[0], cfg).mean() > 0.5


def _painted(rig, images, sphere, grey):
    """The frames with the sphere painted one uniform grey, and its masks."""
    out, masks = [], []
    for cam, img in zip(rig, images, strict=True):
        uv, _ = cam.project(sphere.points3D)
        m = np.zeros((cam.height, cam.width), np.uint8)
        u = np.clip(np.rint(uv[:, 0]).astype(int), 0, cam.width - 1)
        v = np.clip(np.rint(uv[:, 1]).astype(int), 0, cam.height - 1)
        m[v, u] = 1
        m = cv2.dilate(m, np.ones((5, 5), np.uint8)).astype(bool)
        im = img.copy()
        im[m] = grey
        out.append(im)
        masks.append(m)
    return out, masks


def test_a_uniform_object_that_moved_is_densified_whole():
    # Inside the outlines of a uniform grey ball that rolled by a third of its width, no grey
    # level changes: its outline tells that it moved, and none of its old points stay.
    rig, sphere, images, _ = _scene()
    cfg = StillConfig()
    before, masks0 = _painted(rig, images, sphere, 90)
    snap = make_snapshot(0, sphere, before, masks0, list(rig), cfg)
    moved = PointCloud(points3D=sphere.points3D + [0.0, 0.27, 0.0], colors=sphere.colors)
    after, masks = _painted(rig, images, moved, 90)
    # The task densifies it all (the few old points no camera saw move are not worth it).
    assert plan_still(masks, reference_of(1, after, masks, cfg), snap, cfg) is None
    # Without that rule, the cameras' neighbours that saw it roll densify what they see;
    # of the old points only a few within the ball's visual hull where it is now stay
    # (seen by the cameras it rolled towards, inside every outline grown by the margin:
    # what no frame can tell; the hull of a ball from four cameras 90 degrees apart
    # reaches sqrt(2) of its radius, the margin's 4 grid pixels are 13 cm at 4 m).
    kept_any = StillConfig(min_kept=0.0)
    plan = plan_still(masks, reference_of(1, after, masks, kept_any), snap, kept_any)
    assert plan is not None
    for cam, m, d in zip(rig, masks, plan.dense_masks, strict=True):
        facing = abs(cam.center[1]) > abs(cam.center[0])
        assert d.sum() > (0.0 if facing else 0.9 * m.sum())
    inside = np.linalg.norm(plan.kept.points3D - (CENTER + [0.0, 0.27, 0.0]), axis=1)
    assert len(plan.kept) < 0.2 * len(sphere) and (inside < 1.45 * RADIUS + 0.13).all()
    # Without the outline's test, more of the old ball would stay (and be densified less).
    loose = StillConfig(min_outline_iou=0.0, min_kept=0.0)
    plan_loose = plan_still(masks, reference_of(1, after, masks, loose), snap, loose)
    assert plan_loose is not None and len(plan_loose.kept) > 1.5 * len(plan.kept)
    assert plan_loose.share > plan.share


def test_little_still_densifies_everything():
    rig, sphere, images, masks = _scene()
    cfg = StillConfig(min_share=0.5)
    snap = make_snapshot(0, sphere, images, masks, list(rig), cfg)
    other = [np.roll(im, 7, axis=1) for im in images]  # everything moved
    assert plan_still(masks, reference_of(1, other, masks, cfg), snap, cfg) is None
    cache = StillCache(cfg)
    assert cache.plan(images, masks, 1) is None  # no snapshot yet
    cache.set_snapshot(snap)
    assert cache.snapshot_time == 0 and cache.snapshots == 1
    assert cache.plan(other, masks, 1) is None
    plan = cache.plan(images, masks, 1)
    assert plan is not None and plan.share > 0.99


def test_a_camera_without_a_frame_densifies_its_mask_and_a_left_person_takes_nothing():
    rig, sphere, images, masks = _scene()
    cfg = StillConfig()
    snap = make_snapshot(0, sphere, images, masks, list(rig), cfg)
    frames = [None, *images[1:]]
    cut = [None, *masks[1:]]
    plan = plan_still(cut, reference_of(1, frames, cut, cfg), snap, cfg)
    assert plan is not None and plan.dense_masks[0] is None
    # The person left: no mask pixel anywhere, nothing still, nothing densified.
    empty = [np.zeros_like(m) for m in masks]
    assert plan_still(empty, reference_of(1, images, empty, cfg), snap, cfg) is None


@pytest.mark.parametrize(
    "kw",
    [
        {"change_threshold": 0.0},
        {"blur_px": 0},
        {"downsample": 0},
        {"margin_px": -1},
        {"min_share": 1.5},
        {"min_outline_iou": -0.1},
        {"min_kept": 2.0},
        {"min_change_px": -1},
        {"visibility_tol": -0.1},
    ],
)
def test_settings_are_checked(kw):
    with pytest.raises(ValueError):
        StillConfig(**kw)
