"""Mask cleaning: morphology, small blobs, holes."""

from __future__ import annotations

import numpy as np
import pytest

from edgerecon.quality.masks import mask_iou
from edgerecon.scene.masks import (
    MaskConfig,
    clean_mask,
    fill_holes,
    remove_small_blobs,
    resize_mask_smooth,
)
from tests.scene._scenes import square_mask


def test_clean_mask_removes_speckle_and_fills_small_holes() -> None:
    truth = square_mask(100, 100, 20, 20, 40)
    raw = truth.copy()
    raw[35:38, 35:38] = False  # a small hole inside
    rng = np.random.default_rng(0)
    speckle = rng.random((100, 100)) < 0.01
    raw |= speckle & ~square_mask(100, 100, 15, 15, 50)
    out = clean_mask(raw, MaskConfig())
    assert mask_iou(out, truth) > 0.98
    assert not out[:10].any()  # isolated noise pixels are gone
    assert out[35:38, 35:38].all()  # the hole is filled


def test_fill_holes_respects_max_area_and_border() -> None:
    ring = square_mask(50, 50, 10, 10, 30) & ~square_mask(50, 50, 15, 15, 20)  # hole 400 px
    assert fill_holes(ring)[25, 25]
    assert not fill_holes(ring, max_area_px=399)[25, 25]
    assert fill_holes(ring, max_area_px=400)[25, 25]
    # A region open to the border is not a hole.
    u = square_mask(50, 50, 0, 10, 30) & ~square_mask(50, 50, 0, 15, 20)
    assert not fill_holes(u)[20, 5]


def test_remove_small_blobs_keeps_large_ones() -> None:
    m = square_mask(60, 60, 5, 5, 3) | square_mask(60, 60, 30, 30, 10)
    out = remove_small_blobs(m, 10)
    assert not out[5:8, 5:8].any()
    assert out[30:40, 30:40].all()


def test_empty_mask_stays_empty() -> None:
    m = np.zeros((30, 40), bool)
    assert not clean_mask(m).any()
    assert not fill_holes(m).any()


def test_resize_mask_smooth_preserves_shape() -> None:
    m = square_mask(60, 80, 20, 10, 30)
    up = resize_mask_smooth(m, (160, 120))
    assert up.shape == (120, 160)
    assert mask_iou(up, square_mask(120, 160, 40, 20, 60)) > 0.95


def test_mask_iou_known_answers() -> None:
    a = square_mask(10, 10, 0, 0, 4)  # 16 px
    b = square_mask(10, 10, 2, 0, 4)  # overlap 8 px
    assert mask_iou(a, b) == pytest.approx(8 / 24)
    assert mask_iou(np.zeros((3, 3), bool), np.zeros((3, 3), bool)) == 1.0


def test_mask_config_validation() -> None:
    with pytest.raises(ValueError, match="open_radius_px"):
        MaskConfig(open_radius_px=-1)
    with pytest.raises(ValueError, match="min_blob_fraction"):
        MaskConfig(min_blob_fraction=2.0)
