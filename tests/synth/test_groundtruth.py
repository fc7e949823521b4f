"""Ground-truth clouds, view counts and the ground-truth reader."""

from __future__ import annotations

import numpy as np
import pytest

from edgerecon.geometry import Camera, Rig, look_at
from edgerecon.quality import evaluate_clouds
from edgerecon.synth import GroundTruth, count_views, sample_visible_cloud
from edgerecon.synth.groundtruth import voxel_first
from edgerecon.types import DataError


def test_voxel_first_keeps_one_real_point_per_voxel():
    pts = np.array([[0.001, 0.001, 0.001], [0.004, 0.002, 0.0], [0.011, 0, 0], [-0.001, 0, 0]])
    keep = voxel_first(pts, 0.01)
    assert list(keep) == [0, 2, 3]
    assert len(voxel_first(np.zeros((0, 3)), 0.01)) == 0


def _wall_rig():
    """Three cameras looking at the plane z = 0 from z = 4 (one looks away)."""
    cams = []
    for i, (x, look) in enumerate([(-1.0, 0.0), (1.0, 0.0), (0.0, None)]):
        if look is None:
            R, t = look_at((x, 0, 4), (x, 0, 8), up=(0, 1, 0))
        else:
            R, t = look_at((x, 0, 4), (look, 0, 0), up=(0, 1, 0))
        K = np.array([[100.0, 0, 49.5], [0, 100.0, 49.5], [0, 0, 1]])
        cams.append(Camera(name=f"c{i}", width=100, height=100, K=K, R=R, t=t))
    return Rig(cameras=tuple(cams))


def test_count_views_known_answer():
    rig = _wall_rig()
    # Ground-truth depth of the plane z = 0 in each camera (the third sees nothing of it).
    depths, masks = [], []
    for cam in rig:
        h, w = cam.height, cam.width
        vv, uu = np.mgrid[0:h, 0:w]
        rays = cam.pixel_rays(np.stack([uu.ravel(), vv.ravel()], axis=1)) @ cam.R  # world dirs
        s = -cam.center[2] / rays[:, 2]
        depth = np.where(s > 0, s, 100.0).reshape(h, w).astype(np.float32)
        depths.append(depth)
        masks.append(np.zeros((h, w), np.uint8))
    pts = np.array([[0.0, 0.0, 0.0], [2.2, 0.0, 0.0], [0.0, 0.0, 0.5], [50.0, 0, 0]])
    labels = np.zeros(4, np.int32)
    views = count_views(pts, labels, rig, depths, masks)
    # On the plane, in both looking cameras; only in the left one; floating (occluding
    # nothing, but not on the surface any camera sees); far outside every image.
    assert list(views) == [2, 1, 0, 0]
    # A wrong object id is not "seen" even at the right depth.
    assert list(count_views(pts[:1], np.array([3], np.int32), rig, depths, masks)) == [0]


@pytest.mark.parametrize("which", ["demo", "hd4"])
def test_sampled_clouds_lie_on_surfaces_and_count_views(
    which, small_renderer, small_frame, hd4_renderer
):
    renderer, frame, t, ids = small_renderer, small_frame, 2, {1, 2}
    if which == "hd4":  # 4 cameras 90 degrees apart: fewer points seen twice
        renderer, t, ids = hd4_renderer, 212, {1, 2, 3}
        frame = renderer.render(t, clean=True)
    scene = renderer.scene
    rays = [renderer.rays(i) for i in range(len(scene.rig))]
    fg = sample_visible_cloud(
        scene.rig,
        rays,
        frame.depths,
        frame.masks,
        frame.clean,
        voxel_m=0.003,
        part="foreground",
    )
    assert len(fg) > 5000
    assert set(np.unique(fg.labels)) == ids
    views = fg.attributes["num_views"]
    assert views.min() >= 1  # every sampled point is seen by the camera it came from
    assert (views >= 2).mean() > (0.4 if which == "hd4" else 0.5)
    assert fg.colors is not None and fg.colors.std() > 10
    # Points lie on the actors' ellipsoids (exact geometry).
    parts = [p for a in scene.actors_at(t) for p in a.parts(float(t))]
    best = np.full(len(fg), np.inf)
    for p in parts:
        local = (fg.points3D - p.center) @ p.rotation / p.radii
        best = np.minimum(best, np.abs(np.linalg.norm(local, axis=1) - 1) * p.radii.min())
    assert np.percentile(best, 99.9) < 1e-4


def test_gt_clouds_score_one_against_themselves_and_fail_when_shifted(small_dataset):
    gt = GroundTruth.open(small_dataset.path)
    d = 0.01
    shift = 3 * d * np.ones(3) / np.sqrt(3)
    for part, t in (("foreground", 1), ("background", None), ("all", 3)):
        ref = gt.reference_cloud(t, part=part, min_views=1)
        assert evaluate_clouds(ref, ref, d)[0].fscore == 1.0
        moved = evaluate_clouds(ref.points3D + shift, ref, d)[0]
        assert moved.fscore < 0.5, (part, moved)


def test_reader_matches_renderer(small_dataset, small_scene):
    from edgerecon.synth import Renderer

    gt = GroundTruth.open(small_dataset.path)
    assert gt.num_frames == 4 and gt.camera_names == small_scene.rig.names
    assert gt.rig.to_dict() == small_scene.rig.to_dict()
    frame = Renderer(small_scene).render(3)
    for k, name in enumerate(gt.camera_names):
        assert np.array_equal(gt.depth(name, 3), frame.depths[k])
        assert np.array_equal(gt.object_mask(k, 3), frame.masks[k])
        assert np.array_equal(gt.foreground_mask(k, 3), frame.masks[k] > 0)
    positions = gt.actor_positions(3)
    assert set(positions) == {a.actor_id for a in small_scene.actors_at(3)}
    np.testing.assert_allclose(positions[1], small_scene.actors[0].position(3), atol=1e-4)


def test_reference_cloud_parts_and_min_views(small_dataset):
    gt = GroundTruth.open(small_dataset.path / "gt")  # the gt folder itself also opens
    fg_all = gt.reference_cloud(2, "foreground", min_views=1)
    fg2 = gt.reference_cloud(2, "foreground")  # default: seen by >= 2 cameras
    bg = gt.reference_cloud(None, "background", min_views=1)
    both = gt.reference_cloud(2, "all", min_views=1)
    assert 0 < len(fg2) < len(fg_all)
    assert fg2.attributes["num_views"].min() >= 2
    assert len(both) == len(fg_all) + len(bg)
    assert np.all(bg.labels == 0) and np.all(fg_all.labels >= 1)
    assert len(bg) == small_dataset.num_background_points
    assert len(fg_all) == small_dataset.num_foreground_points[2]


def test_reader_errors_are_clean(small_dataset, tmp_path):
    gt = GroundTruth.open(small_dataset.path)
    with pytest.raises(DataError, match="out of range"):
        gt.depth(0, 99)
    with pytest.raises(DataError, match="unknown camera"):
        gt.object_mask("cam9", 0)
    with pytest.raises(DataError, match="needs a time"):
        gt.reference_cloud(None, "foreground")
    with pytest.raises(DataError, match="part must be"):
        gt.reference_cloud(0, "middle")  # type: ignore[arg-type]
    with pytest.raises(DataError, match="not found"):
        GroundTruth.open(tmp_path / "nothing")
    with pytest.raises(DataError, match="no scene.json"):
        GroundTruth.open(tmp_path)


def test_mask_scores_against_ground_truth_masks(small_dataset):
    import cv2

    from edgerecon.quality.masks import score_mask_set, score_masks

    gt = GroundTruth.open(small_dataset.path)
    masks = [gt.object_mask(c, 2) for c in range(len(gt.rig))]
    perfect = score_mask_set([m.astype(np.int32) * 5 for m in masks], masks)
    assert perfect.foreground_iou == 1.0 and perfect.mean_object_iou == 1.0
    grown = cv2.dilate(masks[0], np.ones((7, 7), np.uint8))
    s = score_masks(grown, masks[0])
    assert s.recall == 1.0 and 0.3 < s.foreground_iou < 0.95
    assert set(s.object_iou) == set(np.unique(masks[0])) - {0}
