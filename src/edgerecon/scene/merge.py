"""Merge a task's foreground cloud with the newest background cloud.

Both clouds are in the rig's frame (static calibrated cameras: no registration, no drift). The
foreground wins where both claim space: background points within ``clear_radius`` of a
foreground point, or inside the current visual hull, are dropped, so an actor who was part of
an older background reconstruction (or a background point behind a moving actor) does not
leave a ghost next to its current position.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from edgerecon.io.ply import write_ply
from edgerecon.scene.hull import VisualHull
from edgerecon.types import BACKGROUND_LABEL, UNKNOWN_LABEL, PointCloud

logger = logging.getLogger(__name__)

#: Name of the per-point attribute holding the background version a point came from.
BG_VERSION = "bg_version"


@dataclass(frozen=True, kw_only=True)
class MergeConfig:
    """Parameters of the foreground/background merge."""

    clear_radius: float | None = None
    """Background points closer than this (rig units) to a foreground point are dropped;
    None = ``clear_fraction`` x the rig's scale passed to ``merge_clouds`` (or 0 without)."""
    clear_fraction: float = 0.01
    """``clear_radius`` relative to the rig's scale when ``clear_radius`` is None."""

    def __post_init__(self) -> None:
        if self.clear_radius is not None and self.clear_radius < 0:
            raise ValueError(f"MergeConfig.clear_radius must be >= 0, got {self.clear_radius}")
        if self.clear_fraction < 0:
            raise ValueError(f"MergeConfig.clear_fraction must be >= 0, got {self.clear_fraction}")


def merge_clouds(
    foreground: PointCloud,
    background: PointCloud,
    *,
    bg_version: int,
    config: MergeConfig | None = None,
    scene_scale: float | None = None,
    hull: VisualHull | None = None,
) -> PointCloud:
    """One labelled cloud: the foreground (labels >= 1 kept; unlabelled or non-positive
    labels become object 1) and the background (label 0) minus the points the foreground
    overrides (``overridden``). ``attributes["bg_version"]`` (int32) is the background version
    each point comes from: the background cloud's own ``bg_version`` attribute when it has
    one, else ``bg_version``; foreground points get ``bg_version`` (the background they were
    merged with)."""
    dropped = overridden(
        foreground.points3D,
        background.points3D,
        merge_radius(config, scene_scale),
        hull,
    )
    return compose(foreground, background, bg_version=bg_version, dropped=dropped)


def merge_radius(config: MergeConfig | None, scene_scale: float | None) -> float:
    """The clearing radius of ``config`` (rig units; 0 without a radius or a scale)."""
    config = config or MergeConfig()
    if config.clear_radius is not None:
        return config.clear_radius
    return config.clear_fraction * scene_scale if scene_scale is not None else 0.0


def overridden(
    fg_points: NDArray[np.float64],
    bg_points: NDArray[np.float64],
    radius: float,
    hull: VisualHull | None = None,
) -> NDArray[np.int64]:
    """Sorted indices of the background points the foreground overrides: closer than
    ``radius`` to a foreground point, or inside ``hull``."""
    keep = np.ones(len(bg_points), bool)
    # Only the background points in the box of the foreground (grown by the radius) or of
    # the hull can be overridden: the rest of a room-sized background (a million points
    # on an 8-camera HD rig) is not searched, on the critical path of every task.
    if len(bg_points) and len(fg_points) and radius > 0:
        P = np.asarray(fg_points)
        idx = _in_box(bg_points, P.min(axis=0) - radius, P.max(axis=0) + radius)
        if len(idx):
            d, _ = cKDTree(P).query(bg_points[idx], k=1, distance_upper_bound=radius)
            keep[idx[np.isfinite(d)]] = False
    if hull is not None and len(bg_points) and hull.num_voxels:
        # The occupied voxels' box, half a voxel wider (points on its faces round either way).
        lo = hull.origin + (hull.indices.min(axis=0) - 0.5) * hull.voxel_size
        hi = hull.origin + (hull.indices.max(axis=0) + 1.5) * hull.voxel_size
        idx = _in_box(bg_points, lo, hi)
        keep[idx[hull.contains(bg_points[idx])]] = False
    return np.flatnonzero(~keep).astype(np.int64)


def foreground_part(foreground: PointCloud, bg_version: int) -> PointCloud:
    """The foreground as a merged cloud holds it: labels >= 1 kept (unlabelled or
    non-positive labels become object 1) and ``bg_version`` per point."""
    labels = (
        np.ones(len(foreground), np.int32)
        if foreground.labels is None
        else np.where(foreground.labels >= 1, foreground.labels, 1).astype(np.int32)
    )
    return _with(foreground, labels, np.full(len(foreground), bg_version, np.int32))


def compose(
    foreground: PointCloud,
    background: PointCloud,
    *,
    bg_version: int,
    dropped: NDArray[np.int64],
) -> PointCloud:
    """The merged cloud: ``foreground_part`` first, then the background (label 0) without the
    points at ``dropped`` (``overridden``). A reader of a run folder rebuilds a task's merged
    cloud with it from the task's foreground, its background version and ``dropped``."""
    fg = foreground_part(foreground, bg_version)
    bg_ver = background.attributes.get(BG_VERSION)
    bg_ver = (
        np.full(len(background), bg_version, np.int32)
        if bg_ver is None
        else np.asarray(bg_ver).astype(np.int32)
    )
    bg = _with(background, np.full(len(background), BACKGROUND_LABEL, np.int32), bg_ver)
    keep = np.ones(len(bg), bool)
    keep[np.asarray(dropped, np.int64)] = False
    if not keep.all():
        logger.debug("merge: %d background points overridden by the foreground", len(dropped))
    return PointCloud.concatenate([fg, bg.select(keep)])


def _in_box(points3D: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Indices of the points inside the axis-aligned box [lo, hi] (boundary included)."""
    P = np.asarray(points3D)
    inside = (P[:, 0] >= lo[0]) & (P[:, 0] <= hi[0])
    for k in (1, 2):
        inside &= (P[:, k] >= lo[k]) & (P[:, k] <= hi[k])
    return np.flatnonzero(inside)


def _with(cloud: PointCloud, labels: np.ndarray, version: np.ndarray) -> PointCloud:
    attrs = dict(cloud.attributes)
    attrs[BG_VERSION] = version
    return PointCloud(
        points3D=cloud.points3D,
        colors=cloud.colors,
        normals=cloud.normals,
        labels=labels,
        confidence=cloud.confidence,
        attributes=attrs,
    )


def split_merged(merged: PointCloud) -> tuple[PointCloud, PointCloud]:
    """(foreground, background) parts of a merged cloud (unknown labels go to neither)."""
    if merged.labels is None:
        raise ValueError("split_merged: the cloud has no labels")
    return merged.select(merged.labels >= 1), merged.select(merged.labels == BACKGROUND_LABEL)


def write_merged(
    out_dir: str | os.PathLike[str], merged: PointCloud, **ply: Any
) -> dict[str, Path]:
    """Write ``merged.ply``, ``fg.ply`` and ``bg.ply`` (atomically) into ``out_dir``;
    ``ply`` goes to ``write_ply`` (``unit=``, ``up=``)."""
    out = Path(out_dir)
    fg, bg = split_merged(merged)
    n_unknown = (
        int(np.count_nonzero(merged.labels == UNKNOWN_LABEL)) if merged.labels is not None else 0
    )
    if n_unknown:
        logger.warning(
            "write_merged: %d points with unknown labels are only in merged.ply", n_unknown
        )
    return {
        "merged": write_ply(out / "merged.ply", merged, **ply),
        "fg": write_ply(out / "fg.ply", fg, **ply),
        "bg": write_ply(out / "bg.ply", bg, **ply),
    }
