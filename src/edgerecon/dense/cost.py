"""Photo-consistency: windowed normalised cross-correlation (NCC) between a reference image
and source images resampled onto it, and its aggregation over several sources.

Every function works on whole images with OpenCV box filters (a few SIMD passes per
hypothesis), never per pixel in Python. Grey images are float32 with the mean grey level
subtracted (values in about [-128, 128]) so that ``E[x^2] - E[x]^2`` keeps its precision in
float32.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

F32 = NDArray[np.float32]


def as_f32(a: NDArray[Any]) -> F32:
    """``a`` as float32 (no copy when it already is; also types OpenCV's results)."""
    return np.asarray(a, dtype=np.float32)


#: Grey level subtracted from images before matching.
GREY_OFFSET = 128.0
#: Variance floor (grey levels squared) that keeps NCC finite on flat windows.
_VAR_EPS = 1e-3


def to_grey(image: NDArray[np.uint8]) -> F32:
    """BGR (or grey) uint8 image -> float32 grey with ``GREY_OFFSET`` subtracted."""
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    return grey.astype(np.float32) - np.float32(GREY_OFFSET)


@dataclass(frozen=True, eq=False)
class WindowStats:
    """Window statistics of a reference image, computed once per image and radius."""

    image: F32
    """(H, W) reference grey image."""
    mean: F32
    """(H, W) window means."""
    std: F32
    """(H, W) window standard deviations (grey levels)."""
    radius: int
    """Window half-size in pixels."""


def window_stats(image: F32, radius: int) -> WindowStats:
    """Means and standard deviations of the ``(2 radius + 1)^2`` windows of ``image``."""
    k = (2 * radius + 1, 2 * radius + 1)
    mean = as_f32(cv2.boxFilter(image, -1, k))
    sq = as_f32(cv2.boxFilter(image * image, -1, k))
    var = np.maximum(sq - mean * mean, 0.0)
    return WindowStats(image=image, mean=mean, std=np.sqrt(var), radius=radius)


def ncc(ref: WindowStats, warped: F32) -> F32:
    """(H, W) NCC between the reference windows and the same windows of ``warped`` (a source
    image resampled onto the reference grid, NaN where it had no data). Windows that touch a
    NaN sample are NaN."""
    invalid = np.isnan(warped)
    j = np.nan_to_num(warped, copy=True, nan=0.0)
    k = (2 * ref.radius + 1, 2 * ref.radius + 1)
    stack = cv2.merge([j, j * j, ref.image * j, invalid.astype(np.float32)])
    m = cv2.boxFilter(stack, -1, k)
    mean_j = m[..., 0]
    var_j = np.maximum(m[..., 1] - mean_j * mean_j, 0.0)
    cov = m[..., 2] - ref.mean * mean_j
    denom = np.sqrt((ref.std * ref.std + _VAR_EPS) * (var_j + _VAR_EPS))
    out: F32 = (cov / denom).astype(np.float32, copy=False)
    out[m[..., 3] > 1e-4] = np.nan
    return out


def aggregate(nccs: list[F32], top_k: int, top_gap: float = math.inf) -> F32:
    """Multi-view score: per pixel, the mean of the ``top_k`` best source NCCs (fewer where
    fewer sources have data), each counted as at least the best one's minus ``top_gap``;
    -1 where no source has data.

    Taking the best sources rather than all of them keeps surfaces that are occluded in some
    source views (the standard occlusion heuristic of multi-view stereo). The gap bounds what
    a source that does not see the pixel (an occlusion) can take off the score, while a second
    source that does see it still confirms the depth (the reference NumPy version of
    ``kernels._scores``' aggregation)."""
    if not nccs:
        raise ValueError("aggregate needs at least one NCC map")
    if len(nccs) == 1:
        return np.nan_to_num(nccs[0], nan=-1.0)
    k = min(top_k, len(nccs))
    # Missing values sort last; an odd-even transposition network sorts the few maps
    # element-wise in descending order (much faster than np.sort / np.partition on axis 0).
    vals = [np.where(np.isnan(x), -np.inf, x).astype(np.float32) for x in nccs]
    n = len(vals)
    if k < n:
        for rnd in range(n):
            for i in range(rnd % 2, n - 1, 2):
                hi = np.maximum(vals[i], vals[i + 1])
                vals[i + 1] = np.minimum(vals[i], vals[i + 1])
                vals[i] = hi
    total = np.zeros_like(vals[0])
    count = np.zeros_like(vals[0])
    floor = vals[0] - np.float32(top_gap)
    for x in vals[:k]:
        good = np.isfinite(x)
        total += np.where(good, np.maximum(x, floor), 0.0)
        count += good
    return np.where(count > 0, total / np.maximum(count, 1.0), -1.0).astype(np.float32)
