"""Mask cleaning: morphology, small blobs, holes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from edgerecon.quality.masks import mask_iou
from edgerecon.scene.masks import (
    MaskConfig,
    _guided_filter,
    clean_mask,
    fill_holes,
    guided_mask,
    remove_small_blobs,
    resize_mask_smooth,
)
from edgerecon.scene.objects import find_objects
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


def _actor_scene() -> tuple[np.ndarray, np.ndarray]:
    """A red actor (a rectangle and an arm) before a textured green-grey background."""
    rng = np.random.default_rng(3)
    noise = cv2.GaussianBlur(rng.random((120, 160)).astype(np.float32), (0, 0), 2.0)
    bg = np.stack([60 + 80 * noise, 110 + 60 * noise, 70 + 40 * noise], axis=2)
    actor = np.zeros((120, 160), bool)
    actor[30:100, 60:90] = True
    actor[40:46, 90:120] = True  # an arm
    img = bg.copy()
    img[actor] = (40, 50, 190)
    return np.clip(img, 0, 255).astype(np.uint8), actor


def test_guided_mask_moves_a_halo_and_a_coarse_outline_to_the_colour_edge() -> None:
    img, actor = _actor_scene()
    # What a model gives beside a still actor: a 3-pixel halo of background on one side,
    # a missing strip on the other, and the blocky outline of a 4x coarser resolution.
    coarse = cv2.resize(actor.astype(np.uint8), (40, 30), interpolation=cv2.INTER_AREA)
    mask = cv2.resize(coarse, (160, 120), interpolation=cv2.INTER_NEAREST).astype(bool)
    mask[28:102, 57:60] = True
    mask[48:100, 87:90] = False
    refined = guided_mask(mask, img, radius_px=8, groups=lambda: find_objects(mask).labels)
    before, after = mask_iou(mask, actor), mask_iou(refined, actor)
    assert before < 0.85
    assert after > 0.97
    # The same result as the filter of the whole image (only the mask's box is filtered).
    q, plain = _guided_filter(img.astype(np.float32) / 255, mask.astype(np.float32), 8, 1e-3)
    whole = mask.copy()
    whole[mask & (q < 0.5) & (plain - q > 1e-3)] = False
    whole[~mask & (q > 0.5) & (q - plain > 1e-3)] = True
    np.testing.assert_array_equal(refined, whole)
    # The fast filter (coefficients fitted at half the size): as good here, and again the
    # same as the whole image's.
    fast = guided_mask(mask, img, 8, groups=lambda: find_objects(mask).labels, subsample=2)
    assert mask_iou(fast, actor) > 0.97
    q, plain = _guided_filter(img.astype(np.float32) / 255, mask.astype(np.float32), 8, 1e-3, 2)
    whole = mask.copy()
    whole[mask & (q < 0.5) & (plain - q > 1e-3)] = False
    whole[~mask & (q > 0.5) & (q - plain > 1e-3)] = True
    np.testing.assert_array_equal(fast, whole)
    # One component: nothing to glue, the objects are not asked for.
    np.testing.assert_array_equal(guided_mask(mask, img, radius_px=8), refined)


def test_guided_mask_does_not_glue_two_objects() -> None:
    img, actor = _actor_scene()
    # Two actors in the same red, side by side; the masks hold them 6 pixels apart (two
    # objects to find_objects), with the red between them.
    img[30:100, 90:96] = (40, 50, 190)
    second = np.zeros_like(actor)
    second[30:100, 96:126] = True
    img[second] = (40, 50, 190)
    first = np.zeros_like(actor)
    first[30:100, 60:90] = True
    mask = first | second
    groups = find_objects(mask).labels
    assert groups.max() == 2
    refined = guided_mask(mask, img, radius_px=8, groups=lambda: find_objects(mask).labels)
    assert not refined[30:100, 90:96].any()
    assert find_objects(refined).num_objects == 2


def test_guided_mask_leaves_what_colours_cannot_tell() -> None:
    img, actor = _actor_scene()
    flat = np.full_like(img, 90)
    mask = actor.copy()
    mask[28:102, 57:60] = True
    # Flat colour: nothing pushes a pixel, so the filter's blur changes nothing.
    np.testing.assert_array_equal(guided_mask(mask, flat, radius_px=8), mask)
    # A push below min_push changes nothing either; an empty mask stays empty.
    assert np.count_nonzero(guided_mask(mask, img, 8, min_push=0.49) != mask) == 0
    assert not guided_mask(np.zeros_like(mask), img, 8).any()
    with pytest.raises(ValueError):
        guided_mask(mask, img[:, :100], 8)
