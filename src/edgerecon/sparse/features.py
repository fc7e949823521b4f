"""SIFT features of the views, extracted in parallel.

Choices (measured on utrecht4cam 644x486 and 1920x1080 images, see the package docstring):

* OpenCV SIFT with a lower contrast threshold than OpenCV's default (0.02 instead of 0.04):
  real rooms have weakly textured walls and floors; twice as many keypoints on utrecht4cam.
* A feature budget (``min_features``): a view with fewer keypoints is detected again at a
  lower contrast threshold, a couple of steps at most. Low-contrast grey objects gave ~60-100
  keypoints per view at 0.02, too few sparse points for depth ranges from the scene.
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
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from edgerecon.sparse.config import DEFAULT_CONFIG, SparseConfig
from edgerecon.threads import thread_map
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


def _detector(config: SparseConfig, contrast_threshold: float) -> cv2.Feature2D:
    return cv2.SIFT_create(  # type: ignore[attr-defined]
        nfeatures=config.max_features,
        contrastThreshold=contrast_threshold,
        edgeThreshold=config.edge_threshold,
    )


#: Pixels kept around a mask's bounding box when detecting on it (SIFT's descriptor window
#: at the scales that matter).
_CROP_MARGIN_PX = 24


def _sift(
    gray: NDArray[Any], mask: NDArray[Any] | None, config: SparseConfig, contrast_threshold: float
) -> tuple[NDArray[np.float64], NDArray[np.float32], NDArray[np.float32]]:
    """Positions (N, 2), sizes (N,) and raw descriptors (N, 128) of SIFT on one image."""
    keypoints, desc = _detector(config, contrast_threshold).detectAndCompute(gray, mask)
    if not keypoints or desc is None:
        return np.zeros((0, 2)), np.zeros(0, np.float32), np.zeros((0, 128), np.float32)
    pts = np.array([k.pt for k in keypoints], dtype=np.float64)
    sizes = np.array([k.size for k in keypoints], dtype=np.float32)
    return pts, sizes, desc.astype(np.float32, copy=False)


def _resized(
    gray: NDArray[Any], mask: NDArray[Any] | None, sx: float, sy: float
) -> tuple[NDArray[Any], NDArray[Any] | None]:
    """The image shrunk by (sx, sy) <= 1 per axis, low-passed first along shrunk axes."""
    h, w = gray.shape[:2]
    size = (max(1, round(w * sx)), max(1, round(h * sy)))
    if sx < 1 and sy == 1:
        # Anti-aliasing along x only (ASIFT's 0.8 sqrt(t^2 - 1) for a tilt t).
        gray = cv2.GaussianBlur(gray, (0, 0), sigmaX=0.8 * np.sqrt(1 / sx**2 - 1), sigmaY=1e-6)
        gray = cv2.resize(gray, size, interpolation=cv2.INTER_LINEAR)
    elif sy < 1 and sx == 1:
        gray = cv2.GaussianBlur(gray, (0, 0), sigmaX=1e-6, sigmaY=0.8 * np.sqrt(1 / sy**2 - 1))
        gray = cv2.resize(gray, size, interpolation=cv2.INTER_LINEAR)
    else:
        gray = cv2.resize(gray, size, interpolation=cv2.INTER_AREA)
    if mask is not None:
        mask = cv2.resize(mask, size, interpolation=cv2.INTER_NEAREST).astype(np.uint8)
    return gray, mask


def extract_features(
    view: View, config: SparseConfig = DEFAULT_CONFIG, affine: bool = False
) -> Features:
    """SIFT keypoints of one view, restricted to its mask when it has one.

    With ``affine``, SIFT also runs on the image compressed by ``config.affine_tilt`` along x
    and along y (the two simulated tilts of ASIFT that matter for level cameras looking at
    walls and floors from far apart); keypoints are mapped back to the view's pixels.
    """
    image = view.image
    gray: NDArray[Any] = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    h, w = gray.shape[:2]
    mask: NDArray[Any] | None = None
    x0 = y0 = 0
    if view.mask is not None:
        mask = (view.mask.astype(np.uint8) * 255).astype(np.uint8)
        if not mask.any():
            return Features.empty()
        # Detect on the mask's bounding box (plus the descriptors' support): the cost of the
        # scale space follows the masked area, not the image's.
        bx, by, bw, bh = cv2.boundingRect(mask)
        x0, y0 = max(bx - _CROP_MARGIN_PX, 0), max(by - _CROP_MARGIN_PX, 0)
        x1, y1 = min(bx + bw + _CROP_MARGIN_PX, w), min(by + bh + _CROP_MARGIN_PX, h)
        gray, mask = gray[y0:y1, x0:x1], mask[y0:y1, x0:x1]
    ch, cw = gray.shape[:2]
    base = 1.0
    longest = max(w, h)
    if config.feature_max_size_px and longest > config.feature_max_size_px:
        base = config.feature_max_size_px / longest
    simulations = [(base, base)]
    if affine:
        t = 1.0 / config.affine_tilt
        simulations += [(base * t, base), (base, base * t)]
    # Feature budget: scaled by the share of the image the mask keeps (a small foreground
    # naturally has few keypoints), checked on the main simulation only.
    budget = config.min_features
    if budget and mask is not None:
        budget = int(np.ceil(budget * np.count_nonzero(mask) / float(h * w)))
    threshold = config.contrast_threshold
    parts = []
    for sx, sy in simulations:
        g, m = (gray, mask) if sx == sy == 1.0 else _resized(gray, mask, sx, sy)
        pts, sizes, desc = _sift(g, m, config, threshold)
        if (sx, sy) == simulations[0]:
            steps = 0
            while budget and len(pts) < budget and steps < config.contrast_steps:
                steps += 1
                threshold *= config.contrast_step
                pts, sizes, desc = _sift(g, m, config, threshold)
            if steps:
                logger.debug(
                    "features: view %r: %d keypoints at contrast threshold %.4g (budget %d)",
                    view.name, len(pts), threshold, budget,
                )  # fmt: skip
        if len(pts) == 0:
            continue
        # Pixel centres: x_view = (x_small + 0.5) * (W / w) - 0.5, per axis.
        fx, fy = cw / g.shape[1], ch / g.shape[0]
        if (fx, fy) != (1.0, 1.0):
            pts = (pts + 0.5) * [fx, fy] - 0.5
            sizes = sizes * np.float32(np.sqrt(fx * fy))
        if x0 or y0:
            pts = pts + [x0, y0]
        parts.append((pts, sizes, desc))
    if not parts:
        return Features.empty()
    pts = np.concatenate([p[0] for p in parts])
    sizes = np.concatenate([p[1] for p in parts])
    desc = np.concatenate([p[2] for p in parts])
    if config.root_sift:
        desc = np.sqrt(desc / (desc.sum(axis=1, keepdims=True) + 1e-12))
    desc /= np.linalg.norm(desc, axis=1, keepdims=True) + 1e-12
    location, unique_pts = _merge_locations(pts, config.location_merge_px if affine else 0.0)
    return Features(
        points2D=pts,
        descriptors=np.ascontiguousarray(desc, dtype=np.float32),
        sizes_px=sizes,
        location=location,
        location_points2D=unique_pts,
    )


def _merge_locations(
    pts: NDArray[np.float64], radius: float
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Location index of each keypoint and the locations' positions: identical positions
    always share a location; with ``radius`` > 0, so do chains of keypoints closer than it
    (the same corner found in several simulated views), placed at their mean."""
    unique_pts, location = np.unique(pts, axis=0, return_inverse=True)
    location = location.reshape(-1).astype(np.int64)
    if radius <= 0 or len(unique_pts) < 2:
        return location, unique_pts
    pairs = cKDTree(unique_pts).query_pairs(radius, output_type="ndarray")
    if len(pairs) == 0:
        return location, unique_pts
    n = len(unique_pts)
    graph = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    counts = np.bincount(label)
    merged = np.stack([np.bincount(label, unique_pts[:, k]) / counts for k in range(2)], axis=1)
    return label[location].astype(np.int64), merged


def use_affine(views: Sequence[View], config: SparseConfig = DEFAULT_CONFIG) -> bool:
    """Whether ``config.affine_simulation`` asks for simulated tilts with these views: "on",
    "off", or "auto" = when the median angle between a camera's optical axis and its closest
    neighbour's exceeds ``config.affine_auto_angle_deg`` (wide-baseline rigs)."""
    mode = config.affine_simulation
    if mode != "auto" or len(views) < 2:
        return mode == "on"
    axes = np.array([v.camera.R[2] for v in views])
    cos = np.clip(axes @ axes.T, -1.0, 1.0)
    np.fill_diagonal(cos, -1.0)
    nearest = np.degrees(np.arccos(cos.max(axis=1)))
    return bool(np.median(nearest) > config.affine_auto_angle_deg)


def extract_all(views: Sequence[View], config: SparseConfig = DEFAULT_CONFIG) -> list[Features]:
    """Features of every view (simulated tilts as :func:`use_affine` decides), computed by
    ``config.num_threads`` threads."""
    affine = use_affine(views, config)
    return thread_map(lambda v: extract_features(v, config, affine), views, config.num_threads)
