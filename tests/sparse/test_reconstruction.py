import dataclasses

import numpy as np
import pytest

from edgerecon.sparse import (
    SparseConfig,
    SparseReconstruction,
    extract_features,
    reconstruct_sparse,
)
from edgerecon.sparse.features import use_affine
from edgerecon.sparse.triangulation import project_all
from edgerecon.views import View
from tests.conftest import ring_rig
from tests.sparse.scenes import box_views, scene_distance


@pytest.fixture(scope="module")
def box6():
    rig, views, planes = box_views(6, seed=0)
    return rig, views, planes, reconstruct_sparse(views, SparseConfig())


def test_box_scene_points_lie_on_the_surfaces(box6):
    _rig, _views, planes, rec = box6
    assert rec.num_points >= 300
    d = scene_distance(planes, rec.points3D)
    # Scene ~4 m across seen from 4 m: most points within 1 cm of the true surface.
    assert np.mean(d <= 0.01) >= 0.85
    assert np.mean(d <= 0.05) >= 0.92
    assert np.median(rec.reprojection_error_px) < 0.7
    assert rec.reprojection_error_px.max() <= SparseConfig().max_reprojection_error_px
    assert rec.triangulation_angle_deg.min() >= SparseConfig().min_triangulation_angle_deg
    assert set(rec.timings.seconds) == {"features", "matching", "triangulation"}
    assert rec.stats["num_points"] == rec.num_points


def test_observations_reproject_and_match_visibility(box6):
    _rig, views, _planes, rec = box6
    P, V = rec.visibility.shape
    assert V == len(views) and P == rec.num_points
    # visibility is exactly the set of observations
    vis = np.zeros_like(rec.visibility)
    vis[rec.observation_point_ids, rec.observation_view_ids] = True
    assert np.array_equal(vis, rec.visibility)
    assert np.array_equal(rec.visibility.sum(axis=1), rec.cloud.attributes["num_views"])
    assert rec.visibility.sum(axis=1).min() >= 2
    uv, depth = project_all([v.camera for v in views], rec.points3D)
    pred = uv[rec.observation_point_ids, rec.observation_view_ids]
    err = np.linalg.norm(pred - rec.observation_points2D, axis=1)
    assert err.max() <= SparseConfig().max_reprojection_error_px + 1e-9
    assert np.all(depth[rec.observation_point_ids, rec.observation_view_ids] > 0)
    # mean reprojection error per point agrees with the observations
    mean = np.bincount(rec.observation_point_ids, err) / np.bincount(rec.observation_point_ids)
    assert np.allclose(mean, rec.reprojection_error_px)


def test_colours_come_from_the_images(box6):
    _rig, views, _planes, rec = box6
    k = rec.observation_point_ids == 0
    samples = [
        views[v].image[round(y), round(x), ::-1]
        for v, (x, y) in zip(rec.observation_view_ids[k], rec.observation_points2D[k], strict=True)
    ]
    assert np.abs(rec.cloud.colors[0].astype(float) - np.mean(samples, axis=0)).max() < 25
    assert rec.cloud.colors.std() > 10  # not a constant colour


def test_visibility_matrix_indexed_by_rig_camera_ids():
    _rig, views, _planes = box_views(6, seed=1)
    subset = [views[i] for i in (1, 3, 4, 5)]
    rec = reconstruct_sparse(subset, SparseConfig(affine_simulation="off"))
    assert rec.camera_ids == (1, 3, 4, 5)
    A = rec.visibility_matrix(6)
    assert A.shape == (rec.num_points, 6)
    assert not A[:, [0, 2]].any()
    assert np.array_equal(A[:, [1, 3, 4, 5]], rec.visibility)
    with pytest.raises(ValueError, match="camera id 5"):
        rec.visibility_matrix(5)


def test_select_keeps_observations_consistent(box6):
    rec = box6[3]
    keep = rec.points3D[:, 2] > 0.5  # the upper half of the box
    sub = rec.select(keep)
    assert sub.num_points == int(keep.sum()) > 0
    vis = np.zeros_like(sub.visibility)
    vis[sub.observation_point_ids, sub.observation_view_ids] = True
    assert np.array_equal(vis, sub.visibility)
    assert np.array_equal(sub.points3D, rec.points3D[keep])


def test_mask_restricts_features_and_points():
    _rig, views, _planes = box_views(5, seed=2)
    masked = []
    for v in views:
        mask = np.zeros(v.image.shape[:2], bool)
        mask[:, : v.image.shape[1] // 2] = True
        masked.append(dataclasses.replace(v, mask=mask))
    f = extract_features(masked[0])
    assert len(f) > 50
    assert f.points2D[:, 0].max() < views[0].image.shape[1] / 2
    rec = reconstruct_sparse(masked, SparseConfig(affine_simulation="off"))
    assert rec.num_points > 0
    assert rec.observation_points2D[:, 0].max() < views[0].image.shape[1] / 2
    empty_mask = dataclasses.replace(views[0], mask=np.zeros(views[0].image.shape[:2], bool))
    assert len(extract_features(empty_mask)) == 0


def test_masked_detection_on_the_crop_finds_the_same_keypoints():
    _rig, views, _planes = box_views(3, seed=4)
    view = views[0]
    h, w = view.image.shape[:2]
    box = np.zeros((h, w), bool)
    box[h // 4 : 3 * h // 4, w // 3 : 2 * w // 3] = True
    full = extract_features(view)
    crop = extract_features(dataclasses.replace(view, mask=box))
    # All inside the mask, in view coordinates ...
    u, v = np.rint(crop.points2D).astype(int).T
    assert len(crop) > 20 and box[v.clip(0, h - 1), u.clip(0, w - 1)].all()
    # ... and, away from the box's edges, where detection on the whole view puts them.
    inner = np.zeros_like(box)
    inner[h // 4 + 16 : 3 * h // 4 - 16, w // 3 + 16 : 2 * w // 3 - 16] = True
    fu, fv = np.rint(full.points2D).astype(int).T
    ref = full.points2D[inner[fv.clip(0, h - 1), fu.clip(0, w - 1)]]
    d = np.linalg.norm(ref[:, None] - crop.points2D[None], axis=2).min(axis=1)
    assert len(ref) > 10 and np.mean(d < 0.5) > 0.9


def test_large_views_are_detected_downscaled_at_consistent_coordinates():
    _rig, views, planes = box_views(5, seed=3, width=1280, height_px=960, focal_px=1000.0)
    small = SparseConfig(feature_max_size_px=640, affine_simulation="off")
    rec = reconstruct_sparse(views, small)
    assert rec.num_points > 100
    d = scene_distance(planes, rec.points3D)
    assert np.median(d) < 0.01


def test_empty_and_degenerate_inputs_give_empty_reconstructions():
    _rig, views, _planes = box_views(3, seed=0)
    blank = [dataclasses.replace(v, image=np.full_like(v.image, 90)) for v in views]
    rec = reconstruct_sparse(blank)
    assert rec.num_points == 0 and rec.visibility.shape == (0, 3)
    assert rec.camera_ids == (0, 1, 2)
    assert rec.visibility_matrix(3).shape == (0, 3)
    one = reconstruct_sparse(views[:1])
    assert one.num_points == 0 and one.cloud.colors is not None
    assert reconstruct_sparse([]).num_points == 0
    assert isinstance(SparseReconstruction.empty((0, 1)), SparseReconstruction)


def test_duplicate_camera_ids_are_rejected():
    _rig, views, _planes = box_views(3, seed=0)
    dup = [views[0], View(camera_id=0, camera=views[1].camera, image=views[1].image)]
    with pytest.raises(ValueError, match="duplicate camera ids"):
        reconstruct_sparse(dup)


def test_simulated_tilts_add_points_on_wide_baselines():
    _, views, planes = box_views(5, seed=4)  # 72 degrees between neighbours
    assert use_affine(views, SparseConfig())  # "auto" turns it on for this rig
    off = reconstruct_sparse(views, SparseConfig(affine_simulation="off"))
    on = reconstruct_sparse(views, SparseConfig(affine_simulation="on"))
    assert on.num_points > 1.5 * off.num_points
    d = scene_distance(planes, on.points3D)
    assert np.mean(d <= 0.02) > 0.85
    # no duplicated points from the simulated views (their keypoints share locations)
    from scipy.spatial import cKDTree

    assert len(cKDTree(on.points3D).query_pairs(0.002)) <= 0.01 * on.num_points


def blank_views(num_cameras):
    rig = ring_rig(num_cameras)
    image = np.zeros((rig[0].height, rig[0].width, 3), np.uint8)
    return [View(camera_id=i, camera=c, image=image) for i, c in enumerate(rig)]


def test_auto_tilts_only_for_wide_baseline_rigs():
    assert not use_affine(blank_views(12), SparseConfig())  # 30 degrees apart
    assert use_affine(blank_views(12), SparseConfig(affine_simulation="on"))
    assert use_affine(blank_views(5), SparseConfig())  # 72 degrees apart
    assert not use_affine(blank_views(5), SparseConfig(affine_simulation="off"))


def test_colours_of_many_points_sampled_exactly():
    from edgerecon.sparse.reconstruction import _colors

    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (300, 400, 3), dtype=np.uint8)
    cam = ring_rig(3, width=400, height_px=300)[0]
    view = View(camera_id=0, camera=cam, image=image)
    n = 40_000  # more than OpenCV's 32767-row limit of remap maps
    px = np.stack([rng.integers(0, 400, n), rng.integers(0, 300, n)], axis=1)
    colours = _colors([view], px[:, None, :].astype(float), np.ones((n, 1), bool))
    assert np.array_equal(colours, image[px[:, 1], px[:, 0], ::-1])


def test_bad_images_are_rejected_with_the_camera_named():
    from edgerecon.types import DataError

    _, views, _ = box_views(3, seed=0)
    bad = dataclasses.replace(views[1], image=views[1].image.astype(np.float32))
    with pytest.raises(DataError, match="cam1"):
        reconstruct_sparse([views[0], bad, views[2]])


def test_grey_views_work_and_cameras_at_one_centre_match_nothing():
    _, views, planes = box_views(5, seed=2)
    grey = [dataclasses.replace(v, image=v.image.mean(axis=2).astype(np.uint8)) for v in views]
    rec = reconstruct_sparse(grey, SparseConfig(affine_simulation="off"))
    assert rec.num_points > 100
    assert np.median(scene_distance(planes, rec.points3D)) < 0.01
    # the same camera twice (a rotation-only pair has no epipolar geometry)
    twin = View(camera_id=7, camera=views[0].camera, image=views[0].image)
    assert reconstruct_sparse([views[0], twin]).num_points == 0
