"""The dense stage: per-view depth maps -> cross-view consistency -> fused cloud."""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.dense import filters, gpu, kernels
from edgerecon.dense.config import DenseConfig
from edgerecon.dense.consistency import agreement_tolerance, support_and_conflicts
from edgerecon.dense.cost import as_f32, to_grey
from edgerecon.dense.depth import DepthEstimate, Roi, ViewPyramid, build_pyramid, estimate_depth
from edgerecon.dense.fusion import ViewPoints, view_points, voxel_merge
from edgerecon.dense.neighbors import point_weights, select_sources
from edgerecon.dense.planes import (
    BLANK_TEXTURE,
    TEXTURE_WINDOW,
    Plane,
    below_plane,
    color_model,
    complete_with_plane,
    fit_ground_plane,
    keep_off_levels,
    level_map,
    support_region,
)
from edgerecon.dense.ranges import frustum_range, range_from_points, sample_pixels, scene_scale
from edgerecon.dense.threads import RowBands, run_jobs
from edgerecon.geometry.camera import Camera
from edgerecon.threads import thread_map
from edgerecon.types import (
    DataError,
    DepthMap,
    Image,
    Mask,
    PointCloud,
    StageTimings,
    TaskCancelled,
)
from edgerecon.views import View, resize_mask

logger = logging.getLogger(__name__)

#: A view's depth bounds: one (near, far) pair, or (H, W) near/far maps at the view's
#: resolution (0 = no surface at that pixel), e.g. from a visual hull.
DepthBounds = tuple[float, float] | tuple[NDArray[np.floating[Any]], NDArray[np.floating[Any]]]


class SparseLike(Protocol):
    """What the dense stage reads from ``edgerecon.sparse.SparseReconstruction``."""

    @property
    def cloud(self) -> PointCloud: ...

    @property
    def camera_ids(self) -> tuple[int, ...]: ...

    @property
    def visibility(self) -> NDArray[np.bool_]: ...


@dataclass(frozen=True, kw_only=True, eq=False)
class DenseReconstruction:
    """Result of :func:`reconstruct_dense`."""

    cloud: PointCloud
    """Fused points (rig units) with RGB colours, unit normals facing the cameras,
    ``confidence`` (mean aggregated NCC in [-1, 1]), ``attributes["num_views"]`` (int32:
    views that support the point, including the one it came from) and
    ``attributes["inferred"]`` (uint8: 1 for points of the ground-plane completion, which no
    stereo depth measured; ``PointCloud.inferred``)."""
    depth_maps: dict[int, DepthMap] = field(default_factory=dict)
    """Camera id -> (h, w) float32 depth after the consistency filter (0 = unknown), at the
    working resolution of ``depth_cameras``."""
    depth_cameras: dict[int, Camera] = field(default_factory=dict)
    """Camera id -> the pinhole camera of its depth map (the view's camera, rescaled)."""
    timings: StageTimings = field(default_factory=StageTimings)
    """Seconds of ``prepare`` (pyramids, ranges, sources), ``depth`` (plane sweep and
    refinement), ``consistency`` and ``fusion``."""
    stats: dict[str, Any] = field(default_factory=dict)
    """Counts: per-view sources, depth ranges, planes, ``work`` (pixel x source NCC
    evaluations), raw and consistent depths; ``voxel_size``; ``num_points``;
    ``inferred_points``; ``ground`` (with a ground plane: the level map's cells on the plane,
    raised and lower, the raised levels' heights, depths completed and refused by the map,
    ``completed_points`` in the cloud)."""

    def __len__(self) -> int:
        return len(self.cloud)

    @property
    def num_points(self) -> int:
        return len(self.cloud)


def estimate_up(
    cameras: Sequence[Camera], max_spread_deg: float = 30.0
) -> NDArray[np.float64] | None:
    """The world's up direction as the mean image-up axis (-y) of the cameras, or None when
    the cameras disagree by more than ``max_spread_deg`` (rolled or upside-down cameras)."""
    ups = np.array([-cam.R[1] for cam in cameras])
    mean = ups.sum(axis=0)
    norm = np.linalg.norm(mean)
    if norm < 1e-9:
        return None
    mean /= norm
    if np.degrees(np.arccos(np.clip(ups @ mean, -1, 1))).max() > max_spread_deg:
        return None
    return mean


def _check_views(views: Sequence[View]) -> None:
    ids = [v.camera_id for v in views]
    dup = {i for i in ids if ids.count(i) > 1}
    if dup:
        raise DataError(f"dense: camera ids {sorted(dup)} appear more than once in the views")
    for v in views:
        if v.image.ndim != 3 or v.image.shape[2] != 3 or v.image.dtype != np.uint8:
            raise DataError(
                f"dense: view {v.name!r} (camera {v.camera_id}) must be a BGR uint8 image, got "
                f"{v.image.dtype} of shape {v.image.shape}"
            )


def working_camera(view: View, config: DenseConfig) -> Camera:
    """The pinhole camera of ``view``'s depth map (``2**-level`` of the view, the level from
    ``config.level_for`` of the view's frame size)."""
    return view.camera.scaled(0.5 ** config.level_for(view.frame_size))


def _bounds_maps(
    view: View, cam: Camera, bounds: DepthBounds | None
) -> tuple[NDArray[np.float32], NDArray[np.float32]] | None:
    """Per-pixel near/far at the working resolution from user-given bounds (None if none)."""
    if bounds is None:
        return None
    try:
        near, far = bounds
    except (TypeError, ValueError):
        raise DataError(
            f"dense: depth range of camera {view.camera_id} must be (near, far), got {bounds!r}"
        ) from None
    if np.ndim(near) == 0 and np.ndim(far) == 0:
        n, f = float(near), float(far)
        if not (np.isfinite(n) and np.isfinite(f) and 0 < n < f):
            raise DataError(
                f"dense: depth range of camera {view.camera_id} must satisfy 0 < near < far, "
                f"got ({n}, {f})"
            )
        return (
            np.full((cam.height, cam.width), n, np.float32),
            np.full((cam.height, cam.width), f, np.float32),
        )
    near_a = np.asarray(near, dtype=np.float32)
    far_a = np.asarray(far, dtype=np.float32)
    shape = view.image.shape[:2]
    working = (cam.height, cam.width)
    if near_a.shape == far_a.shape == working:
        shape = working  # already at the working resolution: used as they are
    elif near_a.shape != shape or far_a.shape != shape:
        raise DataError(
            f"dense: depth bound maps of camera {view.camera_id} must be {shape[1]}x{shape[0]} "
            f"(the view's size) or {cam.width}x{cam.height} (the working resolution), got "
            f"{near_a.shape[::-1]} and {far_a.shape[::-1]}"
        )
    # Finite bounds with 0 < near < far; elsewhere none (0).
    ok = (near_a > 0) & (far_a > near_a) & np.isfinite(far_a)
    near_a = np.where(ok, near_a, np.float32(0.0))
    far_a = np.where(ok, far_a, np.float32(0.0))
    if cam.size != (shape[1], shape[0]):
        # Conservative: the nearest near and the farthest far over each working pixel.
        k = max(1, round(shape[1] / cam.width))
        ker = np.ones((k, k), np.uint8)
        nz = cv2.erode(np.where(near_a > 0, near_a, np.inf).astype(np.float32), ker)
        near_a = as_f32(
            cv2.resize(np.where(np.isfinite(nz), nz, 0), cam.size, interpolation=cv2.INTER_NEAREST)
        )
        far_a = as_f32(
            cv2.resize(cv2.dilate(far_a, ker), cam.size, interpolation=cv2.INTER_NEAREST)
        )
        ok = (near_a > 0) & (far_a > near_a)
        near_a = np.where(ok, near_a, 0.0).astype(np.float32)
        far_a = np.where(ok, far_a, 0.0).astype(np.float32)
    return near_a, far_a


def mask_rois(mask: NDArray[np.bool_], margin: int, min_area: int) -> list[Roi]:
    """Boxes around the connected parts of ``mask`` grown by ``margin`` pixels; parts smaller
    than ``min_area`` pixels are dropped; boxes are merged while that saves area."""
    h, w = mask.shape
    m = mask.astype(np.uint8)
    n, _, st, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    boxes = []
    for k in range(1, n):
        x, y, bw, bh, area = st[k]
        if area < min_area:
            continue
        boxes.append(
            [
                max(x - margin, 0),
                max(y - margin, 0),
                min(x + bw + margin, w),
                min(y + bh + margin, h),
            ]
        )
    merged = True
    while merged and len(boxes) > 1:
        merged = False
        for i in range(len(boxes)):
            for j in range(i + 1, len(boxes)):
                a, b = boxes[i], boxes[j]
                u = [min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3])]
                area = lambda r: (r[2] - r[0]) * (r[3] - r[1])  # noqa: E731
                if area(u) <= 1.2 * (area(a) + area(b)):
                    boxes[i] = u
                    del boxes[j]
                    merged = True
                    break
            if merged:
                break
    return [Roi(*b) for b in boxes]


def reconstruct_dense(
    views: Sequence[View],
    config: DenseConfig = DenseConfig(),  # noqa: B008 (frozen, immutable)
    sparse: SparseLike | None = None,
    *,
    depth_ranges: Mapping[int, DepthBounds] | None = None,
    up: Sequence[float] | None = None,
    cancel: threading.Event | None = None,
) -> DenseReconstruction:
    """Dense coloured point cloud of the scene seen by ``views``.

    ``views`` are undistorted pinhole views (``edgerecon.views.prepare_views``); a view's
    ``mask`` restricts the output (and the work, roughly in proportion) to its region.
    ``sparse`` (optional) gives per-view depth ranges and source selection; ``depth_ranges``
    (camera id -> (near, far) or per-pixel near/far maps at the view's size or at the working
    resolution ``working_camera(view, config)``, 0 = excluded) overrides them, e.g. from a
    visual hull. ``up`` is the world's up direction (the rig's
    ``up``) for ground-plane hypotheses; default: estimated from the cameras.

    Fewer than two views, empty masks or nothing consistent give an empty cloud (not an error).

    ``cancel`` (a task's watchdog event): once set, no further depth map starts and the
    filter and fusion passes do not run (:class:`TaskCancelled`); an abandoned task stops
    within one depth map's time instead of running on a core to its end.
    """
    _check_views(views)
    timings = StageTimings()
    stats: dict[str, Any] = {"views": {}}
    ranges = dict(depth_ranges or {})
    unknown = set(ranges) - {v.camera_id for v in views}
    if unknown:
        raise DataError(f"dense: depth ranges given for cameras {sorted(unknown)} not in the views")

    with timings.stage("prepare"):
        cams = [working_camera(v, config) for v in views]
        scale = (
            float(np.median([c.width / v.camera.width for v, c in zip(views, cams, strict=True)]))
            if views
            else config.working_scale
        )
        colors: list[Image] = [
            v.image
            if c.size == v.camera.size
            else np.asarray(cv2.resize(v.image, c.size, interpolation=cv2.INTER_AREA), np.uint8)
            for v, c in zip(views, cams, strict=True)
        ]
        masks: list[Mask | None] = [
            None if v.mask is None else resize_mask(v.mask, c.size)
            for v, c in zip(views, cams, strict=True)
        ]
        up_vec = np.asarray(up, np.float64) if up is not None else estimate_up(cams)
        if up_vec is not None:
            up_vec = up_vec / np.linalg.norm(up_vec)
        scale_len = scene_scale(cams)
        sparse_pts, sparse_vis = _sparse_points(sparse, views)
        plans = []
        for i, (v, cam) in enumerate(zip(views, cams, strict=True)):
            plans.append(
                _plan_view(
                    i,
                    v,
                    cam,
                    cams,
                    masks[i],
                    ranges.get(v.camera_id),
                    sparse_pts,
                    sparse_vis,
                    scale_len,
                    config,
                )
            )
        needed = {i for p in plans if p["rois"] for i in [p["index"], *p["sources"]]}
        pyramids: dict[int, ViewPyramid] = {
            i: build_pyramid(
                views[i].camera_id,
                cams[i],
                to_grey(colors[i]),
                config.coarse_levels,
                config.sweep_min_side_px,
                small_exhaustive=config.sweep_small_exhaustive,
            )
            for i in sorted(needed)
        }

    with timings.stage("depth"):
        # Largest first (ROI area x sources): the threads finish together instead of one
        # waiting for the last big job; the last jobs also get the idle threads' cores
        # (``RowBands``). Results are matched to jobs, so the order does not matter otherwise.
        jobs = sorted(
            ((p, roi) for p in plans for roi in p["rois"]),
            key=lambda job: -job[1].area * len(job[0]["sources"]),
        )
        bands = RowBands(config.num_threads)

        def run(job: tuple[dict[str, Any], Roi]) -> DepthEstimate:
            p, roi = job
            return estimate_depth(
                pyramids[p["index"]],
                [pyramids[j] for j in p["sources"]],
                roi,
                p["near"],
                p["far"],
                up_vec,
                config,
                p["region"],
                bands,
            )

        results = run_jobs(run, jobs, config.num_threads, bands, "dense depth maps", cancel=cancel)
        depths: dict[int, DepthMap] = {}
        scores: dict[int, NDArray[np.float32]] = {}
        work = 0
        for (p, _), est in zip(jobs, results, strict=True):
            i = p["index"]
            cam = cams[i]
            if i not in depths:
                depths[i] = np.zeros((cam.height, cam.width), np.float32)
                scores[i] = np.full((cam.height, cam.width), -1.0, np.float32)
            r = est.roi
            sub = depths[i][r.y0 : r.y1, r.x0 : r.x1]
            take = est.depth > 0
            sub[take] = est.depth[take]
            scores[i][r.y0 : r.y1, r.x0 : r.x1][take] = est.score[take]
            work += est.work
            p["work"] += est.work
            p["planes"] = max(p["planes"], est.num_planes)
        for i, m in enumerate(masks):
            if i in depths and m is not None:
                depths[i][~m] = 0.0

    _checkpoint(cancel, "the consistency filter")
    with timings.stage("consistency"):
        id_cams = {i: cams[i] for i in depths}
        rel_tol, noise = agreement_tolerance(depths, id_cams, config)
        stats.update(depth_noise=noise, consistency_rel_depth=rel_tol)
        support, averaged, conflicts, candidates = support_and_conflicts(
            depths,
            id_cams,
            rel_tol,
            num_threads=config.num_threads,
            max_reproj_px=config.consistency_px,
        )
        by_index = {p["index"]: p for p in plans}

        def filtered(i: int) -> tuple[NDArray[np.bool_], DepthMap]:
            # The view's kept depths and their mask, computed within the box of its depths
            # (a foreground's depths cover a fraction of the image; nothing outside it is
            # kept: the same maps).
            d = depths[i]
            keep = np.zeros(d.shape, bool)
            out = np.zeros(d.shape, np.float32)
            box = _depth_box(d)
            if box is None:
                return keep, out
            d = d[box]
            k = filters.consistency_keep(
                d, support[i][box], conflicts[i][box], candidates[i][box], scores[i][box], config
            )
            if config.depth_edge_rel > 0:
                k &= ~filters.depth_edge_mask(d, config.depth_edge_rel)
            keep[box] = k
            # The average over views stays within the view's own depth bounds.
            near, far = by_index[i]["near"], by_index[i]["far"]  # numbers or (H, W) maps
            avg = np.clip(averaged[i][box], _within(near, box), _within(far, box))
            out[box] = np.where(k, avg, 0.0)
            return keep, out

        done = thread_map(filtered, list(depths), config.num_threads)
        keep_masks = {i: r[0] for i, r in zip(depths, done, strict=True)}
        kept = {i: r[1] for i, r in zip(depths, done, strict=True)}

    _checkpoint(cancel, "the fusion")
    with timings.stage("fusion"):
        parts: list[ViewPoints] = thread_map(
            lambda i: view_points(
                views[i].camera_id,
                cams[i],
                kept[i],
                colors[i],
                keep_masks[i],
                support[i],
                scores[i],
            ),
            kept,
            config.num_threads,
        )
        if config.max_grazing_deg < 90:
            centers = {views[i].camera_id: cams[i].center for i in kept}
            parts = [
                vp.select(~filters.grazing_mask(vp, centers[vp.camera_id], config.max_grazing_deg))
                for vp in parts
            ]
        voxel = config.voxel_size
        if voxel is None:
            foot = _auto_voxel(kept, cams)
            voxel = None if foot is None else foot * config.voxel_rel

    plane = None
    if config.ground_completion and up_vec is not None and voxel and parts:
        with timings.stage("ground"):
            ground_stats: dict[str, Any] = {}
            plane, extra = _complete_ground(
                parts, kept, cams, colors, masks, plans, up_vec, voxel, rel_tol, config,
                ground_stats,
            )  # fmt: skip
            if plane is not None:
                band = 3.0 * voxel
                parts = thread_map(lambda p: _drop_below(p, plane, band), parts, config.num_threads)
            for i, (d, sup) in extra.items():
                add = d > 0
                if not add.any():
                    continue
                kept[i] = np.where(add, d, kept[i]).astype(np.float32)
                vp = view_points(
                    views[i].camera_id, cams[i], d, colors[i], add, sup,
                    np.zeros(d.shape, np.float32),
                )  # fmt: skip
                assert plane is not None
                # Points on the plane get its normal (their neighbours may be stereo pixels).
                vp.normals[:] = np.asarray(plane.normal, np.float32)
                parts.append(dataclasses.replace(vp, inferred=True))
                stats["views"].setdefault(views[i].camera_id, {})["ground_depths"] = int(add.sum())

    with timings.stage("fusion"):
        cloud = voxel_merge(parts, voxel) if voxel else voxel_merge([], 1.0)
        if config.outlier_k > 0 and len(cloud):
            out = filters.outlier_mask(
                cloud.points3D, config.outlier_k, config.outlier_std, config.num_threads
            )
            cloud = cloud.select(~out)
            stats["outliers_removed"] = int(out.sum())

    for p in plans:
        i = p["index"]
        stats["views"].setdefault(views[i].camera_id, {}).update(
            {
                "sources": [views[j].camera_id for j in p["sources"]],
                "depth_range": p["range"],
                "range_from": p["range_from"],
                "rois": len(p["rois"]),
                "roi_pixels": int(sum(r.area for r in p["rois"])),
                "planes": p["planes"],
                "work": p["work"],
                "raw_depths": int((depths[i] > 0).sum()) if i in depths else 0,
                "consistent_depths": int(keep_masks[i].sum()) if i in keep_masks else 0,
            }
        )
    stats.update(
        work=int(work),
        working_scale=scale,
        voxel_size=float(voxel) if voxel else None,
        num_points=len(cloud),
        up=None if up_vec is None else [float(x) for x in up_vec],
        ground_plane=None if plane is None else dataclasses.asdict(plane),
        inferred_points=cloud.num_inferred,
        scoring=gpu.scoring_device(config.device),
    )
    if plane is not None:
        stats["ground"] = {**ground_stats, "completed_points": cloud.num_inferred}
    logger.info(
        "dense: %d points from %d views in %.2f s (%s)",
        len(cloud),
        len(views),
        timings.total,
        timings.to_dict(),
    )
    return DenseReconstruction(
        cloud=cloud,
        depth_maps={views[i].camera_id: kept[i] for i in kept},
        depth_cameras={views[i].camera_id: cams[i] for i in kept},
        timings=timings,
        stats=stats,
    )


def _checkpoint(cancel: threading.Event | None, stage: str) -> None:
    if cancel is not None and cancel.is_set():
        raise TaskCancelled(f"dense: cancelled before {stage}")


def _sparse_points(
    sparse: SparseLike | None, views: Sequence[View]
) -> tuple[NDArray[np.float64], NDArray[np.bool_] | None]:
    """Sparse points and, when it matches, their visibility in the given views' order."""
    if sparse is None or len(sparse.cloud) == 0:
        return np.zeros((0, 3)), None
    pts = sparse.cloud.points3D
    vis = np.asarray(sparse.visibility, dtype=bool)
    ids = list(sparse.camera_ids)
    if vis.shape != (len(pts), len(ids)):
        return pts, None
    cols = []
    for v in views:
        cols.append(
            vis[:, ids.index(v.camera_id)] if v.camera_id in ids else np.zeros(len(pts), bool)
        )
    return pts, np.stack(cols, axis=1)


def _plan_view(
    index: int,
    view: View,
    cam: Camera,
    cams: Sequence[Camera],
    mask: Mask | None,
    given: DepthBounds | None,
    sparse_pts: NDArray[np.float64],
    sparse_vis: NDArray[np.bool_] | None,
    scale_len: float,
    config: DenseConfig,
) -> dict[str, Any]:
    """Depth range, per-pixel bounds, ROIs and source views of one reference view."""
    others = [c for j, c in enumerate(cams) if j != index]
    plan: dict[str, Any] = {"index": index, "sources": [], "rois": [], "work": 0, "planes": 0}
    bounds = _bounds_maps(view, cam, given)
    rng = None
    if bounds is not None:
        ok = bounds[0] > 0
        rng = (float(bounds[0][ok].min()), float(bounds[1][ok].max())) if ok.any() else None
        plan["range_from"] = "given"
    else:
        pts = sparse_pts
        if sparse_vis is not None:
            pts = sparse_pts[sparse_vis[:, index]]
        rng = range_from_points(cam, pts, config.range_margin_rel, config.min_sparse_points)
        plan["range_from"] = "sparse"
        if rng is None:
            rng = frustum_range(cam, others, config.max_depth_rel_scene * scale_len)
            plan["range_from"] = "frustum"
    plan["range"] = rng
    if rng is None:
        return plan
    near, far = rng
    if bounds is None:
        bounds = (
            np.full((cam.height, cam.width), near, np.float32),
            np.full((cam.height, cam.width), far, np.float32),
        )
    plan["near"], plan["far"] = bounds
    region = bounds[0] > 0
    if mask is not None:
        region &= mask
    plan["region"] = region
    # Sources, judged on the reference's sparse points (where its surfaces are) and on rays
    # through the pixels to reconstruct (every part of the region, sparse points or not)
    # across their depth bounds, half each.
    surface = np.zeros((0, 3))
    if sparse_vis is not None:
        surface = sparse_pts[sparse_vis[:, index]]
    if len(surface) < config.min_sparse_points:
        surface = np.zeros((0, 3))
    rays = _region_samples(cam, region, bounds)
    samples = np.concatenate([surface, rays])
    sample_weights = np.concatenate(
        [
            np.full(len(surface), 0.5 / max(len(surface), 1)),
            np.full(len(rays), (0.5 if len(surface) else 1.0) / max(len(rays), 1)),
        ]
    )
    scores, weights = point_weights(cam, cams, index, samples)
    plan["sources"] = select_sources(
        scores,
        config.max_source_views,
        config.min_source_angle_deg,
        config.max_source_angle_deg,
        weights=weights,
        sample_weights=sample_weights,
        min_gain=config.min_source_gain,
        min_sources=config.min_source_views,
    )
    plan["source_scores"] = scores
    if not plan["sources"]:
        return plan
    if region.all():
        plan["rois"] = [Roi(0, 0, cam.width, cam.height)]
    elif region.any():
        min_area = (2 * config.window_radius + 1) ** 2 // 4
        plan["rois"] = mask_rois(region, config.roi_margin_px, min_area)
    return plan


def _region_samples(
    cam: Camera,
    region: NDArray[np.bool_],
    bounds: tuple[DepthMap, DepthMap],
    num_pixels: int = 108,
    num_depths: int = 5,
) -> NDArray[np.float64]:
    """Points on the rays of up to ``num_pixels`` pixels spread over ``region`` (a regular
    grid when it is the whole image), at ``num_depths`` depths across each pixel's bounds."""
    if region.all():
        pix = sample_pixels(cam)
    else:
        rows, cols = np.nonzero(region)
        if len(rows) == 0:
            return np.zeros((0, 3))
        pick = np.unique(np.linspace(0, len(rows) - 1, min(len(rows), num_pixels)).astype(int))
        pix = np.stack([cols[pick], rows[pick]], axis=1).astype(np.float64)
    r = np.rint(pix[:, 1]).astype(int).clip(0, cam.height - 1)
    c = np.rint(pix[:, 0]).astype(int).clip(0, cam.width - 1)
    near = bounds[0][r, c].astype(np.float64)
    far = np.maximum(bounds[1][r, c].astype(np.float64), near)
    fractions = np.linspace(0.0, 1.0, num_depths)
    # Geometric spacing between each pixel's near and far (its own bounds).
    depths = near[None] * (far / near)[None] ** fractions[:, None]
    return np.concatenate([cam.backproject(pix, d) for d in depths])


def _auto_voxel(depths: Mapping[int, DepthMap], cams: Sequence[Camera]) -> float | None:
    """Median pixel footprint (depth / focal) over all kept depths."""
    foot = []
    for i, d in depths.items():
        z = d[d > 0]
        if len(z):
            foot.append(float(np.median(z)) / cams[i].focal_px)
    return float(np.median(foot)) if foot else None


#: Depth points the ground plane is fitted to (an even subsample of them when more).
_GROUND_SAMPLE = 500_000


def _complete_ground(
    parts: Sequence[ViewPoints],
    kept: Mapping[int, DepthMap],
    cams: Sequence[Camera],
    colors: Sequence[Image],
    masks: Sequence[Mask | None],
    plans: Sequence[dict[str, Any]],
    up: NDArray[np.float64],
    voxel: float,
    rel_tol: float,
    config: DenseConfig,
    stats: dict[str, Any] | None = None,
) -> tuple[Plane | None, dict[int, tuple[DepthMap, NDArray[np.int16]]]]:
    """Fit the ground plane to the stereo points and fill the floor pixels stereo left (not
    where the level map finds another measured level; its counts go to ``stats``)."""
    # The plane and its outline from an even subsample of the millions of depth points
    # (support counts scaled alike): the same plane for a third of the stage's time. The
    # subsamples are taken part by part (copying every point into one array cost more than
    # the fit).
    step = max(1, sum(len(p.points3D) for p in parts) // _GROUND_SAMPLE)
    sub = slice(None, None, step)
    sub_pts = _every([p.points3D for p in parts], step)
    sub_normals = _every([p.normals for p in parts], step)
    sub_views = _every([p.num_views for p in parts], step)
    plane = fit_ground_plane(
        sub_pts,
        sub_normals,
        sub_views,
        up,
        3.0 * voxel,
        max(3, config.ground_min_support // step),
    )
    if plane is None:
        return None, {}
    normal = np.asarray(plane.normal)
    on_plane = [np.abs(p.points3D @ normal - plane.offset) <= 3.0 * voxel for p in parts]
    known = color_model(
        np.concatenate([p.colors[on] for p, on in zip(parts, on_plane, strict=True)])
    )
    on_points = np.concatenate([p.points3D[on] for p, on in zip(parts, on_plane, strict=True)])
    hull = support_region(plane, on_points[sub])
    by_index = {p["index"]: p for p in plans}

    def region_of(i: int) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
        """The view's pixels to complete (in its bounds and mask, texture under
        ``ground_max_texture``) and which of them are textured (``planes.BLANK_TEXTURE``)."""
        p = by_index[i]
        region = p["near"] > 0 if "near" in p else np.zeros(kept[i].shape, bool)
        if masks[i] is not None:
            region = region & masks[i]
        _, var, _ = kernels.window_stats(to_grey(colors[i]), TEXTURE_WINDOW // 2)
        var = var - kernels.VAR_EPS
        region = np.asarray(region & (var < config.ground_max_texture**2), bool)
        return region, np.asarray(region & (var >= BLANK_TEXTURE**2), bool)

    found = dict(zip(kept, thread_map(region_of, kept, config.num_threads), strict=True))
    regions = {i: r for i, (r, _) in found.items()}
    textured = {i: t for i, (_, t) in found.items()}
    # The per-pixel bounds the depth search had (regions hold only pixels that have them).
    near = {i: by_index[i].get("near", 0.0) for i in kept}
    far = {i: by_index[i].get("far", 0.0) for i in kept}
    extra = complete_with_plane(
        plane,
        kept,
        {i: cams[i] for i in kept},
        {i: colors[i] for i in kept},
        regions,
        far,
        rel_tol,
        config.ground_color_tol,
        config.min_consistent_views,
        known,
        hull,
        num_threads=config.num_threads,
        textured=textured,
        min_ncc=config.ground_min_ncc,
        near=near,
    )
    completed = int(sum(int((d > 0).sum()) for d, _ in extra.values()))
    refused: dict[int, int] = {}
    if config.ground_level_cell > 0 and completed:
        # Verified against the measured levels (built only when there is something to check).
        t0 = time.perf_counter()
        levels = level_map(
            plane,
            sub_pts,
            sub_normals,
            sub_views,
            3.0 * voxel,
            config.ground_level_cell * voxel,
            config.ground_level_min_points,
            max(3, config.ground_min_support // step),
        )
        extra, refused = keep_off_levels(
            levels, extra, {i: cams[i] for i in kept}, config.num_threads
        )
        if stats is not None:
            stats.update(levels.stats())
            stats["level_map_s"] = time.perf_counter() - t0
    if stats is not None:
        stats["refused_depths"] = int(sum(refused.values()))
        stats["completed_depths"] = completed - stats["refused_depths"]
    logger.info("dense: ground plane %s", plane)
    return plane, extra


def _every(arrays: Sequence[NDArray[Any]], step: int) -> NDArray[Any]:
    """Every ``step``-th row of the concatenation of ``arrays`` (rows 0, step, 2 step, ...),
    without copying them all into one array first."""
    out, offset = [], 0
    for a in arrays:
        out.append(a[(-offset) % step :: step])
        offset += len(a)
    return np.concatenate(out)


def _drop_below(part: ViewPoints, plane: Plane, band: float) -> ViewPoints:
    """The part without its points below the ground plane."""
    keep = ~below_plane(part.points3D, plane, band)
    if keep.all():
        return part
    return part.select(keep)


def _depth_box(depth: DepthMap) -> tuple[slice, slice] | None:
    """The bounding box of a depth map's depths (> 0) as slices; None without any."""
    valid = depth > 0
    rows = np.flatnonzero(valid.any(axis=1))
    if len(rows) == 0:
        return None
    cols = np.flatnonzero(valid[rows[0] : rows[-1] + 1].any(axis=0))
    return slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1)


def _within(bound: Any, box: tuple[slice, slice]) -> Any:
    """A depth bound (a number, or a per-pixel map) within ``box``."""
    return bound[box] if np.ndim(bound) == 2 else bound
