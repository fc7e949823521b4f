"""Precision filters of the dense stage: tests that separate good depths from streaks and
specks before (depth maps) and after (fused cloud) fusion. Each has a ``DenseConfig``
option; the free-space test (``max_conflict_share``) and the depth-edge test
(``depth_edge_rel``) are on by default, the others off (they cost recall or time for little
precision); ``benchmarks/bench_precision.py`` measures what each costs and buys (precision,
recall, CPU seconds).

* ``depth_edge_mask``: pixels on the far side of strong depth discontinuities (the windows
  there mix a near and a far surface; their depths bridge the two or fatten the near one).
* ``grazing_mask``: points whose surface is seen nearly edge-on by their view.
* ``consistency_keep``: support scaled with the views that could have confirmed a depth,
  free-space conflicts and the photometric score of weakly supported depths.
* ``outlier_mask``: statistical outliers of the fused cloud (mean k-NN distance).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from edgerecon.dense.config import DenseConfig
from edgerecon.dense.fusion import ViewPoints
from edgerecon.types import DepthMap


def depth_edge_mask(depth: DepthMap, rel: float) -> NDArray[np.bool_]:
    """(H, W) True at depths with a valid 8-neighbour nearer by more than ``rel`` times the
    depth: the far side of a depth discontinuity and the steps of streaks that bridge one
    (windows there mix the near surface in and fatten it); the near side's rim is kept."""
    valid = depth > 0
    k = np.ones((3, 3), np.uint8)
    dmin = cv2.erode(np.where(valid, depth, np.float32(np.inf)).astype(np.float32), k)
    return valid & (depth - dmin > rel * depth)


def grazing_mask(vp: ViewPoints, center: NDArray[np.float64], max_deg: float) -> NDArray[np.bool_]:
    """(N,) True where the angle between a point's normal and its ray to the camera exceeds
    ``max_deg``."""
    ray = center[None, :] - vp.points3D
    ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-12)
    cos = np.abs(np.einsum("ij,ij->i", ray, vp.normals.astype(np.float64)))
    return cos < math.cos(math.radians(max_deg))


def consistency_keep(
    depth: DepthMap,
    support: NDArray[np.int16],
    conflicts: NDArray[np.int16],
    candidates: NDArray[np.int16],
    score: NDArray[np.float32],
    config: DenseConfig,
) -> NDArray[np.bool_]:
    """(H, W) depths kept by the consistency tests of ``config``: ``min_consistent_views``;
    ``consistent_view_share`` of the views that could have confirmed the depth (its place is
    in their image and not behind what they measured); ``max_conflict_share`` of agreeing +
    contradicting views; ``min_weak_ncc`` for depths with fewer than two supporting views."""
    keep = (depth > 0) & (support >= config.min_consistent_views)
    s = support.astype(np.float32)
    c = conflicts.astype(np.float32)
    if config.consistent_view_share > 0:
        need = np.ceil(config.consistent_view_share * candidates.astype(np.float32) - 1e-6)
        keep &= s >= np.maximum(need, config.min_consistent_views)
    if config.max_conflict_share < 1:
        keep &= c <= config.max_conflict_share * (s + c)
    if config.min_weak_ncc > -1:
        keep &= (support >= 2) | (score >= config.min_weak_ncc)
    return keep


def outlier_mask(
    points3D: NDArray[np.float64], k: int, std_ratio: float, num_threads: int = 1
) -> NDArray[np.bool_]:
    """(N,) True at statistical outliers: mean distance to the ``k`` nearest neighbours above
    the cloud's mean of that distance plus ``std_ratio`` standard deviations."""
    n = len(points3D)
    if n <= k:
        return np.zeros(n, bool)
    d, _ = cKDTree(points3D).query(points3D, k=k + 1, workers=num_threads)
    m = d[:, 1:].mean(axis=1)
    return m > m.mean() + std_ratio * m.std()
