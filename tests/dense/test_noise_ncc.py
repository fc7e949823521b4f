"""The NCC acceptance that follows the images' noise (``DenseConfig.noise_adaptive_ncc``)."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from edgerecon.dense import DenseConfig, reconstruct_dense
from edgerecon.dense.depth import ncc_threshold, noise_sigma
from edgerecon.views import View
from tests.conftest import ring_rig
from tests.dense.scene import box_scene, render

RIG = ring_rig(12, radius=4.0, height=2.0, width=320, height_px=240, focal_px=250.0)
IDS = (11, 0, 1)


def _smooth_image(seed: int, shape: tuple[int, int] = (240, 320)) -> np.ndarray:
    """Smooth content: a ramp plus blobs, no pixel-scale texture."""
    rng = np.random.default_rng(seed)
    blobs = cv2.resize(rng.random((6, 8)).astype(np.float32), shape[::-1], cv2.INTER_CUBIC)
    ramp = np.linspace(0, 60, shape[1], dtype=np.float32)[None, :]
    return (90 + 60 * blobs + ramp).astype(np.float32)


@pytest.mark.parametrize("sigma", [1.0, 3.0, 6.0])
def test_noise_sigma_recovers_added_gaussian_noise(sigma):
    rng = np.random.default_rng(1)
    clean = _smooth_image(0)
    noisy = clean + rng.normal(0, sigma, clean.shape).astype(np.float32)
    assert noise_sigma(noisy) == pytest.approx(sigma, rel=0.15)
    # Smooth content alone reads as (nearly) no noise.
    assert noise_sigma(clean) < 0.1


def test_noise_sigma_of_degenerate_images_is_zero():
    assert noise_sigma(np.zeros((2, 50), np.float32)) == 0.0
    assert noise_sigma(np.full((40, 40), 7.0, np.float32)) == 0.0


def test_threshold_follows_the_texture_to_noise_ratio():
    texture = np.array([100.0, 10.0, 2.0, 1.6, 1.4, 0.5], np.float32)
    thr = ncc_threshold(texture, noise=1.0, min_ncc=0.5, min_snr=1.5)
    # Texture far above the noise: the fixed threshold; 10x: 0.5 * 0.99.
    assert thr[0] == pytest.approx(0.5, abs=1e-3)
    assert thr[1] == pytest.approx(0.495, abs=1e-3)
    # 2x the noise: a true match reaches 0.75 at most, 0.375 is asked.
    assert thr[2] == pytest.approx(0.375, abs=1e-3)
    assert thr[3] == pytest.approx(0.5 * (1 - 1 / 1.6**2), abs=1e-3)
    # Below 1.5x the noise chance wins as often: the fixed threshold again.
    assert thr[4] == pytest.approx(0.5) and thr[5] == pytest.approx(0.5)
    assert np.all(thr <= 0.5 + 1e-6)  # never stricter than the fixed threshold
    # Noise-free images keep the fixed threshold.
    assert np.allclose(ncc_threshold(texture[:4], 0.0, 0.5, 1.5), 0.5)


def test_config_validation():
    assert not DenseConfig().noise_adaptive_ncc  # whole scenes: off (see its docstring)
    with pytest.raises(ValueError, match="ncc_min_snr"):
        DenseConfig(ncc_min_snr=0.5)


@pytest.fixture(scope="module")
def dim_views() -> tuple[list[View], dict[int, np.ndarray], dict[int, tuple]]:
    """The floor-and-cube scene at 30 % of its contrast through sensor noise (sigma 4): many
    windows' texture is 1.5-3 times the noise, where a true match scores well under 1. The
    search is bounded to +-5 % of the true depth, as the visual hull bounds the
    foreground's."""
    rng = np.random.default_rng(7)
    views, depths, ranges = [], {}, {}
    for i in IDS:
        image, depth = render(RIG[i], box_scene())
        dim = 110 + 0.3 * (image.astype(np.float32) - 128)
        noisy = np.clip(np.rint(dim + rng.normal(0, 4.0, dim.shape)), 0, 255).astype(np.uint8)
        views.append(View(camera_id=i, camera=RIG[i], image=noisy))
        depths[i] = depth
        near = np.where(depth > 0, 0.95 * depth, 0).astype(np.float32)
        ranges[i] = (near, np.where(depth > 0, 1.05 * depth, 0).astype(np.float32))
    return views, depths, ranges


def _correct(result, depths) -> tuple[int, int]:
    """(depths within 1 % of the truth, depths) of the middle view."""
    d = result.depth_maps[0]
    gt = cv2.resize(depths[0], result.depth_cameras[0].size, interpolation=cv2.INTER_NEAREST)
    ok = (d > 0) & (gt > 0)
    good = ok & (np.abs(d - gt) < 0.01 * np.maximum(gt, 1e-6))
    return int(good.sum()), int(ok.sum())


def test_dim_noisy_views_keep_more_true_depths_at_the_same_accuracy(dim_views):
    views, depths, ranges = dim_views
    fixed = DenseConfig(resolution_level=0, num_threads=1, window_radius=2)
    adaptive = dataclasses.replace(fixed, noise_adaptive_ncc=True)
    up = (0, 0, 1)
    good_f, all_f = _correct(reconstruct_dense(views, fixed, up=up, depth_ranges=ranges), depths)
    good_a, all_a = _correct(reconstruct_dense(views, adaptive, up=up, depth_ranges=ranges), depths)
    # More correct depths where the fixed threshold turned true matches away (+6 % when
    # written) ...
    assert good_a > 1.03 * good_f
    # ... and the share of correct ones barely moves (0.983 -> 0.979).
    assert good_a / all_a > good_f / all_f - 0.01
