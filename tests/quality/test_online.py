"""The online quality estimate and its correlation with an offline score."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from edgerecon.quality.online import (
    OnlineQualityConfig,
    online_offline_correlation,
    online_quality,
)
from edgerecon.types import PointCloud


def sphere(n: int, seed: int, radius: float = 1.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    return radius * v / np.linalg.norm(v, axis=1, keepdims=True)


def test_identical_clouds_score_one_and_noise_lowers_the_score():
    golden = sphere(3000, 0)
    cfg = OnlineQualityConfig(threshold=0.02)
    assert online_quality(golden, golden, cfg).fscore == 1.0
    rng = np.random.default_rng(1)
    scores = []
    for sigma in (0.0, 0.01, 0.02, 0.04, 0.08):
        cand = golden[:1500] + rng.normal(0, sigma, (1500, 3))
        q = online_quality(cand, golden, cfg)
        assert q.status == "ok" and q.informative
        scores.append(q.fscore)
    assert all(a > b for a, b in itertools.pairwise(scores))
    # half the golden points, noise-free: precision 1, recall about half the sphere's area
    half = online_quality(golden[:1500], golden, cfg)
    assert half.precision == 1.0
    assert 0.5 < half.recall < 0.9


def test_relative_threshold_uses_the_golden_bounding_box():
    golden = sphere(2000, 2, radius=10.0)  # diagonal ~ 34.6
    q = online_quality(golden, golden, OnlineQualityConfig(threshold_rel=0.01))
    assert q.threshold == pytest.approx(0.01 * np.linalg.norm(golden.max(0) - golden.min(0)))


def test_empty_and_tiny_clouds_have_defined_answers():
    golden = sphere(500, 3)
    empty = np.zeros((0, 3))
    q = online_quality(empty, golden, OnlineQualityConfig(threshold=0.05))
    assert (q.fscore, q.status, q.value) == (0.0, "empty_candidate", 0.0)
    q = online_quality(golden, empty)
    assert q.fscore is None and q.value is None and q.status == "empty_reference"
    assert not q.informative
    q = online_quality(golden, golden[:5], OnlineQualityConfig(min_reference_points=10))
    assert q.status == "few_reference_points" and q.value is None
    q = online_quality(empty, empty)
    assert q.status == "empty_reference"


def test_labels_select_the_foreground():
    fg = sphere(800, 4)
    bg = sphere(800, 5, radius=5.0)
    labels = np.r_[np.ones(800, np.int32), np.zeros(800, np.int32)]
    golden = PointCloud(points3D=np.r_[fg, bg], labels=labels)
    # the candidate got the foreground right and the background wrong: FG-only scoring is 1
    cand = PointCloud(points3D=np.r_[fg, bg + 3.0], labels=labels)
    assert online_quality(cand, golden, OnlineQualityConfig(threshold=0.01)).fscore == 1.0
    full = online_quality(cand, golden, OnlineQualityConfig(threshold=0.01, foreground_only=False))
    assert full.fscore < 0.6
    assert online_quality(cand, golden).num_reference == 800


def test_correlation_helper():
    scales = [1.0, 0.95, 0.9, 0.85, 0.8, 0.75, 0.7]
    online = [0.95, 0.911, 0.888, 0.873, 0.864, 0.855, 0.819]  # paper Table IV, online
    offline = [0.9, 0.873, 0.851, 0.836, 0.817, 0.797, 0.770]  # paper Table IV, offline
    rep = online_offline_correlation(online, offline)
    assert rep.num_samples == 7
    assert rep.spearman == pytest.approx(1.0)
    assert rep.pearson > 0.97
    assert rep.trend_agreement == 1.0
    anti = online_offline_correlation(online, offline[::-1])
    assert anti.spearman == pytest.approx(-1.0) and anti.trend_agreement == 0.0
    flat = online_offline_correlation([0.5] * 4, [0.1, 0.2, 0.3, 0.4])
    assert math.isnan(flat.pearson) and math.isnan(flat.spearman)
    missing = online_offline_correlation([0.9, None, 0.7, 0.6], [0.8, 0.7, None, 0.5])
    assert missing.num_samples == 2 and math.isnan(missing.pearson)
    assert missing.to_dict()["pearson"] is None
    with pytest.raises(ValueError, match="online has 2"):
        online_offline_correlation([0.1, 0.2], [0.1])
    _ = scales


def test_online_estimate_tracks_an_offline_score_on_a_synthetic_scale_sweep():
    """Sparse points at scale r: fewer (~r^2) and noisier (~1/r) samples of the surface;
    dense points likewise but 10x more. Online = sparse(r) vs sparse(1); offline = dense(r)
    vs the true surface. Both must fall together as r falls."""
    rng = np.random.default_rng(6)
    truth = sphere(20000, 7)
    golden = truth[rng.choice(len(truth), 2000, replace=False)] + rng.normal(0, 0.004, (2000, 3))
    online, offline = [], []
    scales = np.round(np.arange(1.0, 0.29, -0.1), 2)
    for r in scales:
        n_sparse = int(2000 * r**2)
        sigma = 0.004 / r
        sparse = truth[rng.choice(len(truth), n_sparse, replace=False)]
        sparse = sparse + rng.normal(0, sigma, sparse.shape)
        dense = truth[rng.choice(len(truth), 10 * n_sparse, replace=True)]
        dense = dense + rng.normal(0, sigma, dense.shape)
        online.append(online_quality(sparse, golden, OnlineQualityConfig(threshold=0.02)).fscore)
        offline.append(online_quality(dense, truth, OnlineQualityConfig(threshold=0.02)).fscore)
    rep = online_offline_correlation(online, offline)
    assert rep.spearman > 0.9 and rep.pearson > 0.9


def test_config_validation():
    with pytest.raises(ValueError, match="threshold"):
        OnlineQualityConfig(threshold=0)
    with pytest.raises(ValueError, match="threshold_rel"):
        OnlineQualityConfig(threshold_rel=-1)
    with pytest.raises(ValueError, match="min_reference_points"):
        OnlineQualityConfig(min_reference_points=0)


def test_silhouette_quality_known_answers() -> None:
    """A cloud that fills one camera's silhouette scores 1; half of it, recall ~0.5; points
    outside every silhouette lower precision; no foreground anywhere is uninformative."""
    from edgerecon.geometry.camera import Camera
    from edgerecon.quality.online import silhouette_quality

    K = np.array([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])
    cam = Camera(name="c", width=64, height=48, K=K, R=np.eye(3), t=np.zeros(3))
    mask = np.zeros((48, 64), bool)
    mask[14:34, 22:42] = True
    # One point per mask pixel, back-projected onto the plane z = 0.
    ys, xs = np.nonzero(mask)
    pts = cam.backproject(np.stack([xs, ys], axis=1).astype(float), np.full(len(xs), 4.0))
    full = silhouette_quality(pts, [cam], [mask])
    assert full.value == pytest.approx(1.0)
    half = silhouette_quality(pts[xs < 32], [cam], [mask], splat_px=0)
    assert half.recall == pytest.approx(0.5, abs=0.01) and half.precision == 1.0
    far = cam.backproject(np.array([[5.0, 5.0]] * len(xs)), np.full(len(xs), 4.0))
    mixed = silhouette_quality(np.vstack([pts, far]), [cam], [mask])
    assert mixed.precision == pytest.approx(0.5, abs=0.01)
    assert silhouette_quality(pts, [cam], [np.zeros_like(mask)]).value is None
    assert silhouette_quality(np.zeros((0, 3)), [cam], [mask]).value == 0.0


def test_silhouette_recall_counts_the_textured_mask_pixels() -> None:
    """A black, textureless half of a silhouette (a shirt no stereo measures) leaves the
    recall's denominator when the frames are given."""
    from edgerecon.geometry.camera import Camera
    from edgerecon.quality.online import silhouette_quality, textured

    K = np.array([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])
    cam = Camera(name="c", width=64, height=48, K=K, R=np.eye(3), t=np.zeros(3))
    mask = np.zeros((48, 64), bool)
    mask[14:34, 22:42] = True
    rng = np.random.default_rng(1)
    image = rng.integers(0, 255, (48, 64, 3)).astype(np.uint8)
    image[14:34, 32:48] = 10  # the right half of the silhouette (and beyond): flat black
    tex = textured(image)
    assert tex[20:28, 8:20].all() and not tex[18:30, 36:44].any()
    assert textured(image.astype(np.float32)).sum() == tex.sum()  # working images: float32
    ys, xs = np.nonzero(mask & (np.arange(64) < 32)[None, :])  # points on the textured half
    pts = cam.backproject(np.stack([xs, ys], axis=1).astype(float), np.full(len(xs), 4.0))
    every = silhouette_quality(pts, [cam], [mask], splat_px=0)
    assert every.recall == pytest.approx(0.5, abs=0.01)
    judged = silhouette_quality(pts, [cam], [mask], splat_px=0, images=[image])
    # The black half's pixels within 3 px of the texture (the 7x7 window) still count.
    assert judged.num_reference == 200 + 20 * 3 + 2 * 3 * 7
    assert judged.recall == pytest.approx(200 / 302) and judged.precision == 1.0
