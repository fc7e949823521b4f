"""Sparse foreground/background split: label 3D points from their projections into the masks.

Each camera with a mask votes for every point it observes (``visibility``): foreground when the
point projects onto (or within ``tolerance_px`` of) its foreground, background otherwise.
Cameras that see the point in their image without observing it (occlusion is unknown for them)
vote with a smaller weight, which breaks the ties of two-view points. A point is foreground
when the foreground weight exceeds the background weight, so one camera's bad mask is outvoted
by the others (ties, possible only without tie-breakers, go to the foreground: a stray point
in the foreground costs less than a hole in an actor).

Object ids are made consistent across cameras: each (camera, per-image object) is a node, two
nodes are linked when at least ``min_shared_points`` foreground points land in both, and the
connected groups are the global objects (1..K by decreasing number of points).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from edgerecon.geometry.camera import Camera
from edgerecon.scene._kernels import camera_votes, mode_component, shared_points
from edgerecon.types import (
    BACKGROUND_LABEL,
    UNKNOWN_LABEL,
    DataError,
    Points3D,
    StageTimings,
)
from edgerecon.views import mask_scale

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class SplitConfig:
    """Parameters of the sparse foreground/background split."""

    tolerance_px: int = 2
    """A projection within this many frame pixels of a camera's foreground counts as foreground
    (silhouettes and sparse points are both uncertain by a pixel or two)."""
    unobserving_weight: float = 0.5
    """Vote weight of a camera that sees a point in its image without observing it (0 = only
    observing cameras vote). Keep it below 1 so observing cameras dominate."""
    min_shared_points: int = 3
    """Per-image objects of two cameras are the same object when at least this many
    foreground points observed by both land in them ..."""
    min_shared_fraction: float = 0.1
    """... and at least this share of the smaller object's points."""

    def __post_init__(self) -> None:
        if self.tolerance_px < 0:
            raise ValueError(f"SplitConfig.tolerance_px must be >= 0, got {self.tolerance_px}")
        if not 0.0 <= self.unobserving_weight <= 1.0:
            raise ValueError(
                f"SplitConfig.unobserving_weight must be in [0, 1], got {self.unobserving_weight}"
            )
        if not 0.0 <= self.min_shared_fraction <= 1.0:
            raise ValueError(
                f"SplitConfig.min_shared_fraction must be in [0, 1], got {self.min_shared_fraction}"
            )
        if self.min_shared_points < 1:
            raise ValueError(
                f"SplitConfig.min_shared_points must be >= 1, got {self.min_shared_points}"
            )


@dataclass(frozen=True, kw_only=True, eq=False)
class SplitResult:
    """Labels of sparse points: background, foreground object, or unknown."""

    labels: NDArray[np.int32]
    """(N,) 0 = background, k >= 1 = object k, -1 = unknown (no camera with a mask sees it)."""
    fg_votes: NDArray[np.float32]
    """(N,) total weight of the cameras that put the point in their foreground."""
    bg_votes: NDArray[np.float32]
    """(N,) total weight of the cameras that put it in their background."""
    object_nodes: dict[tuple[int, int], int] = field(default_factory=dict)
    """(camera id, per-image object id) -> global object id."""
    timings: StageTimings = field(default_factory=StageTimings)
    """Seconds per step."""

    @property
    def foreground(self) -> NDArray[np.bool_]:
        return self.labels > 0

    @property
    def background(self) -> NDArray[np.bool_]:
        return self.labels == BACKGROUND_LABEL

    @property
    def num_objects(self) -> int:
        return int(self.labels.max()) if self.labels.size and self.labels.max() > 0 else 0

    def counts(self) -> dict[str, int]:
        return {
            "foreground": int(np.count_nonzero(self.foreground)),
            "background": int(np.count_nonzero(self.background)),
            "unknown": int(np.count_nonzero(self.labels == UNKNOWN_LABEL)),
        }


def _as_visibility(
    visibility: NDArray[np.bool_] | Sequence[Sequence[int]], n: int, num_cameras: int
) -> NDArray[np.bool_]:
    if isinstance(visibility, np.ndarray) and visibility.ndim == 2:
        vis = visibility.astype(bool, copy=False)
        if vis.shape != (n, num_cameras):
            raise DataError(
                f"visibility matrix is {vis.shape}, expected ({n}, {num_cameras}) "
                "(points x rig cameras)"
            )
        return vis
    rows = list(visibility)
    if len(rows) != n:
        raise DataError(f"visibility lists {len(rows)} points, expected {n}")
    vis = np.zeros((n, num_cameras), bool)
    for i, cams in enumerate(rows):
        ids = np.asarray(list(cams), dtype=np.int64)
        if ids.size and (ids.min() < 0 or ids.max() >= num_cameras):
            raise DataError(
                f"visibility of point {i} names camera ids outside 0..{num_cameras - 1}"
            )
        vis[i, ids] = True
    return vis


def _label_image(mask: NDArray[np.generic], cam: Camera) -> NDArray[np.uint8]:
    m = np.asarray(mask)
    if m.ndim != 2:
        raise DataError(f"camera {cam.name!r}: a mask must be a (H, W) image, got {m.shape}")
    mask_scale(m, cam)  # any resolution with the frames' aspect ratio
    if m.dtype == bool:
        return m.astype(np.uint8)
    if m.min() < 0 or m.max() > 255:
        raise DataError(f"camera {cam.name!r}: object ids in a label mask must be in 0..255")
    return m.astype(np.uint8)


def split_sparse(
    points3D: Points3D,
    visibility: NDArray[np.bool_] | Sequence[Sequence[int]],
    cameras: Sequence[Camera],
    masks: Sequence[NDArray[np.generic] | None],
    config: SplitConfig | None = None,
) -> SplitResult:
    """Label sparse points foreground (with a global object id) or background.

    ``points3D`` (N, 3) in rig units; ``visibility`` the (N, C) boolean point-camera matrix
    over the rig's camera ids (or, per point, the list of camera ids observing it);
    ``cameras`` the rig's cameras (full resolution, distortion applied by ``Camera.project``);
    ``masks[c]`` camera c's (H, W) foreground: a boolean mask, or an integer label image
    (0 = background, k = per-image object k, as ``ObjectSegmentation.labels``), or None when
    camera c has no mask (it does not vote).
    """
    config = config or SplitConfig()
    timings = StageTimings()
    pts = np.asarray(points3D, dtype=np.float64).reshape(-1, 3)
    n = len(pts)
    cams = list(cameras)
    if len(masks) != len(cams):
        raise DataError(f"split_sparse: {len(masks)} masks for {len(cams)} cameras")
    vis = _as_visibility(visibility, n, len(cams))
    fg_w = np.zeros(n, np.float32)
    bg_w = np.zeros(n, np.float32)
    # Per camera: the per-image object id each point lands on (0 = background / not voting).
    local = np.zeros((n, len(cams)), np.int32)
    local_any = np.zeros((n, len(cams)), np.int32)
    with timings.stage("split_votes"):
        for c, (cam, mask) in enumerate(zip(cams, masks, strict=True)):
            if mask is None or n == 0:
                continue
            lab = _label_image(mask, cam)
            if config.tolerance_px > 0 and lab.any():
                r = max(1, round(config.tolerance_px * lab.shape[1] / cam.width))
                lab = np.asarray(
                    cv2.dilate(
                        lab, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
                    ),
                    np.uint8,
                )
            uv, depth = cam.project(pts)
            # An observing camera whose projection falls outside its image still votes
            # background-free: it cannot say anything about the point. Object ids come only
            # from cameras that observe the point (an occluded point lands on whatever
            # object hides it).
            camera_votes(
                c,
                uv,
                depth,
                cam.width,
                cam.height,
                lab.shape[1] / cam.width,
                lab.shape[0] / cam.height,
                lab.shape[1] != cam.width,  # a mask at a reduced resolution
                np.ascontiguousarray(lab, np.uint8),
                vis,
                np.float32(config.unobserving_weight),
                fg_w,
                bg_w,
                local,
                local_any,
            )
    labels = np.full(n, UNKNOWN_LABEL, np.int32)
    voted = (fg_w + bg_w) > 0
    is_fg = voted & (fg_w >= bg_w)
    labels[voted & ~is_fg] = BACKGROUND_LABEL
    with timings.stage("split_objects"):
        obj, nodes = _associate_objects(
            local, local_any, is_fg, config.min_shared_points, config.min_shared_fraction
        )
    labels[is_fg] = obj[is_fg]
    return SplitResult(
        labels=labels, fg_votes=fg_w, bg_votes=bg_w, object_nodes=nodes, timings=timings
    )


def _associate_objects(
    local: NDArray[np.int32],
    local_any: NDArray[np.int32],
    is_fg: NDArray[np.bool_],
    min_shared: int,
    min_fraction: float,
) -> tuple[NDArray[np.int32], dict[tuple[int, int], int]]:
    """Global object id per point (meaningful where ``is_fg``) and the node -> id map.

    Nodes are linked through points observed in both (``local``: per-image ids from observing
    cameras); a point takes the component most of its observing nodes belong to, or, without
    any, most of its nodes in the other cameras that saw it in their foreground
    (``local_any``)."""
    n, num_cams = local.shape
    out = np.ones(n, np.int32)
    sel = np.flatnonzero(is_fg)
    if sel.size == 0:
        return out, {}
    loc = local[sel]
    max_id = int(local_any[sel].max())
    if max_id == 0:
        # Foreground only from tie-breaking (no camera with an id): one object.
        return out, {}
    # Node id = camera * (max_id + 1) + local id; node 'c*(max+1)' (local 0) is unused.
    stride = max_id + 1
    node = np.where(loc > 0, np.arange(num_cams)[None, :] * stride + loc, -1)
    num_nodes = num_cams * stride
    # Points each pair of nodes shares (nodes of a lower camera first, so a < b), and the
    # links strong enough to join two cameras' objects.
    shared = shared_points(np.ascontiguousarray(node, np.int64), num_nodes)
    size = np.bincount(node[node >= 0], minlength=num_nodes)
    present = np.flatnonzero(size)
    r, c = np.nonzero(shared)
    need = np.maximum(min_shared, min_fraction * np.minimum(size[r], size[c]))
    ok = shared[r, c] >= need
    graph = coo_matrix(
        (np.ones(int(np.count_nonzero(ok)), np.int8), (r[ok], c[ok])),
        shape=(num_nodes, num_nodes),
    )
    _, comp = connected_components(graph, directed=False)
    # Each point takes the component most of its nodes belong to; without any, most of
    # its nodes in the cameras that saw it in their foreground.
    comp = np.asarray(comp, np.int32)
    best = mode_component(node, comp)
    (lost,) = np.nonzero(best < 0)
    if len(lost):
        any_loc = local_any[sel[lost]]
        node_any = np.where(any_loc > 0, np.arange(num_cams)[None, :] * stride + any_loc, -1)
        best[lost] = mode_component(np.ascontiguousarray(node_any, np.int64), comp)
    # Rank components by the number of points they hold.
    has = best >= 0
    comps, counts = np.unique(best[has], return_counts=True)
    order = comps[np.argsort(-counts, kind="stable")]
    gid = {int(cid): k + 1 for k, cid in enumerate(order)}
    lut = np.zeros(len(comp) + 1, np.int32)
    for cid, k in gid.items():
        lut[cid] = k
    out[sel] = np.where(best >= 0, lut[np.maximum(best, 0)], 1)
    nodes = {}
    for nd in present:
        cid = int(comp[nd])
        if cid in gid:
            nodes[(int(nd // stride), int(nd % stride))] = gid[cid]
    return out, nodes
