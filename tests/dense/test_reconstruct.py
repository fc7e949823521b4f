"""reconstruct_dense on a rendered scene with exact ground truth (textured floor and cube)."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from edgerecon.dense import DenseConfig, DenseReconstruction, reconstruct_dense, working_camera
from edgerecon.geometry.camera import Rig
from edgerecon.types import DataError, FrameSet
from edgerecon.views import View, prepare_views
from tests.conftest import ring_rig
from tests.dense.scene import box_scene, render

#: 5 cameras 30 degrees apart on a 4 m ring, 320x240 (fast enough for unit tests).
RIG = ring_rig(12, radius=4.0, height=2.0, width=320, height_px=240, focal_px=250.0)
IDS = (10, 11, 0, 1, 2)


@pytest.fixture(scope="module")
def scene() -> tuple[list[View], dict[int, np.ndarray]]:
    rects = box_scene()
    views, depths = [], {}
    for i in IDS:
        image, depth = render(RIG[i], rects)
        views.append(View(camera_id=i, camera=RIG[i], image=image))
        depths[i] = depth
    return views, depths


@pytest.fixture(scope="module")
def result(scene) -> DenseReconstruction:
    views, _ = scene
    return reconstruct_dense(views, DenseConfig(resolution_level=0, num_threads=1), up=(0, 0, 1))


def _gt_at(depth: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    return cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST)


def test_depth_maps_match_ground_truth(scene, result):
    _, gts = scene
    for cid in (11, 0, 1):  # views with sources on both sides
        d = result.depth_maps[cid]
        gt = _gt_at(gts[cid], result.depth_cameras[cid].size)
        ok = (d > 0) & (gt > 0)
        # Completeness: most of the rendered surface gets a consistent depth ...
        assert ok.sum() > 0.6 * (gt > 0).sum(), cid
        rel = np.abs(d[ok] - gt[ok]) / gt[ok]
        # ... and those depths are accurate: the median within 0.3 %, 95 % within 1 %.
        assert np.median(rel) < 0.003, cid
        assert np.mean(rel < 0.01) > 0.95, cid


def test_cloud_lies_on_the_scene(result):
    cloud = result.cloud
    assert len(cloud) > 5000
    P = cloud.points3D
    # Distance to the scene: the floor z = 0 or the cube [-0.4, 0.4]^2 x [0, 0.8].
    d_floor = np.abs(P[:, 2])
    q = np.abs(P[:, :2]) - 0.4
    outside = np.linalg.norm(np.maximum(np.c_[q, np.abs(P[:, 2] - 0.4) - 0.4], 0), axis=1)
    inside = np.minimum(np.maximum.reduce([q[:, 0], q[:, 1], np.abs(P[:, 2] - 0.4) - 0.4]), 0)
    d_cube = outside + np.abs(inside)
    dist = np.minimum(d_floor, d_cube)
    # One pixel spans 1.1-2.8 cm at 2.8-7 m with f = 250 px; the few worse points sit where
    # the floor's far edge meets the black void.
    assert np.mean(dist < 0.01) > 0.85
    assert np.mean(dist < 0.03) > 0.95
    assert cloud.colors is not None and cloud.normals is not None
    assert np.allclose(np.linalg.norm(cloud.normals, axis=1), 1.0, atol=1e-4)
    assert cloud.attributes["num_views"].min() >= 2


def test_normals_face_the_cameras_and_match_the_floor(result):
    cloud = result.cloud
    floor = np.abs(cloud.points3D[:, 2]) < 0.01
    floor &= np.abs(cloud.points3D[:, :2]).max(axis=1) > 0.6  # away from the cube
    assert floor.sum() > 1000
    n = cloud.normals[floor]
    # The floor is seen from above: normals point up (+z), within a few degrees mostly.
    assert np.median(n[:, 2]) > 0.98
    assert np.mean(n[:, 2] > 0.9) > 0.9


def test_empty_masks_give_an_empty_cloud(scene):
    views, _ = scene
    masked = [dataclasses.replace(v, mask=np.zeros(v.image.shape[:2], bool)) for v in views]
    res = reconstruct_dense(masked, DenseConfig(num_threads=1))
    assert len(res.cloud) == 0
    assert res.stats["work"] == 0


def test_fewer_than_two_views_is_empty(scene):
    views, _ = scene
    res = reconstruct_dense(views[:1], DenseConfig())
    assert len(res.cloud) == 0


def test_bad_inputs_are_clear_errors(scene):
    views, _ = scene
    with pytest.raises(DataError, match="more than once"):
        reconstruct_dense([views[0], views[0]])
    with pytest.raises(DataError, match="not in the views"):
        reconstruct_dense(views, depth_ranges={99: (1.0, 2.0)})
    with pytest.raises(DataError, match="0 < near < far"):
        reconstruct_dense(views, depth_ranges={IDS[0]: (2.0, 1.0)})


@pytest.mark.parametrize(
    "field,value",
    [
        ("resolution_level", -1),
        ("min_resolution_px", -1),
        ("window_radius", 0),
        ("min_ncc", 1.5),
        ("sweep_families", ("x",)),
        ("refine_median_px", 4),
        ("refine_median_rel", 0.0),
        ("refine_passes", 0),
    ],
)
def test_config_validation(field, value):
    with pytest.raises(ValueError, match=field):
        DenseConfig(**{field: value})


def _disc_masks(views: list[View], radius_px: float) -> list[View]:
    """Views masked to a disc around the cube's centre (about 10 % of each image)."""
    out = []
    for v in views:
        uv, _ = v.camera.project(np.array([[0.0, 0.0, 0.4]]))
        mask = np.zeros(v.image.shape[:2], np.uint8)
        cv2.circle(mask, (round(float(uv[0, 0])), round(float(uv[0, 1]))), int(radius_px), 1, -1)
        out.append(dataclasses.replace(v, mask=mask.astype(bool)))
    return out


def test_masks_restrict_output_and_work(scene, result):
    views, _ = scene
    masked = _disc_masks(views, 50)
    share = np.mean([v.mask.mean() for v in masked])
    assert 0.08 < share < 0.13
    res = reconstruct_dense(masked, DenseConfig(resolution_level=0, num_threads=1), up=(0, 0, 1))
    assert len(res.cloud) > 1000
    # Every point comes from inside some view's mask.
    inside = np.zeros(len(res.cloud), bool)
    for v in masked:
        uv, z = v.camera.project(res.cloud.points3D)
        ok = (z > 0) & v.camera.in_image(uv)
        c = np.clip(np.rint(uv[:, 0]), 0, v.camera.width - 1).astype(int)
        r = np.clip(np.rint(uv[:, 1]), 0, v.camera.height - 1).astype(int)
        inside |= ok & v.mask[r, c]
    assert inside.mean() > 0.99
    # The work (pixel x source evaluations) shrinks roughly with the masked area: the boxes
    # around the discs cover 4/pi of them plus the window margins.
    ratio = res.stats["work"] / result.stats["work"]
    assert ratio < 2.5 * share
    for cid, d in res.depth_maps.items():
        m = next(v.mask for v in masked if v.camera_id == cid)
        assert not np.any(d[~m] > 0)


def test_per_pixel_depth_bounds_restrict_depths_and_work(scene, result):
    views, gts = scene
    ranges = {}
    for v in views:
        gt = gts[v.camera_id]
        near = np.where(gt > 0, gt * 0.97, 0).astype(np.float32)
        far = np.where(gt > 0, gt * 1.03, 0).astype(np.float32)
        near[:, : v.camera.width // 2] = 0  # only the right half of each image
        ranges[v.camera_id] = (near, far)
    res = reconstruct_dense(
        views, DenseConfig(resolution_level=0, num_threads=1), depth_ranges=ranges, up=(0, 0, 1)
    )
    assert res.stats["work"] < 0.7 * result.stats["work"]
    for cid, d in res.depth_maps.items():
        near, far = ranges[cid]
        has = d > 0
        assert has.sum() > 2000
        assert not np.any(has & (near == 0))
        assert np.all(d[has] >= near[has] * 0.999) and np.all(d[has] <= far[has] * 1.001)


def test_resolution_level_follows_the_frames_not_the_task_scale() -> None:
    cfg = DenseConfig()  # resolution_level 1, min_resolution_px 640 (openMVS's)
    assert cfg.level_for((640, 480)) == 0  # half would be 320 px: full resolution
    assert cfg.level_for((1280, 720)) == 1
    assert cfg.level_for((1920, 1080)) == 1
    assert DenseConfig(resolution_level=2).level_for((1920, 1080)) == 1
    assert DenseConfig(min_resolution_px=0).level_for((640, 480)) == 1
    image = np.zeros((120, 160, 3), np.uint8)
    small = RIG[0].scaled(0.5)  # a 320x240 camera's view at r = 0.5
    view = View(camera_id=0, camera=small, image=image, scale=0.5)
    assert view.frame_size == (320, 240)
    # The frames are small: the depth map is at the view's own size (level 0) ...
    assert working_camera(view, cfg).size == (160, 120)
    # ... while a 1920x1080 camera's view at r = 1/12 (160x90) gets level 1: r scales the
    # cost at every r, the level never undoes it.
    big = dataclasses.replace(RIG[0], width=1920, height=1080).scaled(1 / 12)
    view = View(camera_id=0, camera=big, image=np.zeros((90, 160, 3), np.uint8), scale=1 / 12)
    assert working_camera(view, cfg).size == (80, 45)
    with pytest.raises(ValueError, match="scale"):
        View(camera_id=0, camera=small, image=image, scale=0.0)


@pytest.mark.parametrize("scale", [0.955066, 0.855066, 0.802734, 0.720668, 0.3])
def test_prepared_views_know_their_frames_whatever_the_rounding(scale: float) -> None:
    # A 1280x720 camera at r = 0.955066 gives a 1222-wide view; 1222 / r rounds to 1279,
    # under twice the 640 px floor: the depth maps went to full resolution (level 0), four
    # times the pixels (caliscope_charuco's online tasks: 67k foreground points and 3 s
    # instead of 20k and 1 s at r = 0.96).
    rig = Rig(cameras=tuple(dataclasses.replace(c, width=1280, height=720) for c in RIG[:3]))
    frames = FrameSet(time_index=0, images=(np.zeros((720, 1280, 3), np.uint8),) * 3)
    for view in prepare_views(frames, rig, scale):
        assert view.frame_size == (1280, 720)
        assert working_camera(view, DenseConfig()).size == view.camera.scaled(0.5).size
    with pytest.raises(ValueError, match="source_size"):
        dataclasses.replace(view, source_size=(1920, 1080))


def test_small_images_are_swept_exhaustively_except_for_the_foreground():
    """A 192x108 working image (its first octave under the sweep's 120 px): whole scenes sweep
    it at its own size (``sweep_small_exhaustive``), the foreground at a level resized to
    120 px, so that its cost falls with the image scale."""
    from edgerecon.dense.depth import build_pyramid
    from edgerecon.pipeline import foreground_dense_config

    cam = ring_rig(3, width=192, height_px=108, focal_px=150.0).cameras[0]
    grey = np.random.default_rng(0).uniform(0, 255, (108, 192)).astype(np.float32)
    whole = build_pyramid(0, cam, grey, 3, 120)
    assert [c.width for c in whole.cameras] == [192]
    fg = foreground_dense_config(DenseConfig())
    assert not fg.sweep_small_exhaustive and DenseConfig().sweep_small_exhaustive
    small = build_pyramid(0, cam, grey, 3, 120, small_exhaustive=False)
    assert [c.width for c in small.cameras] == [192, 120]
    assert small.greys[1].shape == (small.cameras[1].height, 120)
    # Larger images: the same pyramid either way (320 px: octave 160, then nothing).
    big = ring_rig(3, width=320, height_px=180, focal_px=250.0).cameras[0]
    g2 = np.zeros((180, 320), np.float32)
    a = build_pyramid(0, big, g2, 3, 120)
    b = build_pyramid(0, big, g2, 3, 120, small_exhaustive=False)
    assert [c.width for c in a.cameras] == [c.width for c in b.cameras] == [320, 160]


def test_the_sweep_level_and_the_cost_of_a_depth_map_over_the_working_size():
    """``depth_cost``: the working pixels plus the pixels of the level the sweep runs at
    (``sweep_level`` of ``pyramid_scales``, the pyramid the depth maps are built on), 8
    times each. A 352-wide working image sweeps its 176-px octave, a 384-wide one a level
    resized to 120 px: the larger image costs less (the foreground at r = 0.55 / 0.6 on
    1280-wide frames); one local-search pass costs less than two."""
    from edgerecon.dense.depth import build_pyramid, depth_cost, pyramid_scales, sweep_level
    from edgerecon.pipeline import foreground_dense_config

    fg = foreground_dense_config(DenseConfig())
    cam = ring_rig(3, width=384, height_px=216, focal_px=300.0).cameras[0]
    pyr = build_pyramid(0, cam, np.zeros((216, 384), np.float32), 3, 120, small_exhaustive=False)
    scales = pyramid_scales(384, 216, 3, 120, small_exhaustive=False)
    assert [c.width for c in pyr.cameras] == [384, *(round(384 * s) for s in scales)]
    assert [c.width for c in pyr.cameras] == [384, 192, 120]
    assert sweep_level([c.width for c in pyr.cameras], fg) == 2
    assert sweep_level([352, 176], fg) == 1
    assert sweep_level([200, 100], fg) == 0  # nothing below keeps 120 px
    small, large = depth_cost(352, 198, fg), depth_cost(384, 216, fg)
    assert small == pytest.approx(352 * 198 + 8 * 176 * 99)
    assert large == pytest.approx(384 * 216 + 8 * 120 * 68)
    assert small > large
    one = dataclasses.replace(fg, refine_passes=1)
    assert depth_cost(384, 216, one) < large


@pytest.mark.parametrize("threads", [1, 2])
def test_a_cancelled_dense_stage_starts_no_further_depth_map(scene, monkeypatch, threads):
    # A task's watchdog gave up on it during its depth maps: the maps already running end,
    # no other starts, and the stage raises instead of filtering and fusing (an abandoned
    # task used to run on a core to its end).
    import threading

    import edgerecon.dense.reconstruct as rec
    from edgerecon.types import TaskCancelled

    views, _ = scene
    cancel = threading.Event()
    real = rec.estimate_depth
    started: list[int] = []

    def slow(*args, **kwargs):
        started.append(1)
        cancel.set()  # the watchdog fires while the first maps run
        return real(*args, **kwargs)

    monkeypatch.setattr(rec, "estimate_depth", slow)
    config = DenseConfig(resolution_level=1, num_threads=threads)
    with pytest.raises(TaskCancelled, match="cancelled"):
        reconstruct_dense(views, config, up=(0, 0, 1), cancel=cancel)
    assert 1 <= len(started) <= threads < len(views)
    # An event that is never set changes nothing: every map runs (one per view here).
    started.clear()

    def counted(*args, **kwargs):
        started.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(rec, "estimate_depth", counted)
    assert len(reconstruct_dense(views, config, up=(0, 0, 1), cancel=threading.Event()).cloud)
    assert len(started) == len(views)
