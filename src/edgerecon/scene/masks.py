"""Binary foreground masks: cleaning (morphology, small blobs, holes) and resizing.

All functions are pure and work on ``(H, W)`` boolean masks. Pixel sizes in the configs are
pixels of the image the function is applied to (the background model applies the cleaning at
its working resolution).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.types import Mask
from edgerecon.views import resize_mask, resize_mask_smooth

__all__ = [
    "MaskConfig",
    "clean_mask",
    "disk",
    "fill_holes",
    "remove_small_blobs",
    "resize_mask",
    "resize_mask_smooth",
]

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class MaskConfig:
    """How raw foreground detections are turned into clean silhouettes."""

    open_radius_px: int = 1
    """Radius of the morphological opening that removes isolated noise pixels (0 = none)."""
    close_radius_px: int = 3
    """Radius of the morphological closing that bridges small gaps in a silhouette (0 = none)."""
    min_blob_fraction: float = 2e-4
    """Connected foreground regions smaller than this share of the image area are removed."""
    max_hole_fraction: float = 5e-4
    """Background holes inside the foreground smaller than this share of the image area are
    filled (0 = keep all holes; 1 = fill every enclosed hole)."""

    def __post_init__(self) -> None:
        for name in ("open_radius_px", "close_radius_px"):
            value = getattr(self, name)
            if not isinstance(value, int | np.integer) or value < 0:
                raise ValueError(f"MaskConfig.{name} must be an integer >= 0, got {value!r}")
        for name in ("min_blob_fraction", "max_hole_fraction"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"MaskConfig.{name} must be in [0, 1], got {value!r}")

    def scaled(self, scale: float) -> MaskConfig:
        """The same cleaning for an image resized by ``scale`` (radii scale, fractions stay)."""
        return MaskConfig(
            open_radius_px=round(self.open_radius_px * scale) if self.open_radius_px else 0,
            close_radius_px=round(self.close_radius_px * scale) if self.close_radius_px else 0,
            min_blob_fraction=self.min_blob_fraction,
            max_hole_fraction=self.max_hole_fraction,
        )


def disk(radius: int) -> NDArray[np.uint8]:
    """Elliptic structuring element of the given radius (a 1x1 element for radius 0)."""
    r = max(0, int(radius))
    return np.asarray(
        cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1)), dtype=np.uint8
    )


def remove_small_blobs(mask: Mask, min_area_px: int) -> Mask:
    """Drop 8-connected foreground regions with fewer than ``min_area_px`` pixels."""
    mask = np.asarray(mask, dtype=bool)
    if min_area_px <= 1 or not mask.any():
        return mask.copy()
    _, labels, stats, _ = cv2.connectedComponentsWithStats(mask.view(np.uint8), connectivity=8)
    keep = stats[:, cv2.CC_STAT_AREA] >= min_area_px
    keep[0] = False
    return keep[labels]


def fill_holes(mask: Mask, max_area_px: int | None = None) -> Mask:
    """Fill background regions not connected to the image border (4-connectivity for the
    background), optionally only those with at most ``max_area_px`` pixels."""
    mask = np.asarray(mask, dtype=bool)
    if not mask.any() or (max_area_px is not None and max_area_px <= 0):
        return mask.copy()
    inv = (~mask).view(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(inv, connectivity=4)
    if n <= 1:
        return mask.copy()
    h, w = mask.shape
    border = np.unique(np.concatenate([labels[0], labels[h - 1], labels[:, 0], labels[:, w - 1]]))
    hole = np.ones(n, dtype=bool)
    hole[0] = False  # label 0 is the foreground itself
    hole[border] = False
    if max_area_px is not None:
        hole &= stats[:, cv2.CC_STAT_AREA] <= max_area_px
    return mask | hole[labels]


def clean_mask(mask: Mask, config: MaskConfig | None = None) -> Mask:
    """Opening, closing, small-blob removal and hole filling of a raw foreground mask."""
    config = config or MaskConfig()
    m = np.asarray(mask, dtype=bool)
    if m.ndim != 2:
        raise ValueError(f"clean_mask expects a (H, W) mask, got shape {m.shape}")
    if not m.any():
        return m.copy()
    u8: NDArray[np.uint8] = m.astype(np.uint8)
    if config.open_radius_px:
        u8 = np.asarray(cv2.morphologyEx(u8, cv2.MORPH_OPEN, disk(config.open_radius_px)))
    if config.close_radius_px:
        # Pad so that the closing does not glue silhouettes to the image border.
        r = config.close_radius_px
        padded = cv2.copyMakeBorder(u8, r, r, r, r, cv2.BORDER_CONSTANT, value=0)
        u8 = np.asarray(cv2.morphologyEx(padded, cv2.MORPH_CLOSE, disk(r)), np.uint8)[r:-r, r:-r]
    area = m.shape[0] * m.shape[1]
    out = remove_small_blobs(u8.astype(bool), int(np.ceil(config.min_blob_fraction * area)))
    if config.max_hole_fraction > 0:
        out = fill_holes(out, int(config.max_hole_fraction * area))
    return out
