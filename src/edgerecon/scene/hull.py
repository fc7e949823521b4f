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

import dataclasses
import logging
import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from edgerecon.geometry.camera import Camera
from edgerecon.scene._kernels import (
    DISC_HALF_WIDTHS,
    MAX_KERNEL_DISC,
    carve_camera,
    splat_discs,
    surface_normals,
)
from edgerecon.scene.masks import fill_holes, min_discs
from edgerecon.types import (
    BACKGROUND_LABEL,
    INFERRED,
    DataError,
    DepthMap,
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
#: Splat radii (pixels) of the depth-range classes: a voxel uses the first >= its radius.
_RADIUS_CLASSES = np.array([1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64])
#: ``hull_depth_range`` draws discs up to this radius exactly, wider ones on a coarser grid.
_EXACT_RADIUS_PX = 8
#: Projected-footprint inflation that covers lens distortion's local magnification.
_FOOTPRINT_SLACK = 1.1


@dataclass(frozen=True, kw_only=True)
class HullConfig:
    """Parameters of the visual-hull carving."""

    voxel_size: float | None = None
    """Edge of the finest voxels in rig units; None = ``voxel_px`` pixels at the distance
    where the cameras look (so the hull is as fine as the masks it is carved from)."""
    voxel_px: float = 3.0
    """Finest voxel edge in pixels of the masks, at the median distance from the cameras to
    the point they look at, when ``voxel_size`` is None."""
    coarse_cells: int = 16
    """Cells along the longest side of the initial box at the coarsest level."""
    tolerance_px: float = 1.0
    """Silhouette tolerance in pixels (mask boundaries are uncertain by about this much)."""
    min_views: int = 2
    """A voxel must lie inside the silhouettes of at least this many cameras (capped at the
    number of cameras with a mask)."""
    remove_phantoms: bool = True
    """Drop 'phantom' objects: where few cameras see, the cones of different objects intersect
    in volumes that no silhouette carves away; a phantom projects inside other objects'
    projections in every camera (see ``phantom_objects``)."""
    phantom_unique_fraction: float = 0.15
    """An object is real when at least this share of its projection is covered by no other
    object in at least two cameras (or in the only camera that sees it)."""
    phantom_pair_angle_deg: float = 130.0
    """With ``remove_phantoms``, an object whose cameras (those into whose mask at least a
    tenth as many of its voxels project as into the best one's) all face each other more than this many degrees
    apart, seen from the object, is a phantom whatever it covers: two cameras that look at
    each other cannot place anything along their shared line of sight (their cones meet
    along all of it), and no stereo pair can measure it either (the dense stage's sources
    are at most ``DenseConfig.max_source_angle_deg`` apart). 180 = off."""
    max_missing: int = 0
    """A voxel survives when at most this many of the cameras that see it put it outside
    their silhouette (0 = exact intersection; 1 = robust to one bad mask)."""
    bounds: Bounds | None = None
    """Region to carve ((xmin, ymin, zmin), (xmax, ymax, zmax)) in rig units, in the frame
    the rig works in (a georeferenced rig's local frame: world minus ``Rig.origin``, which
    ``edgerecon info`` prints); None = the region the rig looks at (``rig_region``)."""
    max_voxels: int = 3_000_000
    """Refinement stops (coarser hull, logged) before a level would exceed this many voxels."""
    voxel_budget: int | None = 120_000
    """Refinement also stops, quietly (status "ok"), before the next level's candidates (8
    per boundary voxel) would exceed this many: a hull that fills much of the views keeps
    voxels twice as large (a whole person
    2 m from the cameras, caliscope_charuco with the person model: 333,000 voxels of 1.1 cm,
    121 ms of the hull's carving and 88 ms of the photo check per task; the presets' hulls
    hold a few thousand to tens of thousands). None = only ``max_voxels``."""
    object_gap: float | None = None
    """Parts of the hull closer than about this (rig units) belong to one object; None =
    ``object_gap_fraction`` x the rig's scale."""
    object_gap_fraction: float = 0.02
    """``object_gap`` relative to the rig's scale (median distance between cameras)."""
    min_object_voxels: int = 8
    """Objects with fewer finest voxels are dropped as noise ..."""
    min_object_fraction: float = 0.05
    """... and so are objects smaller than this share of the largest (small phantoms of the
    silhouette intersection)."""

    def __post_init__(self) -> None:
        if self.voxel_size is not None and not self.voxel_size > 0:
            raise ValueError(f"HullConfig.voxel_size must be > 0 or None, got {self.voxel_size}")
        if not self.voxel_px > 0:
            raise ValueError(f"HullConfig.voxel_px must be > 0, got {self.voxel_px}")
        if self.coarse_cells < 1:
            raise ValueError(f"HullConfig.coarse_cells must be >= 1, got {self.coarse_cells}")
        if self.tolerance_px < 0:
            raise ValueError(f"HullConfig.tolerance_px must be >= 0, got {self.tolerance_px}")
        if self.min_views < 1:
            raise ValueError(f"HullConfig.min_views must be >= 1, got {self.min_views}")
        if not 0.0 <= self.phantom_unique_fraction <= 1.0:
            raise ValueError(
                "HullConfig.phantom_unique_fraction must be in [0, 1], got "
                f"{self.phantom_unique_fraction}"
            )
        if not 0.0 < self.phantom_pair_angle_deg <= 180.0:
            raise ValueError(
                "HullConfig.phantom_pair_angle_deg must be in (0, 180], got "
                f"{self.phantom_pair_angle_deg}"
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
        if self.voxel_budget is not None and self.voxel_budget < 8:
            raise ValueError(
                f"HullConfig.voxel_budget must be >= 8 or None, got {self.voxel_budget}"
            )
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
    phantom_surface: NDArray[np.int64] = field(default_factory=lambda: np.zeros((0, 3), np.int64))
    """(P, 3) grid indices of the surface voxels of the objects dropped as phantoms
    (``phantom_objects``; ``phantom_explained_masks``)."""

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


def _check_masks(
    cameras: Sequence[Camera], masks: Sequence[NDArray[Any] | None], what: str = "mask"
) -> None:
    if len(masks) != len(cameras):
        raise DataError(f"visual hull: {len(masks)} {what}s for {len(cameras)} cameras")
    for cam, m in zip(cameras, masks, strict=True):
        if m is not None and np.shape(m) != (cam.height, cam.width):
            raise DataError(
                f"camera {cam.name!r}: {what} is {np.shape(m)[1]}x{np.shape(m)[0]} but the "
                f"camera is {cam.width}x{cam.height}"
            )


_Distances = tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]
SilhouetteDistances = list[_Distances | None]
"""Per camera, the distance maps ``visual_hull`` carves with (``silhouette_distances``)."""


def silhouette_distances(masks: Sequence[Mask | None]) -> SilhouetteDistances:
    """The distance maps of ``masks`` that ``visual_hull`` carves with: computed once, they
    can serve several hulls of the same masks (``distances=``)."""
    return [None if m is None else _distance_to_silhouette(m) for m in masks]


def _distance_to_silhouette(mask: Mask) -> _Distances:
    """Per pixel, the distances (pixels) to the nearest foreground pixel; to the nearest
    foreground pixel or the image border (beyond the border is unknown: it may be
    foreground); and to the nearest background pixel or the image border (0 outside)."""
    m = np.asarray(mask, dtype=bool).view(np.uint8)
    if m.any():
        to_fg = cv2.distanceTransform(1 - m, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    else:
        to_fg = np.full(m.shape, np.inf, np.float32)
    bg = cv2.copyMakeBorder(1 - m, 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0)
    to_fg_or_border = cv2.distanceTransform(bg, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[1:-1, 1:-1]
    fg = cv2.copyMakeBorder(m, 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0)
    inside = cv2.distanceTransform(fg, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[1:-1, 1:-1]
    return (
        np.ascontiguousarray(to_fg, np.float32),
        np.ascontiguousarray(to_fg_or_border, np.float32),
        np.ascontiguousarray(inside, np.float32),
    )


def convergence_point(cameras: Sequence[Camera]) -> NDArray[np.float64] | None:
    """(3,) point nearest (least squares) to all optical axes, or None when they are nearly
    parallel."""
    centers = np.array([c.center for c in cameras])
    axes = np.array([c.viewing_direction for c in cameras])
    proj = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    A = proj.sum(axis=0)
    if np.linalg.cond(A) >= 1e8:
        return None
    return np.asarray(np.linalg.solve(A, np.einsum("nij,nj->i", proj, centers)), np.float64)


def _pixel_footprint(cameras: Sequence[Camera], fallback_distance: float) -> float:
    """Size (rig units) of one pixel at the median distance from the cameras to where they
    look (their convergence point; ``fallback_distance`` without one)."""
    target = convergence_point(cameras)
    centers = np.array([c.center for c in cameras])
    dist = (
        float(np.median(np.linalg.norm(centers - target, axis=1)))
        if target is not None
        else fallback_distance
    )
    return dist / float(np.median([c.focal_px for c in cameras]))


def rig_region(cameras: Sequence[Camera], margin_fraction: float = 0.05) -> NDArray[np.float64]:
    """(2, 3) box of the capture volume: the camera centres and a ball around the point
    nearest to all optical axes (where the cameras look) reaching 90 % of the way to the
    nearest camera, grown by ``margin_fraction`` of the largest distance between cameras.

    Cameras standing around a scene bound it; cameras on an arc see a scene around the point
    they look at. Objects outside some cameras' fields of view are still inside (unlike an
    intersection of the silhouettes' frusta); space beyond the cameras is not, where cones
    seen by only two cameras would intersect in large phantoms.
    """
    centers = np.array([c.center for c in cameras])
    span = float(np.max(np.linalg.norm(centers[:, None] - centers[None], axis=2)))
    pts = centers
    target = convergence_point(cameras)
    if target is not None:
        reach = 0.9 * float(np.min(np.linalg.norm(centers - target, axis=1)))
        pts = np.vstack([centers, target - reach, target + reach])
    margin = margin_fraction * max(span, 1e-9)
    return np.stack([pts.min(axis=0) - margin, pts.max(axis=0) + margin])


def _carve_level(
    idx: NDArray[np.int64],
    origin: NDArray[np.float64],
    size: float,
    cameras: Sequence[Camera],
    dists: Sequence[_Distances | None],
    walls: Sequence[NDArray[np.float32] | None],
    config: HullConfig,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """(keep, full) among voxels of edge ``size``: ``keep`` = survives; ``full`` = its whole
    footprint lies inside the silhouette in every camera that can see any part of it (then
    every child survives too and need not be tested)."""
    n = len(idx)
    idx = np.ascontiguousarray(idx, np.int64)
    agree = np.zeros(n, np.int32)
    missing = np.zeros(n, np.int32)
    full = np.ones(n, bool)
    half_diag = np.float32(0.5 * np.sqrt(3.0) * size)
    tol = np.float32(config.tolerance_px + 0.71)  # + 0.71: the centre is rounded to a pixel
    no_wall = np.zeros((1, 1), np.float32)
    for cam, dist, wall in zip(cameras, dists, walls, strict=True):
        if dist is None:
            continue
        to_fg, to_fg_or_border, inside_dist = dist
        # A camera confirms a voxel whose footprint touches its silhouette, and carves one
        # whose footprint touches neither the silhouette nor the image border (beyond the
        # border, part of the voxel may be foreground that this camera does not see); one
        # pass per camera (``_kernels.carve_camera``).
        carve_camera(
            idx,
            (cam.R * size).astype(np.float32),
            (cam.R @ (origin + 0.5 * size) + cam.t).astype(np.float32),
            cam.K.astype(np.float32),
            cam.dist.astype(np.float32),
            cam.has_distortion,
            cam.width,
            cam.height,
            half_diag,
            np.float32(half_diag * np.float32(cam.focal_px * _FOOTPRINT_SLACK)),
            tol,
            to_fg,
            to_fg_or_border,
            inside_dist,
            no_wall if wall is None else wall,
            wall is not None,
            agree,
            missing,
            full,
        )
    num_masks = sum(d is not None for d in dists)
    # At least min_views cameras put the voxel in their foreground, at most max_missing not.
    keep = (agree >= max(min(config.min_views, num_masks), 1)) & (missing <= config.max_missing)
    return keep, keep & full


def _occluder_maps(
    occluders: Sequence[DepthMap | None] | None, n: int
) -> list[NDArray[np.float32] | None]:
    """Per camera, the static scene's depth with unknown pixels (NaN, <= 0) at +inf, and the
    depth at each pixel raised to its 3x3 neighbourhood's maximum (a voxel counts as hidden
    only where the occluder covers it with a pixel to spare)."""
    if occluders is None:
        return [None] * n
    out: list[NDArray[np.float32] | None] = []
    for d in occluders:
        if d is None:
            out.append(None)
            continue
        depth = np.asarray(d, np.float32)
        depth = np.where(np.isfinite(depth) & (depth > 0), depth, np.inf).astype(np.float32)
        out.append(np.asarray(cv2.dilate(depth, np.ones((3, 3), np.uint8)), np.float32))
    return out


def _expand(idx: NDArray[np.int64], levels: int) -> NDArray[np.int64]:
    """All descendants ``levels`` levels down of voxels ``idx``."""
    if levels == 0 or len(idx) == 0:
        return idx
    m = 1 << levels
    r = np.arange(m, dtype=np.int64)
    offs = np.stack(np.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
    return (idx[:, None, :] * m + offs[None]).reshape(-1, 3)


#: Largest dense occupancy grid (cells) used for neighbour look-ups; beyond it, sorted keys.
_MAX_DENSE_CELLS = 64_000_000


def _occupancy(
    idx: NDArray[np.int64], pad: int = 1
) -> tuple[NDArray[np.bool_], NDArray[np.int64]] | None:
    """Dense boolean grid of the voxels (with ``pad`` empty cells around) and its offset, or
    None when it would be too large."""
    lo = idx.min(axis=0) - pad
    shape = idx.max(axis=0) - lo + 1 + pad
    if int(np.prod(shape)) > _MAX_DENSE_CELLS:
        return None
    occ = np.zeros(tuple(int(x) for x in shape), bool)
    p = idx - lo
    occ[p[:, 0], p[:, 1], p[:, 2]] = True
    return occ, lo


def _empty_neighbours(idx: NDArray[np.int64]) -> NDArray[np.bool_]:
    """(M, 6) whether each voxel's 6-neighbours (in ``_NEIGHBOURS6`` order) are empty; ``idx``
    sorted by key."""
    out = np.empty((len(idx), 6), bool)
    grid = _occupancy(idx)
    if grid is not None:
        occ, lo = grid
        p = idx - lo
        for j, d in enumerate(_NEIGHBOURS6):
            q = p + d
            out[:, j] = ~occ[q[:, 0], q[:, 1], q[:, 2]]
        return out
    keys = _pack(idx)
    for j, d in enumerate(_NEIGHBOURS6):
        out[:, j] = _lookup(keys, idx + d) < 0
    return out


def _surface_normals(idx: NDArray[np.int64]) -> tuple[NDArray[np.bool_], NDArray[np.float32]]:
    """Per voxel (``idx`` sorted by key): whether it has an empty 6-neighbour, and its outward
    unit normal (the sum of the directions towards empty neighbours; zero inside)."""
    grid = _occupancy(idx) if len(idx) else None
    if grid is not None:  # one compiled pass over the dense grid (the same numbers)
        occ, lo = grid
        return surface_normals(occ, idx - lo, _NEIGHBOURS6)
    empty_nb = _empty_neighbours(idx)
    surface = np.any(empty_nb, axis=1)
    outward = empty_nb.astype(np.float64) @ _NEIGHBOURS6.astype(np.float64)
    norm = np.linalg.norm(outward, axis=1, keepdims=True)
    normals = np.where(norm > 0, outward / np.maximum(norm, 1e-12), 0.0).astype(np.float32)
    return surface, normals


def visual_hull(
    cameras: Sequence[Camera],
    masks: Sequence[Mask | None],
    config: HullConfig | None = None,
    *,
    occluders: Sequence[DepthMap | None] | None = None,
    distances: SilhouetteDistances | None = None,
) -> VisualHull:
    """Carve the visual hull of the foreground masks.

    ``cameras`` are the rig's cameras (full resolution, with distortion: projection goes
    through ``Camera.project``) or any cameras the masks were made for; ``masks[i]`` is the
    (H, W) foreground of camera i, or None for a camera without a mask (it does not carve).
    ``occluders[i]``, when given, is camera i's depth map of the static scene (e.g. rendered
    from the background cloud by ``depth_map``; NaN or 0 = unknown): a voxel behind it is
    hidden from camera i, which then neither carves nor confirms it (without it, an actor
    behind furniture in one view is carved away). An empty foreground, or masks whose cones
    do not intersect, give an empty hull (``status == "empty"``), not an error.
    ``distances``: ``silhouette_distances(masks)`` when the caller already has them.
    """
    config = config or HullConfig()
    cameras = list(cameras)
    _check_masks(cameras, masks)
    if occluders is not None:
        _check_masks(cameras, occluders, "occluder depth map")
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
    target = (
        config.voxel_size
        if config.voxel_size is not None
        else config.voxel_px * _pixel_footprint(cameras, span)
    )

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
        dists = silhouette_distances(masks) if distances is None else list(distances)
        if len(dists) != len(cameras):
            raise DataError(f"visual hull: {len(dists)} distance maps for {len(cameras)} cameras")
        walls = _occluder_maps(occluders, len(cameras))

    extent = float(np.max(box[1] - box[0]))
    # Coarsest size is target * 2^L with L chosen so that ~coarse_cells cover the box.
    levels = max(0, int(np.ceil(np.log2(max(extent / config.coarse_cells / target, 1.0)))))
    size = target * 2.0**levels
    origin = box[0] - 0.5 * size  # pad half a cell so boundary objects are not clipped
    counts = np.maximum(np.ceil((box[1] + 0.5 * size - origin) / size).astype(np.int64), 1)
    idx = np.stack(np.meshgrid(*[np.arange(c) for c in counts], indexing="ij"), -1).reshape(-1, 3)
    status = "ok"
    full_parts: list[tuple[NDArray[np.int64], int]] = []
    with timings.stage("hull_carve"):
        level = levels
        while True:
            keep, full = _carve_level(idx, origin, size, cameras, dists, walls, config)
            if full.any():
                full_parts.append((idx[full], level))
            idx = idx[keep & ~full]
            logger.debug(
                "hull level %d: size %.4g, %d boundary + %d full voxels",
                level,
                size,
                len(idx),
                int(full.sum()),
            )
            if level == 0 or len(idx) == 0:
                break
            total = 8 * len(idx) + sum(len(f) * 8 ** (lv - level + 1) for f, lv in full_parts)
            if config.voxel_budget is not None and total > config.voxel_budget:
                logger.debug(
                    "visual hull: voxel size %.4g (%d voxels at the next level; voxel_budget=%d)",
                    size,
                    total,
                    config.voxel_budget,
                )
                break
            if total > config.max_voxels:
                logger.warning(
                    "visual hull: stopping at voxel size %.4g (%d voxels at the next level; "
                    "max_voxels=%d)",
                    size,
                    total,
                    config.max_voxels,
                )
                status = "coarse"
                break
            idx = _expand(idx, 1)
            size *= 0.5
            level -= 1
        idx = np.concatenate([idx] + [_expand(f, lv - level) for f, lv in full_parts])
    if len(idx) == 0:
        return empty(box)

    with timings.stage("hull_topology"):
        idx = idx[np.argsort(_pack(idx), kind="stable")]
        surface, normals = _surface_normals(idx)
        gap = (
            config.object_gap
            if config.object_gap is not None
            else config.object_gap_fraction * span
        )
        labels = _objects(
            idx,
            # At least 2 voxels: parts a voxel apart are one object (a hand a voxel off the
            # arm), and the labelling grid is 8x smaller than at 1.
            max(2, round(gap / size)),
            config.min_object_voxels,
            config.min_object_fraction,
        )
        keep = labels > 0
        if not keep.all():
            idx, labels, surface, normals = idx[keep], labels[keep], surface[keep], normals[keep]
    if len(idx) == 0:
        return empty(box)
    hull = VisualHull(
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
    if config.remove_phantoms and (
        hull.num_objects > 1 or (hull.num_objects and config.phantom_pair_angle_deg < 180.0)
    ):
        with timings.stage("hull_phantoms"):
            phantoms = phantom_objects(
                hull,
                cameras,
                masks,
                config.phantom_unique_fraction,
                max_pair_angle_deg=config.phantom_pair_angle_deg,
            )
            if phantoms:
                logger.debug("visual hull: dropping phantom objects %s", phantoms)
                dropped = np.isin(hull.labels, phantoms) & hull.surface
                hull = dataclasses.replace(
                    _without_objects(hull, phantoms), phantom_surface=hull.indices[dropped]
                )
    return hull


def _cleared(hull: VisualHull) -> VisualHull:
    """The hull's grid and box without any voxel."""
    return dataclasses.replace(
        hull,
        indices=np.zeros((0, 3), np.int64),
        labels=np.zeros(0, np.int32),
        surface=np.zeros(0, bool),
        normals=np.zeros((0, 3), np.float32),
        status="empty",
    )


def _without_objects(hull: VisualHull, object_ids: Sequence[int]) -> VisualHull:
    """The hull without some objects; the others renumbered 1..K by decreasing size."""
    keep = ~np.isin(hull.labels, list(object_ids))
    sizes = np.bincount(hull.labels[keep], minlength=hull.num_objects + 1)
    order = [k for k in np.argsort(-sizes[1:], kind="stable") + 1 if sizes[k] > 0]
    lut = np.zeros(hull.num_objects + 1, np.int32)
    lut[order] = np.arange(1, len(order) + 1)
    return dataclasses.replace(
        hull,
        indices=hull.indices[keep],
        labels=lut[hull.labels[keep]],
        surface=hull.surface[keep],
        normals=hull.normals[keep],
    )


def phantom_objects(
    hull: VisualHull,
    cameras: Sequence[Camera],
    masks: Sequence[Mask | None],
    unique_fraction: float = 0.15,
    *,
    max_pair_angle_deg: float = 180.0,
) -> list[int]:
    """Ids of hull objects that explain no silhouette pixel of their own (phantoms).

    Where few cameras see, the silhouette cones of real objects intersect in extra volumes.
    A phantom lies on rays through real objects in every camera, so within the masks its
    projection is covered by the other objects' projections; a real object has pixels only it
    covers. An object is real when at least ``unique_fraction`` of its projection (inside the
    mask) is its own in two cameras (or in the only camera whose image it is in). Phantoms
    are removed one at a time, re-counting after each: in an ambiguous configuration (two
    objects seen by two cameras) real objects and phantoms look alike. With
    ``max_pair_angle_deg`` < 180 the candidate that stereo pairs could measure least goes
    first (the share of its voxels in the masks of two cameras that do not face each
    other, in tenths), then the smallest: a phantom of facing cameras that a third camera
    sees at its edge can be larger than the real object whose pixels it covers (hd4p).

    First, an object seen by two or more cameras that all lie more than
    ``max_pair_angle_deg`` apart as seen from it (opposite cameras) is a phantom whatever
    it covers (``HullConfig.phantom_pair_angle_deg``): the cones of two cameras that face
    each other meet along their whole shared line of sight, so such a volume is where two
    unrelated detections (a ghost in each, or one object and another's ghost) line up, and
    nothing could measure its depth. Without that rule a large opposite-camera phantom can
    cover a real object's pixels in every camera and outlast it (smallest first). A camera
    sees an object where at least a tenth of the object's voxels (the most any camera has)
    project into its mask.
    """
    n = hull.num_objects
    if n < 1:
        return []
    sizes = np.bincount(hull.labels, minlength=n + 1)[1:]
    alive = np.ones(n, bool)
    removed: list[int] = []
    geometry = None
    if max_pair_angle_deg < 180.0:
        geometry = _pair_geometry(hull, cameras, masks, max_pair_angle_deg)
        for k in _facing_objects(hull, *geometry):
            alive[k - 1] = False
            removed.append(k)
    if alive.sum() < 2:
        return removed
    shares: NDArray[np.float64] | None = None  # computed when two candidates compete
    sils = []  # per camera with a mask: (n, h, w) object projections inside the mask
    for cam, m in zip(cameras, masks, strict=True):
        if m is None:
            continue
        stack = hull_object_silhouettes(hull, cam) & np.asarray(m, bool)[None]
        # Only the box that holds them is counted in (the objects cover a few percent of
        # the image; every removal below counts again).
        covered = stack.any(axis=0)  # one pass over the stack, then over one image
        rows = np.flatnonzero(covered.any(axis=1))
        cols = np.flatnonzero(covered.any(axis=0))
        if len(rows):
            stack = stack[:, rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]
        sils.append(stack)
    while alive.sum() > 1:
        own = np.zeros(n, np.int32)
        seen = np.zeros(n, np.int32)
        for stack in sils:
            cover = stack[alive].sum(axis=0)
            area = stack.reshape(n, -1).sum(axis=1)
            unique = (stack & (cover == 1)[None]).reshape(n, -1).sum(axis=1)
            seen += area > 0
            own += (area > 0) & (unique >= unique_fraction * np.maximum(area, 1))
        phantom = alive & (own < np.minimum(2, seen))
        if not phantom.any():
            break
        cand = np.flatnonzero(phantom)
        if len(cand) > 1 and shares is None and geometry is not None:
            shares = _paired_shares(hull, *geometry)
        if shares is None:
            k = int(cand[np.argmin(sizes[cand])])
        else:
            # The one that stereo pairs could measure least (tenths), then the smallest.
            k = int(cand[np.lexsort((sizes[cand], np.round(shares[cand], 1)))[0]])
        alive[k] = False
        removed.append(k + 1)
    return removed


def _pair_geometry(
    hull: VisualHull,
    cameras: Sequence[Camera],
    masks: Sequence[Mask | None],
    max_pair_angle_deg: float,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """``held``: (C, V) whether each voxel centre projects into each camera's mask;
    ``close``: (K, C, C) per hull object, the camera pairs at most ``max_pair_angle_deg``
    apart as seen from its centroid (those that do not face each other)."""
    n = hull.num_objects
    centers = hull.centers
    held = np.zeros((len(cameras), len(centers)), bool)
    for i, (cam, m) in enumerate(zip(cameras, masks, strict=True)):
        if m is None or not m.any():
            continue
        uv, depth = cam.project(centers)
        inside = (depth > 0) & cam.in_image(uv)
        px = np.rint(uv[inside]).astype(np.int64)
        h, w = m.shape
        px[:, 0] = np.clip(px[:, 0], 0, w - 1)
        px[:, 1] = np.clip(px[:, 1], 0, h - 1)
        held[i, np.flatnonzero(inside)] = np.asarray(m, bool)[px[:, 1], px[:, 0]]
    sizes = np.maximum(np.bincount(hull.labels - 1, minlength=n)[:n], 1)
    # (Per coordinate a weighted bincount: the sums np.add.at made, 10x faster.)
    sums = [np.bincount(hull.labels - 1, weights=centers[:, j], minlength=n)[:n] for j in range(3)]
    centroids = np.stack(sums, axis=1).astype(np.float64) / sizes[:, None]
    origins = np.array([c.center for c in cameras], np.float64).reshape(-1, 3)
    rays = centroids[:, None, :] - origins[None]  # (K, C, 3)
    rays /= np.maximum(np.linalg.norm(rays, axis=2, keepdims=True), 1e-12)
    close = np.einsum("kad,kbd->kab", rays, rays) >= math.cos(math.radians(max_pair_angle_deg))
    return held, close


def _facing_objects(
    hull: VisualHull, held: NDArray[np.bool_], close: NDArray[np.bool_]
) -> list[int]:
    """Ids of the hull objects seen by two or more cameras that all face each other
    (``_pair_geometry``; see ``phantom_objects``). A camera sees an object where at least a
    tenth of the object's voxels (the most any camera has) project into its mask."""
    facing = []
    for k in range(1, hull.num_objects + 1):
        counts = held[:, hull.labels == k].sum(axis=1)
        sees = (counts > 0) & (counts >= 0.1 * counts.max())
        pairs_ok = np.triu(close[k - 1][np.ix_(sees, sees)], 1)
        if sees.sum() >= 2 and not pairs_ok.any():
            facing.append(k)
    return facing


def _paired_shares(
    hull: VisualHull, held: NDArray[np.bool_], close: NDArray[np.bool_]
) -> NDArray[np.float64]:
    """(K,) per hull object, the share of its voxels whose centres lie in the masks of two
    cameras that do not face each other (``_pair_geometry``): the part of it that a stereo
    pair could measure."""
    shares = np.zeros(hull.num_objects)
    pairs = np.triu_indices(held.shape[0], 1)
    for k in range(1, hull.num_objects + 1):
        sub = held[:, hull.labels == k]
        paired = np.zeros(sub.shape[1], bool)
        for a, b in zip(*pairs, strict=True):
            if close[k - 1, a, b]:
                paired |= sub[a] & sub[b]
        shares[k - 1] = float(paired.mean()) if len(paired) else 0.0
    return shares


def _objects(
    idx: NDArray[np.int64], cluster: int, min_voxels: int, min_fraction: float
) -> NDArray[np.int32]:
    """Object id per voxel: 26-connected components of the voxels grouped into cubes of
    ``cluster`` voxels (so parts closer than about ``cluster`` voxels join), by decreasing
    size as 1..K; 0 for components below ``min_voxels`` or ``min_fraction`` of the largest."""
    coarse = np.floor_divide(idx, max(cluster, 1))
    grid = _occupancy(coarse, pad=0)
    if grid is not None:
        occ, lo = grid
        lab, ncomp = ndimage.label(occ, structure=np.ones((3, 3, 3), bool))
        p = coarse - lo
        voxel_comp = lab[p[:, 0], p[:, 1], p[:, 2]] - 1
        return _rank_components(voxel_comp, ncomp, min_voxels, min_fraction)
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
    return _rank_components(comp[inv], ncomp, min_voxels, min_fraction)


def _rank_components(
    voxel_comp: NDArray[np.intp], ncomp: int, min_voxels: int, min_fraction: float
) -> NDArray[np.int32]:
    """Component ids -> 1..K by decreasing size, 0 for the small ones."""
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


def sample_bilinear(image: Image, points2D: NDArray[np.float64]) -> NDArray[np.float32]:
    """(N, C) bilinear samples of an image at (N, 2) pixel positions (border replicated)."""
    n = len(points2D)
    if n == 0:
        return np.zeros((0, image.shape[2] if image.ndim == 3 else 1), np.float32)
    # remap needs maps smaller than 32767 on each side: lay the points out in rows.
    width = 1024
    rows = -(-n // width)
    maps = np.zeros((2, rows * width), np.float32)
    maps[:, :n] = points2D.T
    out = cv2.remap(
        image.astype(np.float32),
        maps[0].reshape(rows, width),
        maps[1].reshape(rows, width),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    return np.asarray(out, np.float32).reshape(rows * width, -1)[:n]


def hull_cloud(
    hull: VisualHull,
    cameras: Sequence[Camera],
    images: Sequence[Image | None],
) -> PointCloud:
    """The hull's surface voxels as a point cloud: labels = 3D object ids, normals from the
    hull, colours = median over the cameras that see each point unoccluded (grey when none),
    ``attributes["num_views"]`` = that number of cameras. Every point is inferred
    (``attributes["inferred"]`` = 1): silhouettes bound the shape, no depth measured it."""
    if hull.num_voxels == 0:
        return PointCloud(
            points3D=np.zeros((0, 3)),
            colors=np.zeros((0, 3), np.uint8),
            labels=np.zeros(0, np.int32),
            attributes={"num_views": np.zeros(0, np.int32), INFERRED: np.zeros(0, np.uint8)},
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
        m = sample_bilinear(img, uv[vis])
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
        attributes={"num_views": num_views, INFERRED: np.ones(n, np.uint8)},
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

    def maps(self) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """(near, far) with 0 where the ray misses the hull: the per-pixel form of
        ``dense.reconstruct_dense(..., depth_ranges={camera_id: maps})``."""
        near = np.where(np.isnan(self.near), 0.0, np.maximum(self.near, 0.0))
        far = np.where(np.isnan(self.far), 0.0, self.far)
        return near.astype(np.float32), far.astype(np.float32)


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
    # Each voxel covers a disc of its projected radius: splat the centres per radius class
    # (a few geometric classes), spread them with a min (near) / max (far) filter of that
    # radius, and combine the classes.
    radius = 0.5 * np.sqrt(3.0) * hull.voxel_size * camera.focal_px / depth
    u = np.clip(np.rint(uv[:, 0]).astype(np.intp), 0, w - 1)
    v = np.clip(np.rint(uv[:, 1]).astype(np.intp), 0, h - 1)
    z = depth.astype(np.float32)
    zn = np.full((h, w), np.inf, np.float32)
    zf = np.full((h, w), np.inf, np.float32)  # minus the far depth
    classes = np.searchsorted(_RADIUS_CLASSES, radius)
    for c in np.unique(classes):
        sel = classes == c
        r = int(_RADIUS_CLASSES[min(c, len(_RADIUS_CLASSES) - 1)])
        # Discs wider than _EXACT_RADIUS_PX (voxels near a camera, or a view much finer than
        # the masks the hull was carved from) on a coarser grid that covers them: the
        # intervals only widen a little at the outline (one camera's 48-px discs took 1.5 s
        # at 1824x1026 as exact whole-image filters).
        min_discs(zn, u[sel], v[sel], z[sel], r, coarse_above=_EXACT_RADIUS_PX)
        min_discs(zf, u[sel], v[sel], -z[sel], r, coarse_above=_EXACT_RADIUS_PX)
    zf = -zf
    # (OpenCV's filters turn infinities into +-FLT_MAX.)
    valid = (zn < 1e30) & (zf > -1e30)
    near[valid] = zn[valid] - margin
    far[valid] = zf[valid] + margin
    return DepthRange(near=near, far=far, objects=objects)


def hull_silhouette(hull: VisualHull, camera: Camera, *, object_id: int | None = None) -> Mask:
    """(H, W) projection of the hull (or of one object) into ``camera`` (each surface voxel
    splatted as a disc of its projected radius)."""
    if hull.num_voxels == 0:
        return np.zeros((camera.height, camera.width), bool)
    sel = hull.surface if object_id is None else hull.surface & (hull.labels == object_id)
    return _splat_voxels(hull.origin + (hull.indices[sel] + 0.5) * hull.voxel_size, hull, camera)


def phantom_silhouette(
    hull: VisualHull, camera: Camera, *, box: tuple[int, int, int, int] | None = None
) -> Mask:
    """(H, W) projection of the objects the hull dropped as phantoms into ``camera``; with
    ``box`` = (x0, y0, x1, y1), drawn only within it (the rest is False)."""
    centers = hull.origin + (hull.phantom_surface + 0.5) * hull.voxel_size
    return _splat_voxels(centers, hull, camera, box)


def hull_object_silhouettes(hull: VisualHull, camera: Camera) -> NDArray[np.bool_]:
    """(objects, H, W) ``hull_silhouette`` of every object of the hull (object k at k - 1),
    its surface voxels projected once."""
    h, w = camera.height, camera.width
    n = hull.num_objects
    out = np.zeros((n, h, w), np.uint8)
    if n == 0 or hull.num_voxels == 0:
        return out.view(bool)
    sel = hull.surface & (hull.labels > 0)
    labels = hull.labels[sel]
    drawn = _projected_voxels(
        hull.origin + (hull.indices[sel] + 0.5) * hull.voxel_size, hull, camera
    )
    if drawn is None:
        return out.view(bool)
    u, v, r_int, ok = drawn
    labels = labels[ok]
    for k in np.unique(labels).tolist():
        on = labels == k
        _draw_voxels(out[k - 1], u[on], v[on], r_int[on], (0, 0, w, h))
    return out.view(bool)


def _projected_voxels(
    centers: Points3D, hull: VisualHull, camera: Camera
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], NDArray[np.bool_]] | None:
    """The pixels (u, v) and integer disc radii of voxels of ``hull``'s size centred at
    ``centers`` in ``camera``, and which centres they are (None: none is drawn)."""
    h, w = camera.height, camera.width
    if len(centers) == 0:
        return None
    uv, depth = camera.project(centers)
    # (Voxels near the camera's plane project to huge or non-finite pixels: never drawn.)
    ok = (depth > 0) & np.all(np.abs(uv) < 1e9, axis=1)
    if not ok.any():
        return None
    uv, depth = uv[ok], depth[ok]
    radius = 0.5 * np.sqrt(3.0) * hull.voxel_size * camera.focal_px / depth
    # (At most the image's size: a voxel at the camera's centre covers it all.)
    r_int = np.clip(np.ceil(radius), 0, max(h, w)).astype(np.int64)
    u = np.rint(uv[:, 0]).astype(np.int64)
    v = np.rint(uv[:, 1]).astype(np.int64)
    return u, v, r_int, ok


def _splat_voxels(
    centers: Points3D,
    hull: VisualHull,
    camera: Camera,
    box: tuple[int, int, int, int] | None = None,
) -> Mask:
    """Voxels of ``hull``'s size centred at ``centers`` splatted into ``camera`` as discs
    (only within ``box`` = (x0, y0, x1, y1) when given: a phantom reaching towards a camera
    covers much of its image with discs of many radii)."""
    h, w = camera.height, camera.width
    out = np.zeros((h, w), np.uint8)
    drawn = _projected_voxels(centers, hull, camera)
    if drawn is not None:
        u, v, r_int, _ = drawn
        _draw_voxels(out, u, v, r_int, (0, 0, w, h) if box is None else box)
    return out.view(bool)


def _draw_voxels(
    out: NDArray[np.uint8],
    u: NDArray[np.int64],
    v: NDArray[np.int64],
    r_int: NDArray[np.int64],
    box: tuple[int, int, int, int],
) -> None:
    """Set in ``out`` (within ``box``) the discs of radius ``r_int`` around (u, v)."""
    bx0, by0, bx1, by1 = box
    # The discs up to MAX_KERNEL_DISC point by point (compiled), the wider ones (voxels near
    # the camera: few, large) with one dilation per radius.
    small = r_int <= MAX_KERNEL_DISC
    if small.any():
        splat_discs(out, u[small], v[small], r_int[small], DISC_HALF_WIDTHS, bx0, by0, bx1, by1)
    if small.all():
        return
    wide = ~small
    u, v, r_int = u[wide], v[wide], r_int[wide]
    for r in np.flatnonzero(np.bincount(r_int)).tolist():  # the radii present (small integers)
        sel = (r_int == r) & (u >= bx0 - r) & (u < bx1 + r) & (v >= by0 - r) & (v < by1 + r)
        if not sel.any():
            continue
        us, vs = u[sel], v[sel]
        # Only the box around these splats (+ r) is dilated: an object covers a few percent
        # of the image, and phantom removal splats every object into every camera.
        x0, y0 = max(int(us.min()) - r, bx0), max(int(vs.min()) - r, by0)
        x1, y1 = min(int(us.max()) + r + 1, bx1), min(int(vs.max()) + r + 1, by1)
        layer = np.zeros((y1 - y0 + 2 * r, x1 - x0 + 2 * r), np.uint8)
        ok = (us >= x0 - r) & (us < x1 + r) & (vs >= y0 - r) & (vs < y1 + r)
        layer[vs[ok] - y0 + r, us[ok] - x0 + r] = 1
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        layer = np.asarray(cv2.dilate(layer, disc), np.uint8)
        out[y0:y1, x0:x1] |= layer[r : r + y1 - y0, r : r + x1 - x0]


def depth_map(points3D: Points3D, camera: Camera, *, fill_px: int = 2) -> NDArray[np.float32]:
    """(H, W) depth (along the optical axis) of the nearest point per pixel of ``camera``,
    NaN where no point projects; gaps up to ``fill_px`` pixels between the points are filled
    with the nearest depth around them (a point cloud of the static scene becomes an occluder
    map for ``visual_hull``)."""
    h, w = camera.height, camera.width
    uv, depth = camera.project(points3D)
    ok = (depth > 0) & camera.in_image(uv)
    z = np.full(h * w, np.inf, np.float32)
    if ok.any():
        u = np.clip(np.rint(uv[ok, 0]).astype(np.intp), 0, w - 1)
        v = np.clip(np.rint(uv[ok, 1]).astype(np.intp), 0, h - 1)
        np.minimum.at(z, v * w + u, depth[ok].astype(np.float32))
    img = z.reshape(h, w)
    if fill_px > 0:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * fill_px + 1,) * 2)
        img = np.minimum(img, np.asarray(cv2.erode(img, k), np.float32))
    return np.where(np.isfinite(img), img, np.nan).astype(np.float32)


def hull_consistent_masks(
    hull: VisualHull,
    cameras: Sequence[Camera],
    masks: Sequence[Mask | None],
    *,
    max_missing: int = 0,
    occluders: Sequence[DepthMap | None] | None = None,
    ray_samples: int = 48,
    pixels_per_region: int = 64,
) -> list[Mask | None]:
    """Masks with the foreground that the other cameras contradict removed.

    Foreground that no hull voxel explains (e.g. a change of the scene that one camera alone
    sees) is removed when the other cameras contradict it: every point of the pixel's ray
    inside the hull's region is seen as background by more than ``max_missing`` other
    cameras (use the hull's ``HullConfig.max_missing``); with ``occluders`` (as for
    ``visual_hull``), a camera does not contradict points hidden behind its static scene. Where some part of
    the ray is seen by no other camera (an actor next to a camera, outside its neighbours'
    fields of view), nobody can check it and the foreground stays. Each connected region of
    unexplained pixels is decided as a whole, from up to ``pixels_per_region`` of its pixels
    with ``ray_samples`` points along each ray.

    Tried and kept out: letting only the points that another camera sees keep the
    foreground. It removes the ghosts whose rays end outside the other cameras' views (hd4:
    2,541 of 5,224 false pixels of one camera; moving-actor IoU 0.661 -> 0.673), but on
    caliscope_charuco it removed 1,000-15,000 working pixels per task of the seated person
    (head, shoulders) that the other cameras' models had learned as background.
    """
    cams = list(cameras)
    _check_masks(cams, masks)
    walls = _occluder_maps(occluders, len(cams))
    out: list[Mask | None] = []
    for c, (cam, m) in enumerate(zip(cams, masks, strict=True)):
        if m is None:
            out.append(None)
            continue
        mask = np.asarray(m, bool)
        kept = mask & hull_silhouette(hull, cam)
        unexplained = mask & ~kept
        if unexplained.any():
            others = [
                (o, np.asarray(om, bool), walls[i])
                for i, (o, om) in enumerate(zip(cams, masks, strict=True))
                if i != c and om is not None
            ]
            kept |= _uncontradicted(
                cam, others, unexplained, hull.bounds, max_missing, ray_samples, pixels_per_region
            )
        out.append(kept)
    return out


def _uncontradicted(
    cam: Camera,
    others: Sequence[tuple[Camera, Mask, NDArray[np.float32] | None]],
    region_mask: Mask,
    box: NDArray[np.float64],
    max_missing: int,
    ray_samples: int,
    per_region: int,
) -> Mask:
    """The connected regions of ``region_mask`` where, for most sampled pixels, some point
    of the ray inside ``box`` is not seen as background by any camera of ``others``."""
    n, comp = cv2.connectedComponents(region_mask.view(np.uint8), connectivity=8)
    ys, xs = np.nonzero(region_mask)
    lab = comp[ys, xs]
    # Up to per_region random pixels of each region: shuffle, group by region (stable), keep
    # the first per_region of each group.
    order = np.random.default_rng(0).permutation(len(lab))
    order = order[np.argsort(lab[order], kind="stable")]
    grouped = lab[order]
    rank = np.arange(len(grouped)) - np.searchsorted(grouped, grouped, side="left")
    pick = order[rank < per_region]
    px = np.stack([xs[pick], ys[pick]], axis=1).astype(np.float64)
    plab = lab[pick]
    rays = cam.pixel_rays(px)
    dirs = rays @ cam.R  # world directions (not unit; depth parametrisation)
    origin = cam.center
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (box[0] - origin) / dirs
        t2 = (box[1] - origin) / dirs
    tnear = np.maximum(np.nanmax(np.minimum(t1, t2), axis=1), 0.0)
    tfar = np.nanmin(np.maximum(t1, t2), axis=1)
    hit = tfar > tnear
    contradicted = np.zeros((len(px), ray_samples), np.int32)
    grow = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    frac = (np.arange(ray_samples) + 0.5) / ray_samples
    depth = tnear[:, None] + (tfar - tnear)[:, None] * frac[None, :]
    pts = origin + dirs[:, None, :] * depth[..., None]  # (P, S, 3)
    flat = pts.reshape(-1, 3)
    for other, omask, wall in others:
        fg = cv2.dilate(omask.view(np.uint8), grow).astype(bool)
        _, d, u, v, vis = other.nearest_pixels(flat)
        if wall is not None:
            vis &= ~(d > wall[v, u])
        contradicted += (vis & ~fg[v, u]).reshape(len(px), ray_samples)
    unverified = ~hit | ~(contradicted > max_missing).all(axis=1)
    votes = np.bincount(plab, weights=unverified.astype(np.float64), minlength=n)
    total = np.bincount(plab, minlength=n)
    restore = (total > 0) & (votes >= 0.5 * np.maximum(total, 1))
    restore[0] = False
    return np.asarray(restore[comp], bool)


def tolerant_hull(
    hull: VisualHull,
    cameras: Sequence[Camera],
    model_masks: Sequence[Mask | None],
    config: HullConfig,
    *,
    occluders: Sequence[DepthMap | None] | None = None,
    distances: SilhouetteDistances | None = None,
) -> VisualHull:
    """The hull that one camera may disagree with (``max_missing`` = 1), carved from
    ``model_masks`` with voxels twice the exact hull's inside the exact hull ``hull``'s box
    (plus 4 of its voxels), keeping only its objects that contain exact-hull voxels (the rest
    are the phantoms that a tolerant hull of few views adds). Empty with fewer than 4
    cameras with a mask (a 2-of-3 hull is too loose to vouch for anything) or an empty
    ``hull``. ``distances``: ``silhouette_distances(model_masks)`` when the caller has
    them."""
    cams = list(cameras)
    _check_masks(cams, model_masks)
    with_mask = sum(m is not None for m in model_masks)
    if hull.num_voxels == 0 or with_mask < 4:
        return _cleared(hull)
    centers = hull.centers
    margin = 4.0 * hull.voxel_size
    lo = np.maximum(centers.min(axis=0) - margin, hull.bounds[0])
    hi = np.minimum(centers.max(axis=0) + margin, hull.bounds[1])
    tolerant_cfg = dataclasses.replace(
        config,
        max_missing=max(config.max_missing, 1),
        remove_phantoms=False,  # anchoring in the exact hull below does that job
        voxel_size=2.0 * hull.voxel_size,  # its users clip it to outlines or sample it
        bounds=(tuple(float(x) for x in lo), tuple(float(x) for x in hi)),  # type: ignore[arg-type]
    )
    tolerant = visual_hull(
        cams, model_masks, tolerant_cfg, occluders=occluders, distances=distances
    )
    if tolerant.num_voxels == 0:
        return tolerant
    anchored = set(np.unique(tolerant.labels[hull.contains(tolerant.centers)]).tolist())
    drop = [k for k in range(1, tolerant.num_objects + 1) if k not in anchored]
    return _without_objects(tolerant, drop) if drop else tolerant


def _grown_silhouette(hull: VisualHull, camera: Camera, grow_px: int) -> Mask:
    """The hull's silhouette in ``camera`` grown by ``grow_px`` pixels (a disc)."""
    sil = hull_silhouette(hull, camera)
    if grow_px > 0 and sil.any():
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * grow_px + 1, 2 * grow_px + 1))
        sil = cv2.dilate(sil.astype(np.uint8), k).astype(bool)
    return sil


def hull_explained_masks(
    hull: VisualHull,
    cameras: Sequence[Camera],
    masks: Sequence[Mask | None],
    allowed: Sequence[Mask | None],
    grow_px: int = 4,
) -> list[Mask | None]:
    """``masks`` without the ``allowed`` pixels (e.g. the background models' unsettled ones)
    that the hull does not explain: outside its silhouette in that camera grown by
    ``grow_px`` pixels. A ghost that two facing cameras share survives the consistency test
    (each camera's ray runs along the other's ghost, so neither contradicts the other), and
    where the other cameras do not see that far it is contradicted by nobody; the hull's
    objects, phantoms removed, do not hold it. A camera without a mask or ``allowed`` map
    is left as it is; an empty hull explains nothing."""
    _check_masks(list(cameras), masks)
    out: list[Mask | None] = []
    for cam, m, a in zip(cameras, masks, allowed, strict=True):
        if m is None or a is None or not (m & a).any():
            out.append(m)
            continue
        out.append(m & ~(a & ~_grown_silhouette(hull, cam, grow_px)))
    return out


def phantom_explained_masks(
    hull: VisualHull,
    cameras: Sequence[Camera],
    masks: Sequence[Mask | None],
    allowed: Sequence[Mask | None],
    grow_px: int = 4,
    *,
    min_settled_px: int = 500,
) -> list[Mask | None]:
    """``masks`` without the ``allowed`` pixels (e.g. the background models' unsettled ones)
    that only a phantom explains: inside the silhouette of the objects the hull dropped as
    phantoms (``VisualHull.phantom_surface``) and outside its own silhouette grown by
    ``grow_px`` pixels. Ghosts that two facing cameras share carve a phantom where their
    cones meet; removing the phantom leaves their pixels in the masks, explained by nothing
    real. Unlike ``hull_explained_masks`` it leaves alone the parts of a real object that
    the hull does not hold (a close person's head that two cameras' masks miss).

    Nothing changes when the masks hold fewer than ``min_settled_px`` pixels outside
    ``allowed`` in all (the first second of a stream without an empty clip: every actor
    stands where the models learned, and one that only the two cameras facing each other
    along its path still detect is a phantom to the hull), nor for a hull without
    phantoms."""
    _check_masks(list(cameras), masks)
    if len(hull.phantom_surface) == 0:
        return list(masks)
    settled = sum(
        int(np.count_nonzero(m & ~a))
        for m, a in zip(masks, allowed, strict=True)
        if m is not None and a is not None
    )
    if settled < min_settled_px:
        return list(masks)
    out: list[Mask | None] = []
    for cam, m, a in zip(cameras, masks, allowed, strict=True):
        if m is None or a is None or not (m & a).any():
            out.append(m)
            continue
        unexplained = m & a & ~_grown_silhouette(hull, cam, grow_px)
        if unexplained.any():
            x, y, bw, bh = cv2.boundingRect(unexplained.view(np.uint8))
            phantom = phantom_silhouette(hull, cam, box=(x, y, x + bw, y + bh))
            m = m & ~(unexplained & phantom)
        out.append(m)
    return out


def hull_filled_masks(
    hull: VisualHull,
    cameras: Sequence[Camera],
    masks: Sequence[Mask | None],
    model_masks: Sequence[Mask | None],
    config: HullConfig,
    *,
    close_px: int = 15,
    occluders: Sequence[DepthMap | None] | None = None,
    distances: SilhouetteDistances | None = None,
    allowed: Sequence[Mask | None] | None = None,
    tolerant: VisualHull | None = None,
) -> list[Mask | None]:
    """Masks with their holes filled where the other cameras agree that an object is there.

    A still actor whose colours match the background model in places (a ghost-free model
    cannot be learned while it stands where it stood during the bootstrap) gets holes in
    some cameras' masks; the exact hull ``hull`` is then carved through by them. This
    takes the tolerant hull (``tolerant_hull``: one camera may disagree, anchored in the
    exact hull; ``tolerant`` when the caller has it), projects it into every camera and
    adds the projection where it lies inside the camera's mask outline: the mask closed by
    a disc of ``close_px`` pixels, holes filled. Foreground is only ever added, and only
    inside an outline the camera itself drew, so the hull's looseness does not leak out of
    the silhouettes.

    ``allowed[c]``, when given, limits where camera c may be filled (its background
    model's ``unsettled`` pixels: elsewhere a hole is the camera's own carving of the
    hull's looseness, e.g. between an actor's legs, and filling it costs precision; demo
    preset with an empty-scene clip: precision 0.949 -> 0.885 with the fill everywhere).

    Needs at least 4 cameras with a mask (a 2-of-3 hull is too loose to vouch for a pixel);
    with fewer, or an empty hull, the masks come back unchanged. ``distances``:
    ``silhouette_distances(model_masks)`` when the caller already has them.
    """
    cams = list(cameras)
    _check_masks(cams, masks)
    _check_masks(cams, model_masks)
    out = [None if m is None else np.asarray(m, bool) for m in masks]
    with_mask = sum(m is not None for m in model_masks)
    if hull.num_voxels == 0 or with_mask < 4:
        return out
    # Where each camera may gain pixels: inside its mask's closed outline, less the mask,
    # within ``allowed``. Nothing to fill anywhere: no second hull.
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * (close_px // 2) + 1,) * 2)
    room: list[Mask | None] = []
    for c, mask in enumerate(out):
        if mask is None or not mask.any():
            room.append(None)
            continue
        outline = fill_holes(cv2.morphologyEx(mask.view(np.uint8), cv2.MORPH_CLOSE, disc) > 0)
        gap = outline & ~mask
        if allowed is not None and allowed[c] is not None:
            gap &= np.asarray(allowed[c], bool)
        room.append(gap if gap.any() else None)
    if all(r is None for r in room):
        return out
    if tolerant is None:
        tolerant = tolerant_hull(
            hull, cams, model_masks, config, occluders=occluders, distances=distances
        )
    if tolerant.num_voxels == 0:
        return out
    # The projection of a solid is that of its surface, and the exact hull's projection lies
    # in the masks already: only the surface voxels outside the exact hull can add pixels.
    tolerant = dataclasses.replace(
        tolerant, surface=tolerant.surface & ~hull.contains(tolerant.centers)
    )
    if not tolerant.surface.any():
        return out
    for c, cam in enumerate(cams):
        gap = room[c]
        mask = out[c]
        if gap is not None and mask is not None:
            out[c] = mask | (_coarse_silhouette(tolerant, cam) & gap)
    return out


def _coarse_silhouette(hull: VisualHull, camera: Camera, max_radius_px: float = 2.0) -> Mask:
    """``hull_silhouette`` drawn on a smaller canvas where the voxel disc at the hull's centre has at most
    ``max_radius_px`` pixels, then enlarged (nearest): what large discs cost is the
    dilations that draw them, and a caller that clips the result to an outline of its own
    does not need the silhouette's outline to the pixel."""
    if not hull.surface.any():
        return np.zeros((camera.height, camera.width), bool)
    # The disc size at the hull's centre sets the canvas (``hull_silhouette`` projects the
    # voxels themselves).
    _, depth = camera.project(hull.centers.mean(axis=0, keepdims=True))
    if not depth[0] > 0:
        return hull_silhouette(hull, camera)
    radius = 0.5 * np.sqrt(3.0) * hull.voxel_size * camera.focal_px / float(depth[0])
    factor = int(np.clip(np.floor(radius / max_radius_px), 1, 8))
    if factor == 1:
        return hull_silhouette(hull, camera)
    small = hull_silhouette(hull, camera.scaled(1.0 / factor))
    big = cv2.resize(
        small.view(np.uint8), (camera.width, camera.height), interpolation=cv2.INTER_NEAREST
    )
    return np.asarray(big, bool)


#: The tolerant hull of ``hull_rescued`` is carved with voxels 2^_RESCUE_LEVELS times the
#: exact hull's: it only has to tell objects apart and count the cameras that see them.
_RESCUE_LEVELS = 1
_RESCUE_COARSEN = 1 << _RESCUE_LEVELS


@dataclass(frozen=True, kw_only=True)
class Rescue:
    """What ``hull_rescued`` brought back."""

    objects: int = 0
    """Objects of the tolerant hull added to the hull."""
    voxels: int = 0
    """Finest voxels they added."""
    dissenters: tuple[int, ...] = ()
    """Per rescued object, the camera whose mask had carved it away."""


def hull_rescued(
    hull: VisualHull,
    cameras: Sequence[Camera],
    masks: Sequence[Mask | None],
    model_masks: Sequence[Mask | None],
    unsettled: Sequence[Mask | None],
    config: HullConfig,
    *,
    occluders: Sequence[DepthMap | None] | None = None,
    distances: SilhouetteDistances | None = None,
    min_lost_fraction: float = 0.002,
    min_support: float = 0.8,
    min_unsettled: float = 0.5,
) -> tuple[VisualHull, list[Mask | None], Rescue]:
    """The hull and masks with the objects back that one camera's uncertain model carved away.

    A background model learned from the stream may hold an actor who stood in one camera's
    view while it learned: that camera then cannot see the actor, its mask carves the actor
    out of the exact hull, and ``hull_consistent_masks`` removes the actor from every other
    camera's mask too (6-camera hd4 rig: one actor lost in 16 of 100 tasks). Here a tolerant
    hull (one camera may disagree, at least 3 agree; voxels twice the exact hull's, no
    phantom removal) is carved from ``model_masks``; each of its objects that holds no
    exact-hull voxel is brought back when

    * every camera that sees it but one puts at least ``min_support`` of its voxels in its
      mask (at least 3 cameras), and
    * the one camera that carves it does so mostly (``min_unsettled`` of the voxels it puts
      outside its mask) at its model's ``unsettled`` pixels: where something moved while the
      model learned, so the model may hold the object.

    A rescued object joins the hull (new object ids, by decreasing size with the others) and
    gives back, in every camera, the pixels of its model mask that its projection covers. The
    tolerant hull is only carved when at least two cameras lost ``min_lost_fraction`` of their
    pixels to the hull consistency (``model_masks`` against ``masks``), never with a hull that
    is already tolerant (``config.max_missing`` > 0) or fewer than 4 cameras with a mask. A
    phantom of the tolerant hull would need the one camera that carves it to be unsettled
    there as well; the exact hull's own objects are never changed.
    """
    cams = list(cameras)
    _check_masks(cams, masks)
    _check_masks(cams, model_masks)
    _check_masks(cams, unsettled, "unsettled map")
    out = [None if m is None else np.asarray(m, bool) for m in masks]
    nothing = (hull, out, Rescue())
    if config.max_missing > 0 or sum(m is not None for m in model_masks) < 4:
        return nothing
    if not any(u is not None and bool(np.any(u)) for u in unsettled):
        return nothing
    losing = 0
    for m, mm, cam in zip(out, model_masks, cams, strict=True):
        if m is not None and mm is not None:
            lost = int(np.count_nonzero(np.asarray(mm, bool) & ~m))
            losing += lost >= min_lost_fraction * cam.width * cam.height
    if losing < 2:
        return nothing
    tolerant_cfg = dataclasses.replace(
        config,
        max_missing=1,
        min_views=max(config.min_views, 3),  # what a rescue needs; fewer merge phantoms in
        remove_phantoms=False,  # a phantom has no camera that carves it at unsettled pixels
        voxel_size=_RESCUE_COARSEN * hull.voxel_size,
        max_voxels=config.max_voxels // _RESCUE_COARSEN**3,
    )
    tolerant = visual_hull(
        cams, model_masks, tolerant_cfg, occluders=occluders, distances=distances
    )
    if tolerant.num_voxels == 0:
        return nothing
    in_exact = hull.contains(tolerant.centers)
    dists = silhouette_distances(model_masks) if distances is None else list(distances)
    walls = _occluder_maps(occluders, len(cams))
    half_diag = 0.5 * np.sqrt(3.0) * tolerant.voxel_size
    tol = config.tolerance_px + 0.71
    rescued: list[int] = []
    dissenters: list[int] = []
    for k in range(1, tolerant.num_objects + 1):
        sel = tolerant.labels == k
        if in_exact[sel].any():
            continue  # the exact hull has this object (the fill's business)
        pts = tolerant.centers[sel]
        support: list[tuple[int, float, float]] = []  # (camera, share in mask, share unsettled)
        for c, (cam, dist, wall, unset) in enumerate(
            zip(cams, dists, walls, unsettled, strict=True)
        ):
            if dist is None:
                continue
            uv, depth = cam.project(pts)
            vis = (depth > half_diag) & cam.in_image(uv)
            u = np.clip(np.rint(np.where(vis, uv[:, 0], 0)), 0, cam.width - 1).astype(np.intp)
            v = np.clip(np.rint(np.where(vis, uv[:, 1], 0)), 0, cam.height - 1).astype(np.intp)
            if wall is not None:
                vis &= ~(depth - half_diag > wall[v, u])
            if vis.sum() < 0.5 * len(pts):
                continue  # this camera does not see the object
            u, v = u[vis], v[vis]
            radius = half_diag * cam.focal_px * _FOOTPRINT_SLACK / depth[vis]
            inside = dist[0][v, u] <= radius + tol
            outside = ~inside
            unsure = (
                float(np.asarray(unset, bool)[v[outside], u[outside]].mean())
                if unset is not None and outside.any()
                else 0.0
            )
            support.append((c, float(inside.mean()), unsure))
        against = [s for s in support if s[1] < min_support]
        logger.debug(
            "rescue: tolerant object %d (%d voxels), (camera, in mask, unsettled): %s",
            k,
            len(pts),
            [(c, round(a, 2), round(b, 2)) for c, a, b in support],
        )
        if len(against) != 1 or len(support) - 1 < 3:
            continue
        c, _, unsure = against[0]
        if unsure < min_unsettled:
            continue
        rescued.append(k)
        dissenters.append(c)
    if not rescued:
        return nothing
    # The rescued objects' voxels on the exact hull's (finer) grid.
    sel = np.isin(tolerant.labels, rescued)
    corners = tolerant.origin + tolerant.indices[sel] * tolerant.voxel_size
    offsets = (_expand(np.zeros((1, 3), np.int64), _RESCUE_LEVELS) + 0.5) * hull.voxel_size
    children = (corners[:, None, :] + offsets[None]).reshape(-1, 3)
    new_idx = np.floor((children - hull.origin) / hull.voxel_size).astype(np.int64)
    new_lab = np.repeat(tolerant.labels[sel], len(offsets))
    _, first = np.unique(_pack(new_idx), return_index=True)
    keep = (
        _lookup(_pack(hull.indices), new_idx[first]) < 0
        if hull.num_voxels
        else np.ones(len(first), bool)
    )
    new_idx, new_lab = new_idx[first[keep]], new_lab[first[keep]]
    lut = np.zeros(tolerant.num_objects + 1, np.int32)
    lut[rescued] = hull.num_objects + 1 + np.arange(len(rescued))
    new_lab = lut[new_lab]
    idx = np.concatenate([hull.indices, new_idx])
    labels = np.concatenate([hull.labels, new_lab])
    order = np.argsort(_pack(idx), kind="stable")
    idx, labels = idx[order], labels[order]
    surface, normals = _surface_normals(idx)
    merged = dataclasses.replace(
        hull,
        indices=idx,
        labels=labels,
        surface=surface,
        normals=normals,
        status="ok" if hull.status == "empty" else hull.status,
    )
    merged = _without_objects(merged, [])  # renumber by decreasing size
    added = dataclasses.replace(
        tolerant, surface=tolerant.surface & sel, labels=np.where(sel, 1, 0).astype(np.int32)
    )
    for c, cam in enumerate(cams):
        mask, model = out[c], model_masks[c]
        if mask is not None and model is not None:
            out[c] = mask | (np.asarray(model, bool) & _coarse_silhouette(added, cam))
    logger.debug(
        "visual hull: %d object(s) carved away by one camera's unsettled model brought back "
        "(cameras %s, %d voxels)",
        len(rescued),
        dissenters,
        len(new_idx),
    )
    return (
        merged,
        out,
        Rescue(objects=len(rescued), voxels=len(new_idx), dissenters=tuple(dissenters)),
    )
