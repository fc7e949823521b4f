"""SIFT features of the views, extracted in parallel.

Choices (measured on utrecht4cam 644x486 and 1920x1080 images, see the package docstring):

* OpenCV SIFT with a lower contrast threshold than OpenCV's default (0.02 instead of 0.04):
  real rooms have weakly textured walls and floors; twice as many keypoints on utrecht4cam.
* Large views are downscaled to ``feature_max_size_px`` before detection: OpenCV's SIFT
  upsamples the image 2x internally, so 1920x1080 costs ~1 s per image against ~0.07 s at
  960x540, for a similar count of keypoints that survive matching.
* RootSIFT (Hellinger) descriptors, unit L2 norm: squared distances are ``2 - 2 a.b``, so
  descriptor distances of many candidate pairs are a dot product.
* SIFT returns the same location several times with different orientations; ``location``
  maps each keypoint to a unique location so that matching and tracks treat them as one point.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.sparse.config import DEFAULT_CONFIG, SparseConfig
from edgerecon.types import Points2D
from edgerecon.views import View

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True, eq=False)
class Features:
    """Keypoints and descriptors of one view."""

    points2D: Points2D
    """(N, 2) float64 keypoint positions in the view's pixels."""
    descriptors: NDArray[np.float32]
    """(N, 128) float32 descriptors with unit L2 norm."""
    sizes_px: NDArray[np.float32]
    """(N,) keypoint diameters in the view's pixels."""
    location: NDArray[np.int64]
    """(N,) index of the keypoint's unique location (keypoints that SIFT returns at the same
    position with different orientations share one)."""
    location_points2D: Points2D
    """(L, 2) float64 position of each unique location."""

    @property
    def num_locations(self) -> int:
        return int(self.location_points2D.shape[0])

    def __len__(self) -> int:
        return int(self.points2D.shape[0])

    @classmethod
    def empty(cls) -> Features:
        return cls(
            points2D=np.zeros((0, 2)),
            descriptors=np.zeros((0, 128), np.float32),
            sizes_px=np.zeros(0, np.float32),
            location=np.zeros(0, np.int64),
            location_points2D=np.zeros((0, 2)),
        )


def _detector(config: SparseConfig) -> cv2.Feature2D:
    return cv2.SIFT_create(  # type: ignore[attr-defined]
        nfeatures=config.max_features,
        contrastThreshold=config.contrast_threshold,
        edgeThreshold=config.edge_threshold,
    )


def extract_features(view: View, config: SparseConfig = DEFAULT_CONFIG) -> Features:
    """SIFT keypoints of one view, restricted to its mask when it has one."""
    image = view.image
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    h, w = gray.shape[:2]
    mask: NDArray[np.uint8] | None = None
    if view.mask is not None:
        mask = (view.mask.astype(np.uint8) * 255).astype(np.uint8)
    if mask is not None and not mask.any():
        return Features.empty()
    scale = 1.0
    longest = max(w, h)
    if config.feature_max_size_px and longest > config.feature_max_size_px:
        scale = config.feature_max_size_px / longest
        size = (max(1, round(w * scale)), max(1, round(h * scale)))
        gray = cv2.resize(gray, size, interpolation=cv2.INTER_AREA)
        if mask is not None:
            mask = cv2.resize(mask, size, interpolation=cv2.INTER_NEAREST).astype(np.uint8)
    keypoints, desc = _detector(config).detectAndCompute(gray, mask)
    if not keypoints or desc is None:
        return Features.empty()
    pts = np.array([k.pt for k in keypoints], dtype=np.float64)
    sizes = np.array([k.size for k in keypoints], dtype=np.float32)
    if scale != 1.0:
        # Pixel centres: x_full = (x_small + 0.5) * (W / w) - 0.5, per axis.
        sx, sy = w / gray.shape[1], h / gray.shape[0]
        pts = (pts + 0.5) * [sx, sy] - 0.5
        sizes = sizes * np.float32(0.5 * (sx + sy))
    desc = desc.astype(np.float32, copy=False)
    if config.root_sift:
        desc = np.sqrt(desc / (desc.sum(axis=1, keepdims=True) + 1e-12))
    desc /= np.linalg.norm(desc, axis=1, keepdims=True) + 1e-12
    unique_pts, location = np.unique(pts, axis=0, return_inverse=True)
    location = location.reshape(-1).astype(np.int64)
    return Features(
        points2D=pts,
        descriptors=np.ascontiguousarray(desc, dtype=np.float32),
        sizes_px=sizes,
        location=location,
        location_points2D=unique_pts,
    )


def extract_all(views: Sequence[View], config: SparseConfig = DEFAULT_CONFIG) -> list[Features]:
    """Features of every view, computed by ``config.num_threads`` threads."""
    if config.num_threads <= 1 or len(views) <= 1:
        return [extract_features(v, config) for v in views]
    with ThreadPoolExecutor(max_workers=config.num_threads) as pool:
        return list(pool.map(lambda v: extract_features(v, config), views))
