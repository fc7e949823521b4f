"""Visual hull: the intersection of the silhouette cones of static calibrated cameras.

With known static poses the foreground masks are geometry: every foreground object lies inside
the cone that its silhouette spans from each camera. The hull is carved on a voxel grid,
coarse to fine:

1. the initial box is the region the rig looks at (``rig_region``) or given bounds;
2. at each level, every voxel is projected into every camera with a mask; it survives when its
   projected footprint (a disc bounding the projected cube, plus ``tolerance_px``) touches the
   silhouette (looked up in a distance transform of the mask) in all cameras that see it but
   ``max_missing`` of them; survivors are split into 8 children for the next level.

The result is conservative (it contains every object that all masks cover, up to the pixel
tolerance) and tight up to one voxel plus the intrinsic looseness of a visual hull from few
views. From it come: a coloured point cloud of the hull surface (a fallback foreground shape),
per-view near/far depth ranges for the dense stage, hull-consistent masks (foreground that no
3D object explains is removed), and 3D object ids (connected components).
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from edgerecon.geometry.camera import Camera
from edgerecon.types import (
    BACKGROUND_LABEL,
    DataError,
    Image,
    Mask,
    PointCloud,
    Points3D,
    StageTimings,
)

logger = logging.getLogger(__name__)

Bounds = tuple[tuple[float, float, float], tuple[float, float, float]]

_NEIGHBOURS6 = np.array(
    [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.int64
)
_CHILDREN = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=np.int64)
#: Projected-footprint inflation that covers lens distortion's local magnification.
_FOOTPRINT_SLACK = 1.1


@dataclass(frozen=True, kw_only=True)
class HullConfig:
    """Parameters of the visual-hull carving."""

    voxel_size: float | None = None
    """Edge of the finest voxels in rig units; None = ``voxel_fraction`` x the rig's scale."""
    voxel_fraction: float = 0.003
    """Finest voxel edge relative to the rig's scale (median camera distance) when
    ``voxel_size`` is None."""
    coarse_cells: int = 16
    """Cells along the longest side of the initial box at the coarsest level."""
    tolerance_px: float = 1.0
    """Silhouette tolerance in pixels (mask boundaries are uncertain by about this much)."""
    min_views: int = 3
    """A voxel must lie inside the images of at least this many cameras with a mask ..."""
    min_views_fraction: float = 0.5
    """... and of at least this share of them (the larger bound wins, capped at the number of
    cameras with a mask): where few cameras see, the cones of different objects intersect in
    'phantom' volumes (beside or below a camera, behind walls) that nothing carves away."""
    max_missing: int = 0
    """A voxel survives when at most this many of the cameras that see it put it outside
    their silhouette (0 = exact intersection; 1 = robust to one bad mask)."""
    bounds: Bounds | None = None
    """Region to carve ((xmin, ymin, zmin), (xmax, ymax, zmax)) in rig units; None = the
    region the rig looks at (``rig_region``)."""
    max_voxels: int = 3_000_000
    """Refinement stops (coarser hull, logged) before a level would exceed this many voxels."""
    object_gap: float | None = None
    """Parts of the hull closer than about this (rig units) belong to one object; None =
    ``object_gap_fraction`` x the rig's scale."""
    object_gap_fraction: float = 0.02
    """``object_gap`` relative to the rig's scale (median camera distance)."""
    min_object_voxels: int = 8
    """Objects with fewer finest voxels are dropped as noise ..."""
    min_object_fraction: float = 0.05
    """... and so are objects smaller than this share of the largest (small phantoms of the
    silhouette intersection)."""

    def __post_init__(self) -> None:
        if self.voxel_size is not None and not self.voxel_size > 0:
            raise ValueError(f"HullConfig.voxel_size must be > 0 or None, got {self.voxel_size}")
        if not 0 < self.voxel_fraction < 1:
            raise ValueError(
                f"HullConfig.voxel_fraction must be in (0, 1), got {self.voxel_fraction}"
            )
        if self.coarse_cells < 1:
            raise ValueError(f"HullConfig.coarse_cells must be >= 1, got {self.coarse_cells}")
        if self.tolerance_px < 0:
            raise ValueError(f"HullConfig.tolerance_px must be >= 0, got {self.tolerance_px}")
        if self.min_views < 1:
            raise ValueError(f"HullConfig.min_views must be >= 1, got {self.min_views}")
        if not 0.0 <= self.min_views_fraction <= 1.0:
            raise ValueError(
                f"HullConfig.min_views_fraction must be in [0, 1], got {self.min_views_fraction}"
            )
        if self.max_missing < 0:
            raise ValueError(f"HullConfig.max_missing must be >= 0, got {self.max_missing}")
        if self.bounds is not None:
            lo, hi = np.asarray(self.bounds[0], float), np.asarray(self.bounds[1], float)
            if lo.shape != (3,) or hi.shape != (3,) or not np.all(hi > lo):
                raise ValueError(
                    f"HullConfig.bounds must be ((x0,y0,z0), (x1,y1,z1)) with x1 > x0 ..., got {self.bounds}"
                )
        if self.max_voxels < 8:
            raise ValueError(f"HullConfig.max_voxels must be >= 8, got {self.max_voxels}")
        if self.object_gap is not None and self.object_gap < 0:
            raise ValueError(f"HullConfig.object_gap must be >= 0 or None, got {self.object_gap}")
        if not 0.0 <= self.object_gap_fraction < 1.0:
            raise ValueError(
                f"HullConfig.object_gap_fraction must be in [0, 1), got {self.object_gap_fraction}"
            )
        if not 0.0 <= self.min_object_fraction <= 1.0:
            raise ValueError(
                f"HullConfig.min_object_fraction must be in [0, 1], got {self.min_object_fraction}"
            )
        if self.min_object_voxels < 1:
            raise ValueError(
                f"HullConfig.min_object_voxels must be >= 1, got {self.min_object_voxels}"
            )


@dataclass(frozen=True, kw_only=True, eq=False)
class VisualHull:
    """Occupied voxels of the finest level (a sparse set on a regular grid)."""

    origin: NDArray[np.float64]
    """(3,) world position of the corner of voxel (0, 0, 0)."""
    voxel_size: float
    """Edge length of the voxels, rig units."""
    indices: NDArray[np.int64]
    """(M, 3) integer grid indices of the occupied voxels, sorted by their key."""
    labels: NDArray[np.int32]
    """(M,) 3D object id per voxel (1..num_objects by decreasing volume)."""
    surface: NDArray[np.bool_]
    """(M,) True for voxels with at least one empty 6-neighbour."""
    normals: NDArray[np.float32]
    """(M,) x 3 outward unit normals estimated from empty neighbours (zero inside)."""
    bounds: NDArray[np.float64]
    """(2, 3) box that was carved."""
    status: str = "ok"
    """"ok", "empty" (no voxel survived: masks empty or inconsistent), or "coarse" (refinement
    stopped at ``max_voxels``)."""
    timings: StageTimings = field(default_factory=StageTimings)
    """Seconds per step."""

    @property
    def num_voxels(self) -> int:
        return int(self.indices.shape[0])

    @property
    def num_objects(self) -> int:
        return int(self.labels.max()) if self.labels.size else 0

    @property
    def centers(self) -> Points3D:
        """(M, 3) voxel centres, rig units."""
        return self.origin + (self.indices + 0.5) * self.voxel_size

    @property
    def volume(self) -> float:
        return float(self.num_voxels * self.voxel_size**3)

    def object_volume(self, object_id: int) -> float:
        return float(np.count_nonzero(self.labels == object_id) * self.voxel_size**3)

    def voxel_of(self, points3D: Points3D) -> NDArray[np.int64]:
        """(N,) index into the voxel arrays of the voxel holding each point, -1 if empty."""
        pts = np.asarray(points3D, dtype=np.float64).reshape(-1, 3)
        if self.num_voxels == 0 or len(pts) == 0:
            return np.full(len(pts), -1, np.int64)
        idx = np.floor((pts - self.origin) / self.voxel_size).astype(np.int64)
        return _lookup(_pack(self.indices), idx)

    def contains(self, points3D: Points3D) -> NDArray[np.bool_]:
        """(N,) True where a point lies in an occupied voxel."""
        return self.voxel_of(points3D) >= 0

    def label_points(self, points3D: Points3D) -> NDArray[np.int32]:
        """(N,) hull object id of each point, 0 (background) outside the hull."""
        v = self.voxel_of(points3D)
        out = np.full(len(v), BACKGROUND_LABEL, np.int32)
        out[v >= 0] = self.labels[v[v >= 0]]
        return out

    def object_bounds(self) -> dict[int, NDArray[np.float64]]:
        """Per object id, its (2, 3) axis-aligned box (voxel extents), rig units."""
        out = {}
        for k in range(1, self.num_objects + 1):
            idx = self.indices[self.labels == k]
            if len(idx):
                lo = self.origin + idx.min(axis=0) * self.voxel_size
                hi = self.origin + (idx.max(axis=0) + 1) * self.voxel_size
                out[k] = np.stack([lo, hi])
        return out


# --------------------------------------------------------------------------- helpers
_KEY_OFFSET = 1 << 20  # indices in [-2^20, 2^20) pack into 21 bits each


def _pack(idx: NDArray[np.int64]) -> NDArray[np.int64]:
    i = np.asarray(idx, dtype=np.int64) + _KEY_OFFSET
    return (i[:, 0] << 42) | (i[:, 1] << 21) | i[:, 2]


def _lookup(sorted_keys: NDArray[np.int64], idx: NDArray[np.int64]) -> NDArray[np.int64]:
    """Position of each index triple in ``sorted_keys`` (-1 when absent)."""
    ok = np.all((idx >= -_KEY_OFFSET) & (idx < _KEY_OFFSET), axis=1)
    keys = _pack(np.where(ok[:, None], idx, 0))
    pos = np.searchsorted(sorted_keys, keys)
    pos = np.minimum(pos, len(sorted_keys) - 1)
    found = ok & (sorted_keys[pos] == keys)
    return np.where(found, pos, -1)


def _check_masks(cameras: Sequence[Camera], masks: Sequence[Mask | None]) -> None:
    if len(masks) != len(cameras):
        raise DataError(f"visual hull: {len(masks)} masks for {len(cameras)} cameras")
    for cam, m in zip(cameras, masks, strict=True):
        if m is not None and np.shape(m) != (cam.height, cam.width):
            raise DataError(
                f"camera {cam.name!r}: mask is {np.shape(m)[1]}x{np.shape(m)[0]} but the camera "
                f"is {cam.width}x{cam.height}"
            )


def _distance_to_silhouette(mask: Mask) -> NDArray[np.float32]:
    """Distance (pixels) from every pixel to the nearest foreground pixel (0 inside)."""
    m = np.asarray(mask, dtype=bool)
    if not m.any():
        return np.full(m.shape, np.inf, np.float32)
    return np.asarray(
        cv2.distanceTransform((~m).view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE), np.float32
    )


def rig_region(cameras: Sequence[Camera], margin_fraction: float = 0.5) -> NDArray[np.float64]:
    """(2, 3) box where a rig's cameras can see objects together: the camera centres and the
    point nearest to all optical axes (where the cameras look), grown by ``margin_fraction``
    of the largest distance between cameras.

    Objects outside some cameras' fields of view are still inside it (unlike the intersection
    of the silhouettes' frusta, which assumes every camera sees every object).
    """
    centers = np.array([c.center for c in cameras])
    axes = np.array([c.viewing_direction for c in cameras])
    proj = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    A = proj.sum(axis=0)
    b = np.einsum("nij,nj->i", proj, centers)
    pts = centers
    if np.linalg.cond(A) < 1e8:
        pts = np.vstack([centers, np.linalg.solve(A, b)])
    span = float(np.max(np.linalg.norm(centers[:, None] - centers[None], axis=2)))
    margin = margin_fraction * max(span, 1e-9)
    return np.stack([pts.min(axis=0) - margin, pts.max(axis=0) + margin])


def _carve_level(
    centers: Points3D,
    size: float,
    cameras: Sequence[Camera],
    dists: Sequence[NDArray[np.float32] | None],
    config: HullConfig,
) -> NDArray[np.bool_]:
    """(M,) survivors among voxels of edge ``size`` centred at ``centers``."""
    n = len(centers)
    seen = np.zeros(n, np.int32)
    missing = np.zeros(n, np.int32)
    half_diag = 0.5 * np.sqrt(3.0) * size
    for cam, dist in zip(cameras, dists, strict=True):
        if dist is None:
            continue
        uv, depth = cam.project(centers)
        front = depth > half_diag
        u = np.rint(uv[:, 0])
        v = np.rint(uv[:, 1])
        inside = front & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        if not inside.any():
            continue
        ui = u[inside].astype(np.intp)
        vi = v[inside].astype(np.intp)
        radius = half_diag * cam.focal_px * _FOOTPRINT_SLACK / depth[inside]
        # + 0.71: the centre was rounded to the nearest pixel.
        touches = dist[vi, ui] <= radius + config.tolerance_px + 0.71
        seen[inside] += 1
        missing[np.flatnonzero(inside)[~touches]] += 1
    num_masks = sum(d is not None for d in dists)
    min_views = max(config.min_views, int(np.ceil(config.min_views_fraction * num_masks)))
    return (seen >= max(min(min_views, num_masks), 1)) & (missing <= config.max_missing)


def _neighbour_positions(keys: NDArray[np.int64], idx: NDArray[np.int64]) -> NDArray[np.int64]:
    """(M, 6) position of each voxel's 6-neighbours in the sorted ``keys`` (-1 = empty)."""
    out = np.empty((len(idx), 6), np.int64)
    for j, d in enumerate(_NEIGHBOURS6):
        out[:, j] = _lookup(keys, idx + d)
    return out


def visual_hull(
    cameras: Sequence[Camera],
    masks: Sequence[Mask | None],
    config: HullConfig | None = None,
) -> VisualHull:
    """Carve the visual hull of the foreground masks.

    ``cameras`` are the rig's cameras (full resolution, with distortion: projection goes
    through ``Camera.project``) or any cameras the masks were made for; ``masks[i]`` is the
    (H, W) foreground of camera i, or None for a camera without a mask (it does not carve).
    An empty foreground, or masks whose cones do not intersect, give an empty hull
    (``status == "empty"``), not an error.
    """
    config = config or HullConfig()
    cameras = list(cameras)
    _check_masks(cameras, masks)
    timings = StageTimings()
    centers_all = np.array([c.center for c in cameras])
    span = (
        float(
            np.median(
                np.linalg.norm(centers_all[:, None] - centers_all[None], axis=2)[
                    np.triu_indices(len(cameras), 1)
                ]
            )
        )
        if len(cameras) > 1
        else 1.0
    )
    target = config.voxel_size if config.voxel_size is not None else config.voxel_fraction * span

    def empty(bounds: NDArray[np.float64]) -> VisualHull:
        return VisualHull(
            origin=bounds[0].copy(),
            voxel_size=float(target),
            indices=np.zeros((0, 3), np.int64),
            labels=np.zeros(0, np.int32),
            surface=np.zeros(0, bool),
            normals=np.zeros((0, 3), np.float32),
            bounds=bounds,
            status="empty",
            timings=timings,
        )

    if config.bounds is not None:
        box = np.array(config.bounds, dtype=np.float64)
    else:
        box = rig_region(cameras)
    if sum(m is not None and bool(np.any(m)) for m in masks) < 1:
        return empty(box)
    with timings.stage("hull_distance"):
        dists = [None if m is None else _distance_to_silhouette(m) for m in masks]

    extent = float(np.max(box[1] - box[0]))
    # Coarsest size is target * 2^L with L chosen so that ~coarse_cells cover the box.
    levels = max(0, int(np.ceil(np.log2(max(extent / config.coarse_cells / target, 1.0)))))
    size = target * 2.0**levels
    origin = box[0] - 0.5 * size  # pad half a cell so boundary objects are not clipped
    counts = np.maximum(np.ceil((box[1] + 0.5 * size - origin) / size).astype(np.int64), 1)
    idx = np.stack(np.meshgrid(*[np.arange(c) for c in counts], indexing="ij"), -1).reshape(-1, 3)
    status = "ok"
    with timings.stage("hull_carve"):
        level = levels
        while True:
            centers = origin + (idx + 0.5) * size
            keep = _carve_level(centers, size, cameras, dists, config)
            idx = idx[keep]
            logger.debug("hull level %d: size %.4g, %d voxels kept", level, size, len(idx))
            if level == 0 or len(idx) == 0:
                break
            if len(idx) * 8 > config.max_voxels:
                logger.warning(
                    "visual hull: stopping at voxel size %.4g (%d voxels; max_voxels=%d)",
                    size,
                    len(idx),
                    config.max_voxels,
                )
                status = "coarse"
                break
            idx = (idx[:, None, :] * 2 + _CHILDREN[None]).reshape(-1, 3)
            size *= 0.5
            level -= 1
    if len(idx) == 0:
        return empty(box)

    with timings.stage("hull_topology"):
        keys = _pack(idx)
        order = np.argsort(keys)
        idx, keys = idx[order], keys[order]
        nb = _neighbour_positions(keys, idx)
        surface = np.any(nb < 0, axis=1)
        # Outward normal: the sum of the directions towards empty neighbours.
        outward = (nb < 0).astype(np.float64) @ _NEIGHBOURS6.astype(np.float64)
        norm = np.linalg.norm(outward, axis=1, keepdims=True)
        normals = np.where(norm > 0, outward / np.maximum(norm, 1e-12), 0.0).astype(np.float32)
        gap = (
            config.object_gap
            if config.object_gap is not None
            else config.object_gap_fraction * span
        )
        labels = _objects(
            idx,
            max(1, round(gap / size)),
            config.min_object_voxels,
            config.min_object_fraction,
        )
        keep = labels > 0
        if not keep.all():
            idx, labels, surface, normals = idx[keep], labels[keep], surface[keep], normals[keep]
    if len(idx) == 0:
        return empty(box)
    return VisualHull(
        origin=origin,
        voxel_size=float(size),
        indices=idx,
        labels=labels,
        surface=surface,
        normals=normals,
        bounds=box,
        status=status,
        timings=timings,
    )


def _objects(
    idx: NDArray[np.int64], cluster: int, min_voxels: int, min_fraction: float
) -> NDArray[np.int32]:
    """Object id per voxel: 26-connected components of the voxels grouped into cubes of
    ``cluster`` voxels (so parts closer than about ``cluster`` voxels join), by decreasing
    size as 1..K; 0 for components below ``min_voxels`` or ``min_fraction`` of the largest."""
    coarse = np.floor_divide(idx, max(cluster, 1))
    ckeys = _pack(coarse)
    uniq, inv = np.unique(ckeys, return_inverse=True)
    first = np.zeros(len(uniq), np.int64)
    first[inv] = np.arange(len(idx))
    cidx = coarse[first]
    m = len(uniq)
    offsets = np.array(
        [
            [i, j, k]
            for i in (-1, 0, 1)
            for j in (-1, 0, 1)
            for k in (-1, 0, 1)
            if (i, j, k) > (0, 0, 0)
        ],
        dtype=np.int64,
    )
    rows, cols = [], []
    for d in offsets:
        pos = _lookup(uniq, cidx + d)
        ok = pos >= 0
        rows.append(np.flatnonzero(ok))
        cols.append(pos[ok])
    r = np.concatenate(rows)
    c = np.concatenate(cols)
    graph = coo_matrix((np.ones(len(r), np.int8), (r, c)), shape=(m, m))
    ncomp, comp = connected_components(graph, directed=False)
    voxel_comp = comp[inv]
    sizes = np.bincount(voxel_comp, minlength=ncomp)
    keep = (sizes >= min_voxels) & (sizes >= min_fraction * sizes.max())
    order = np.argsort(-sizes, kind="stable")
    order = order[keep[order]]
    lut = np.zeros(ncomp, np.int32)
    lut[order] = np.arange(1, len(order) + 1)
    return lut[voxel_comp]


# --------------------------------------------------------------------------- products
def _zbuffer_visible(
    cam: Camera, points: Points3D, voxel_size: float, tolerance: float
) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
    """(N,) visibility of points in ``cam`` (in the image, in front, not hidden behind other
    points by more than ``tolerance``) and their (N, 2) pixel positions."""
    uv, depth = cam.project(points)
    inside = (depth > 0) & cam.in_image(uv)
    vis = np.zeros(len(points), bool)
    if not inside.any():
        return vis, uv
    ii = np.flatnonzero(inside)
    # Buffer cells about one voxel footprint wide so the splats of a surface leave no holes.
    foot = voxel_size * cam.focal_px / depth[ii]
    cell = max(1.0, float(np.median(foot)))
    cw = int(np.ceil(cam.width / cell)) + 1
    cu = (uv[ii, 0] + 0.5) // cell
    cv_ = (uv[ii, 1] + 0.5) // cell
    key = (cv_ * cw + cu).astype(np.int64)
    zmin = np.full(int(key.max()) + 1, np.inf)
    np.minimum.at(zmin, key, depth[ii])
    vis[ii] = depth[ii] <= zmin[key] + tolerance
    return vis, uv


def hull_cloud(
    hull: VisualHull,
    cameras: Sequence[Camera],
    images: Sequence[Image | None],
) -> PointCloud:
    """The hull's surface voxels as a point cloud: labels = 3D object ids, normals from the
    hull, colours = median over the cameras that see each point unoccluded (grey when none),
    ``attributes["num_views"]`` = that number of cameras."""
    if hull.num_voxels == 0:
        return PointCloud(
            points3D=np.zeros((0, 3)),
            colors=np.zeros((0, 3), np.uint8),
            labels=np.zeros(0, np.int32),
            attributes={"num_views": np.zeros(0, np.int32)},
        )
    if len(images) != len(cameras):
        raise DataError(f"hull_cloud: {len(images)} images for {len(cameras)} cameras")
    sel = hull.surface
    pts = hull.centers[sel]
    n = len(pts)
    samples = np.full((len(cameras), n, 3), np.nan, np.float32)
    for ci, (cam, img) in enumerate(zip(cameras, images, strict=True)):
        if img is None:
            continue
        if img.shape[:2] != (cam.height, cam.width):
            raise DataError(
                f"camera {cam.name!r}: image is {img.shape[1]}x{img.shape[0]} but the camera is "
                f"{cam.width}x{cam.height}"
            )
        vis, uv = _zbuffer_visible(cam, pts, hull.voxel_size, 2.0 * hull.voxel_size)
        if not vis.any():
            continue
        m = cv2.remap(
            img,
            uv[vis, 0].astype(np.float32).reshape(-1, 1),
            uv[vis, 1].astype(np.float32).reshape(-1, 1),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        ).reshape(-1, 3)
        samples[ci, vis] = m[:, ::-1]  # BGR -> RGB
    num_views = np.sum(~np.isnan(samples[..., 0]), axis=0).astype(np.int32)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns: no camera sees it
        rgb = np.nanmedian(samples, axis=0)
    rgb = np.where(np.isnan(rgb), 128.0, rgb)
    return PointCloud(
        points3D=pts,
        colors=np.clip(np.rint(rgb), 0, 255).astype(np.uint8),
        normals=hull.normals[sel],
        labels=hull.labels[sel],
        attributes={"num_views": num_views},
    )


@dataclass(frozen=True, kw_only=True, eq=False)
class DepthRange:
    """Per-pixel depth interval of the hull in one view (for the dense stage's search)."""

    near: NDArray[np.float32]
    """(H, W) smallest depth along the optical axis, NaN where the pixel sees no hull."""
    far: NDArray[np.float32]
    """(H, W) largest depth, NaN where the pixel sees no hull."""
    objects: dict[int, tuple[float, float]]
    """Per 3D object id, its (near, far) depth over the whole view."""

    @property
    def mask(self) -> Mask:
        """(H, W) pixels whose ray meets the hull."""
        return ~np.isnan(self.near)


def hull_depth_range(
    hull: VisualHull, camera: Camera, *, margin: float | None = None
) -> DepthRange:
    """Near/far depth of the hull along each pixel's ray of ``camera`` (any camera: a view's
    undistorted, rescaled camera or a rig camera), widened by ``margin`` rig units
    (default: one voxel)."""
    h, w = camera.height, camera.width
    near = np.full((h, w), np.nan, np.float32)
    far = np.full((h, w), np.nan, np.float32)
    margin = hull.voxel_size if margin is None else float(margin)
    if hull.num_voxels == 0:
        return DepthRange(near=near, far=far, objects={})
    pts = hull.centers[hull.surface]
    lab = hull.labels[hull.surface]
    uv, depth = camera.project(pts)
    ok = (depth > 0) & camera.in_image(uv)
    if not ok.any():
        return DepthRange(near=near, far=far, objects={})
    uv, depth, lab = uv[ok], depth[ok], lab[ok]
    objects = {}
    for k in np.unique(lab):
        d = depth[lab == k]
        objects[int(k)] = (float(d.min() - margin), float(d.max() + margin))
    # Splat on a grid of cells about one voxel footprint wide, then fill 3x3 neighbourhoods so
    # that the splats of a surface cover every pixel of its projection.
    foot = hull.voxel_size * camera.focal_px / depth
    cell = max(1, int(np.floor(np.percentile(foot, 10))))
    gh, gw = -(-h // cell), -(-w // cell)
    ci = np.clip(np.rint(uv[:, 1]).astype(np.int64) // cell, 0, gh - 1)
    cj = np.clip(np.rint(uv[:, 0]).astype(np.int64) // cell, 0, gw - 1)
    key = ci * gw + cj
    zn_flat = np.full(gh * gw, np.inf, np.float32)
    zf_flat = np.full(gh * gw, -np.inf, np.float32)
    np.minimum.at(zn_flat, key, depth.astype(np.float32))
    np.maximum.at(zf_flat, key, depth.astype(np.float32))
    k3 = np.ones((3, 3), np.uint8)
    zn = np.asarray(
        cv2.erode(zn_flat.reshape(gh, gw), k3, borderType=cv2.BORDER_CONSTANT, borderValue=np.inf)
    )
    zf = np.asarray(
        cv2.dilate(zf_flat.reshape(gh, gw), k3, borderType=cv2.BORDER_CONSTANT, borderValue=-np.inf)
    )
    valid = np.isfinite(zn) & np.isfinite(zf)
    zn_m = np.where(valid, zn - margin, np.nan).astype(np.float32)
    zf_m = np.where(valid, zf + margin, np.nan).astype(np.float32)
    near[...] = np.repeat(np.repeat(zn_m, cell, axis=0), cell, axis=1)[:h, :w]
    far[...] = np.repeat(np.repeat(zf_m, cell, axis=0), cell, axis=1)[:h, :w]
    return DepthRange(near=near, far=far, objects=objects)


def hull_silhouette(hull: VisualHull, camera: Camera) -> Mask:
    """(H, W) projection of the hull into ``camera`` (each voxel splatted as a disc of its
    projected radius)."""
    h, w = camera.height, camera.width
    out = np.zeros((h, w), np.uint8)
    if hull.num_voxels == 0:
        return out.astype(bool)
    pts = hull.centers[hull.surface]
    uv, depth = camera.project(pts)
    ok = depth > 0
    if not ok.any():
        return out.astype(bool)
    uv, depth = uv[ok], depth[ok]
    radius = 0.5 * np.sqrt(3.0) * hull.voxel_size * camera.focal_px / depth
    # Group by integer radius: one dilation per distinct radius.
    r_int = np.maximum(np.ceil(radius).astype(np.int64), 0)
    u = np.rint(uv[:, 0]).astype(np.int64)
    v = np.rint(uv[:, 1]).astype(np.int64)
    for r in np.unique(r_int):
        sel = (r_int == r) & (u >= -r) & (u < w + r) & (v >= -r) & (v < h + r)
        if not sel.any():
            continue
        layer = np.zeros((h + 2 * r, w + 2 * r), np.uint8)
        layer[v[sel] + r, u[sel] + r] = 1
        if r > 0:
            layer = cv2.dilate(
                layer, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
            )
        out |= layer[r : r + h, r : r + w]
    return out.astype(bool)


def hull_consistent_masks(
    hull: VisualHull, cameras: Sequence[Camera], masks: Sequence[Mask | None]
) -> list[Mask | None]:
    """Masks with the foreground that no hull voxel explains removed (e.g. a change of the
    scene that one camera alone sees, which the other cameras carve away)."""
    _check_masks(list(cameras), masks)
    out: list[Mask | None] = []
    for cam, m in zip(cameras, masks, strict=True):
        if m is None:
            out.append(None)
            continue
        out.append(np.asarray(m, bool) & hull_silhouette(hull, cam))
    return out
