"""End-to-end tests of one task: whole-scene and foreground/background pipelines."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from edgerecon.config import ReconstructionConfig
from edgerecon.dense import DenseConfig
from edgerecon.io.dataset import open_dataset
from edgerecon.pipeline import (
    SplitPipelineConfig,
    dominated_scales,
    fine_scale_limit,
    foreground_cost,
    foreground_dense_config,
    foreground_pixels,
    reconstruct,
    reconstruct_task,
    task_configs,
)
from edgerecon.quality import evaluate_clouds
from edgerecon.scene.foreground import RigForeground
from edgerecon.synth import GroundTruth
from edgerecon.types import BACKGROUND_LABEL, DataError, FrameSet, PointCloud
from tests.conftest import ring_rig, shared_data


@pytest.fixture(scope="module")
def tiny(tiny_dataset):
    ds = open_dataset(tiny_dataset)
    with ds.open_frames() as src:
        frames = src.read(4)
    return ds, frames, GroundTruth.open(tiny_dataset)


def test_golden_reconstruction_matches_ground_truth(tiny):
    ds, frames, gt = tiny
    result = reconstruct(frames, ds.rig)
    assert result.camera_ids == tuple(range(len(ds.rig)))
    assert result.sparse.num_points > 40  # 5 cameras 72 degrees apart at 320x240
    assert result.dense is not None and result.dense.num_points > 2000
    ref = gt.reference_cloud(4, "all", min_views=2)
    # 320x240 pixels see ~3 cm of surface each at 4 m: score at a few pixel footprints.
    (s,) = evaluate_clouds(result.dense.cloud, ref, 0.08)
    assert s.precision > 0.7, s
    assert {"prepare", "sparse.features", "dense.depth"} <= set(result.timings.seconds)
    # Points of the ground completion are flagged (this floor is textured: none), and the
    # flag is in the cloud (tests/dense/test_inferred.py: a blank floor).
    cloud, stats = result.dense.cloud, result.dense.stats
    assert stats["ground_plane"] is not None and "inferred" in cloud.attributes
    assert cloud.num_inferred == stats["inferred_points"] == stats["ground"]["completed_points"]
    assert result.summary()["num_inferred_points"] == cloud.num_inferred


def test_scale_and_camera_subset_reduce_work(tiny):
    ds, frames, _ = tiny
    full = reconstruct(frames, ds.rig, ReconstructionConfig(dense=False))
    small = reconstruct(
        frames, ds.rig, ReconstructionConfig(scale=0.8, camera_ids=(0, 1, 2), dense=False)
    )
    assert small.camera_ids == (0, 1, 2)
    assert small.sparse.visibility.shape[1] == 3
    assert 0 < small.sparse.num_points < full.sparse.num_points
    assert small.dense is None


def test_missing_frames_leave_too_few_cameras(tiny):
    ds, frames, _ = tiny
    images = list(frames.images)
    images[1] = images[2] = images[3] = None
    with pytest.raises(DataError, match=r"only 2 usable camera\(s\).*cam1"):
        reconstruct(FrameSet(time_index=4, images=tuple(images)), ds.rig)


def test_split_pipeline_labels_foreground_and_background(tiny, tiny_dataset):
    ds, frames, gt = tiny
    with ds.open_background() as bg:
        model = RigForeground.learn_from_framesets(ds.rig, bg.iter_frames())
    fg = model.segment(frames)
    result = reconstruct_task(frames, ds.rig, fg, sparse_scope="scene")
    merged = result.merged
    assert merged.labels is not None and "bg_version" in merged.attributes
    fg_pts = merged.select(merged.labels > 0)
    bg_pts = merged.select(merged.labels == BACKGROUND_LABEL)
    assert len(fg_pts) > 300 and len(bg_pts) > 1000
    # Foreground points lie on the actors, background points mostly do not.
    ref_fg = gt.reference_cloud(4, "foreground", min_views=1)
    d_fg = evaluate_clouds(fg_pts, ref_fg, 0.08)[0]
    d_bg = evaluate_clouds(bg_pts, ref_fg, 0.08)[0]
    assert d_fg.precision > 0.8, d_fg
    assert d_bg.precision < 0.1, d_bg
    # ... and cover the actors the cameras see (a plane fitted to the tops of the heads once
    # cut everything below them away).
    ref_fg2 = gt.reference_cloud(4, "foreground", min_views=2)
    d_fg2 = evaluate_clouds(fg_pts, ref_fg2, 0.08)[0]
    assert d_fg2.recall > 0.85, d_fg2
    # The foreground stage densified only the foreground: far fewer points than the background.
    assert result.foreground.dense is not None
    assert result.foreground.dense.num_points < 0.5 * len(bg_pts)
    s = result.summary()
    assert s["num_objects"] >= 1 and s["num_foreground_points"] == len(fg_pts)
    # Inferred points (ground completion) stay flagged from the dense stages to the merge.
    assert "inferred" in merged.attributes
    flagged = result.foreground.cloud.num_inferred + result.background.num_inferred
    assert s["num_inferred_points"] == merged.num_inferred <= flagged


def test_hull_scope_skips_sfm_with_the_same_foreground(tiny, tiny_dataset):
    ds, frames, _ = tiny
    with ds.open_background() as bg:
        model = RigForeground.learn_from_framesets(ds.rig, bg.iter_frames())
    fg = model.segment(frames)
    assert fg.hull is not None and fg.hull.num_voxels > 0
    background = PointCloud.empty()
    with_sfm = reconstruct_task(frames, ds.rig, fg, background=background)
    hull = reconstruct_task(frames, ds.rig, fg, background=background, sparse_scope="hull")
    assert with_sfm.sparse.num_points > 0 and "sfm" in with_sfm.timings.to_dict()
    # No SfM: the hull bounds the depth search, the sources are chosen from rays through the
    # masks; with these 4 cameras every other view is a source either way.
    assert hull.sparse.num_points == 0 and "sfm" not in hull.timings.to_dict()
    assert "prepare" in hull.timings.to_dict()
    assert len(hull.foreground.cloud) == len(with_sfm.foreground.cloud) > 300
    np.testing.assert_array_equal(
        hull.foreground.cloud.points3D, with_sfm.foreground.cloud.points3D
    )
    assert hull.summary()["num_sparse_points"] == 0
    # Without hull bounds the task needs its sparse points (depth ranges): SfM runs.
    no_hull = reconstruct_task(
        frames,
        ds.rig,
        fg,
        background=background,
        split_config=SplitPipelineConfig(use_hull_ranges=False),
        sparse_scope="hull",
    )
    assert no_hull.sparse.num_points > 0 and "sfm" in no_hull.timings.to_dict()
    # With the option, a background that hides nothing (the room's walls, far behind the
    # actors) carves the depth search's hull again to the same foreground; off (the
    # default), no second hull.
    far = fg.hull.centers.mean(axis=0) + np.array(
        [[dx, dy, 0.0] for dx in (-40, 40) for dy in (-40, 40)]
    )
    walls = PointCloud(points3D=far)
    again = reconstruct_task(
        frames,
        ds.rig,
        fg,
        background=walls,
        split_config=SplitPipelineConfig(fg_hull_occluders=True),
        sparse_scope="hull",
    )
    assert "fg_occluded_hull" in again.timings.to_dict()
    np.testing.assert_array_equal(again.foreground.cloud.points3D, hull.foreground.cloud.points3D)
    off = reconstruct_task(frames, ds.rig, fg, background=walls, sparse_scope="hull")
    assert "fg_occluded_hull" not in off.timings.to_dict()


def test_split_pipeline_with_empty_foreground(tiny):
    ds, _, _ = tiny
    with ds.open_background() as bg:
        framesets = list(bg.iter_frames())
    model = RigForeground.learn_from_framesets(ds.rig, framesets)
    empty = model.segment(framesets[0])  # the empty scene: nothing moves
    assert not any(m.any() for m in empty.masks if m is not None)
    result = reconstruct_task(framesets[0], ds.rig, empty, sparse_scope="scene")
    assert result.foreground.is_empty and result.foreground.dense is None
    assert len(result.merged) == len(result.background) > 0


def test_utrecht_frame_200_golden():
    ds = open_dataset(shared_data("utrecht4cam"))
    with ds.open_frames() as src:
        frames = src.read(200)
    result = reconstruct(frames, ds.rig)
    assert result.sparse.num_points > 30  # COLMAP's SIFT + triangulation: 3 points
    assert result.dense is not None and result.dense.num_points > 5000
    pts = result.dense.cloud.points3D
    # The board frame's floor is z = 0 (Z points down): a good share of points lie on it.
    near_floor = np.abs(pts[:, 2]) < 100
    assert near_floor.sum() > 200
    # The floor plane fitted to the stereo points lies 27-31 mm below the board's z = 0
    # (measured; about 3 working-resolution pixels of depth at 4-5 m).
    assert np.median(np.abs(pts[near_floor, 2])) < 40


def test_foreground_dense_settings():
    from edgerecon.dense import DenseConfig
    from edgerecon.pipeline import SplitPipelineConfig, foreground_dense_config

    base = DenseConfig(window_radius=3, resolution_level=1, refine_median_px=5)
    fg = foreground_dense_config(base)
    # 5x5 windows, the dense level kept, no floor completion, the search from the median
    # only where it is within 1 % of the pixel's depth.
    assert fg.window_radius == 2
    assert fg.resolution_level == 1
    assert not fg.ground_completion
    assert fg.refine_median_px == 5 and fg.refine_median_rel == 0.01
    assert fg.noise_adaptive_ncc
    # The whole-scene settings are not changed.
    assert base.window_radius == 3 and base.ground_completion
    assert not base.noise_adaptive_ncc
    assert base.refine_median_rel == DenseConfig().refine_median_rel
    full = foreground_dense_config(
        base,
        SplitPipelineConfig(
            fg_resolution_level=0,
            fg_window_radius=None,
            fg_refine_median_px=0,
            fg_refine_median_rel=None,
            fg_noise_adaptive_ncc=False,
        ),
    )
    assert not full.noise_adaptive_ncc
    assert full.resolution_level == 0 and full.window_radius == 3
    assert full.refine_median_px == 0 and full.refine_median_rel == base.refine_median_rel
    assert full.level_for((1920, 1080)) == 0
    for bad in (
        {"fg_resolution_level": 5},
        {"fg_window_radius": 0},
        {"fg_refine_median_px": 4},
        {"fg_refine_median_rel": 0.0},
    ):
        with pytest.raises(ValueError, match=next(iter(bad))):
            SplitPipelineConfig(**bad)


def test_the_depth_search_hull_knows_what_the_background_hides():
    # Four cameras around an actor (a box); a crate of the static scene (background to the
    # models) stands between camera 0 and the actor's lower half, so camera 0's mask lacks
    # that half and the masks' hull loses it. With the background's depth as occluders the
    # hull that bounds the depth search keeps it.
    import dataclasses

    from edgerecon.geometry import Camera, look_at
    from edgerecon.pipeline import occluded_hull
    from edgerecon.scene.foreground import ForegroundResult
    from edgerecon.scene.hull import HullConfig, visual_hull
    from edgerecon.types import StageTimings
    from tests.scene._scenes import box_silhouette, box_surface_points

    cams = []
    for i, a in enumerate(np.radians([0, 90, 180, 270])):
        R, t = look_at((4 * np.cos(a), 4 * np.sin(a), 1.2), (0.0, 0.0, 0.8))
        K = np.array([[300.0, 0, 159.5], [0, 300, 119.5], [0, 0, 1]])
        cams.append(Camera(name=f"c{i}", width=320, height=240, K=K, R=R, t=t))
    actor = (np.array([-0.25, -0.25, 0.0]), np.array([0.25, 0.25, 1.7]))
    crate = (np.array([1.9, -0.6, 0.0]), np.array([2.3, 0.6, 0.9]))  # before camera 0
    hidden = np.array([[0.0, 0.0, 0.3]])  # the actor's lower half, behind the crate in cam 0
    masks = [box_silhouette(c, *actor) for c in cams]
    masks[0] = masks[0] & ~box_silhouette(cams[0], *crate)
    config = HullConfig(voxel_size=0.04, max_missing=0)
    hull = visual_hull(cams, masks, config)
    assert hull.contains(np.array([[0.0, 0.0, 1.5]]))[0] and not hull.contains(hidden)[0]
    fg = ForegroundResult(
        time_index=0,
        masks=tuple(masks),
        model_masks=tuple(masks),
        objects=(None,) * 4,
        hull=hull,
        timings=StageTimings(),
        cameras=tuple(cams),
        hull_config=config,
    )
    background = PointCloud(points3D=box_surface_points(*crate, 60))
    carved = occluded_hull(fg, background)
    assert carved is not None and carved.contains(hidden)[0]
    assert carved.contains(np.array([[0.0, 0.0, 1.5]]))[0]
    assert not carved.contains(np.array([[0.0, 0.0, 1.9]]))[0]  # above the actor: carved
    # Nothing to hide behind, or no hull: nothing to carve again.
    assert occluded_hull(fg, PointCloud.empty()) is None
    assert occluded_hull(dataclasses.replace(fg, hull=None), background) is None


def test_task_configs_above_one_make_the_foreground_finer():
    """r > 1 (the controller's ``r_fine``): on a 1920x1080 rig, whose golden foreground
    densifies at half resolution, r = 1.5 is views at 0.75 densified at level 0; rigs
    densified at level 0 (640x480), or at different levels, have nothing above 1."""
    hd = ring_rig(4, width=1920, height_px=1080, focal_px=1400.0)
    dense = DenseConfig()
    assert fine_scale_limit(hd, dense) == 2.0
    rc, split = task_configs(0.6, hd, camera_ids=[0, 1, 2], dense_config=dense)
    assert (rc.scale, rc.camera_ids, split.fg_resolution_level) == (0.6, (0, 1, 2), None)
    assert foreground_dense_config(dense, split).refine_passes == 2  # the golden passes
    rc, split = task_configs(1.5, hd, dense_config=dense)
    assert (rc.scale, split.fg_resolution_level) == (0.75, 0)
    # Finer than golden: one local-search pass (the pixels pay more than the second pass).
    assert foreground_dense_config(dense, split).refine_passes == 1
    rc, split = task_configs(2.0, hd, dense_config=dense)
    assert (rc.scale, split.fg_resolution_level) == (1.0, 0)
    keep = SplitPipelineConfig(fine_refine_passes=None)
    _, split = task_configs(2.0, hd, dense_config=dense, split_config=keep)
    assert foreground_dense_config(dense, split).refine_passes == 2
    with pytest.raises(ValueError, match="fine_refine_passes"):
        SplitPipelineConfig(fine_refine_passes=0)
    with pytest.raises(ValueError, match="task scale"):
        task_configs(2.5, hd, dense_config=dense)
    vga = ring_rig(4)
    assert fine_scale_limit(vga, dense) == 1.0
    with pytest.raises(ValueError, match="task scale"):
        task_configs(1.2, vga, dense_config=dense)
    other = dataclasses.replace(vga.cameras[3], name="vga")
    mixed = type(hd)(cameras=(*hd.cameras[:3], other), unit="m")
    assert fine_scale_limit(mixed, dense) == 1.0
    assert fine_scale_limit(hd, dense, SplitPipelineConfig(fg_resolution_level=0)) == 1.0


def test_dominated_scales_are_where_the_sweep_level_drops():
    """``dominated_scales``: on 1280x720 frames (golden foreground at half resolution) the
    plane sweep runs at a 176-pixel octave at r = 0.55 and at a 120-pixel level from r =
    0.5625: r 0.45-0.5625 costs more than a larger r (measured: 0.42 s at r = 0.55 against
    0.30 s at 0.6 for one caliscope_charuco task), and so do r just above 1 (r = 1.1 sweeps
    at 176 pixels, r = 1.2 at 120). Each interval's upper end costs less than any scale
    inside; r_max bounds the intervals; a 640x480 rig has one interval and nothing above 1."""
    hd = ring_rig(4, width=1280, height_px=720, focal_px=1000.0)
    skip = dominated_scales(hd, 0.3, 1.0, 2.0)
    assert len(skip) == 2
    (a, b), (c, d) = skip
    assert 0.42 < a < 0.48 and 0.5625 < b < 0.58
    assert 1.0 <= c < 1.01 and 1.125 < d < 1.15
    for lo, hi in skip:
        top = foreground_cost(hi, hd)
        # (the upper end is 1 % above the drop, the first r that is not dominated)
        inside = [r for r in np.linspace(lo, hi, 40)[1:-1] if r < hi / 1.011]
        assert all(foreground_cost(float(r), hd) > top for r in inside)
    # Outside the intervals the cost grows with r.
    outside = [r for r in np.arange(0.3, 2.0, 0.01) if not any(x < r < y for x, y in skip)]
    costs = [foreground_cost(float(r), hd) for r in outside if r <= 1.0]
    assert all(np.diff(costs) > -0.02 * np.array(costs[1:]))
    # Without r_fine nothing above r_max; the golden configuration is never inside.
    assert dominated_scales(hd, 0.3, 1.0) == skip[:1]
    vga = ring_rig(4)
    (v,) = dominated_scales(vga, 0.3, 1.0, 1.0)
    assert 0.4 < v[0] < v[1] < 0.6
    # The estimate's pyramid is the one the depth maps use.
    assert foreground_cost(0.55, hd) > foreground_cost(0.6, hd) > foreground_cost(0.45, hd)
    # What it weighs: r = 0.55, 352x198 working images sweeping their 176x99 octave.
    assert foreground_pixels(0.55, hd) == (4 * 352 * 198, 4 * 176 * 99, 2)
    assert foreground_pixels(0.6, hd) == (4 * 384 * 216, 4 * 120 * 68, 2)
    assert foreground_pixels(1.5, hd)[2] == 1  # finer than golden: one local-search pass
    assert foreground_cost(0.55, hd) == pytest.approx(4 * (352 * 198 + 8 * 176 * 99))


def test_retune_chooses_the_configuration_from_the_masks(tiny, tiny_dataset):
    """``reconstruct_task(retune=...)``: called once with the task's foreground, before the
    views are prepared; the task runs at what it returns (as if given from the start)."""
    ds, frames, _ = tiny
    with ds.open_background() as bg:
        model = RigForeground.learn_from_framesets(ds.rig, bg.iter_frames())
    fg = model.segment(frames)
    seen = []

    def retune(result):
        seen.append(result)
        return task_configs(0.5, ds.rig)

    background = PointCloud.empty()
    tuned = reconstruct_task(
        frames,
        ds.rig,
        lambda timings: fg,
        task_configs(1.0, ds.rig)[0],
        background=background,
        sparse_scope="hull",
        retune=retune,
    )
    assert seen == [fg]
    assert tuned.config.scale == 0.5
    rc, sc = task_configs(0.5, ds.rig)
    direct = reconstruct_task(
        frames, ds.rig, fg, rc, background=background, split_config=sc, sparse_scope="hull"
    )
    np.testing.assert_array_equal(tuned.foreground.cloud.points3D, direct.foreground.cloud.points3D)
    # The paper's order needs the views for its SfM first: no retune there.
    scene = reconstruct_task(
        frames, ds.rig, fg, background=background, sparse_scope="scene", retune=retune
    )
    assert len(seen) == 1 and scene.config.scale == 1.0


def test_a_task_cancelled_in_its_depth_maps_stops_there(tiny, monkeypatch):
    # The watchdog's event reaches the foreground's dense stage: set while the first depth
    # map runs, the task raises from there and starts no other map.
    import threading

    import edgerecon.dense.reconstruct as rec
    from edgerecon.pipeline import TaskCancelled

    ds, frames, _ = tiny
    with ds.open_background() as bg:
        model = RigForeground.learn_from_framesets(ds.rig, bg.iter_frames())
    fg = model.segment(frames)
    cancel = threading.Event()
    real = rec.estimate_depth
    started: list[int] = []

    def first_then_cancel(*args, **kwargs):
        started.append(1)
        cancel.set()
        return real(*args, **kwargs)

    monkeypatch.setattr(rec, "estimate_depth", first_then_cancel)
    config = ReconstructionConfig(dense_config=DenseConfig(num_threads=1))
    with pytest.raises(TaskCancelled, match="dense depth maps: cancelled"):
        reconstruct_task(
            frames,
            ds.rig,
            fg,
            config,
            background=PointCloud.empty(),
            sparse_scope="hull",
            cancel=cancel,
        )
    assert started == [1]
