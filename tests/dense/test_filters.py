"""Precision filters of the dense stage (dense.filters) and the conflict / candidate counts
of the consistency check."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from edgerecon.dense import DenseConfig
from edgerecon.dense.consistency import agreement_tolerance, depth_noise, support_and_conflicts
from edgerecon.dense.filters import (
    consistency_keep,
    depth_edge_mask,
    grazing_mask,
    outlier_mask,
)
from edgerecon.dense.fusion import ViewPoints
from edgerecon.geometry.camera import Camera
from tests.conftest import ring_rig
from tests.dense.scene import box_scene, render

RIG = ring_rig(12, radius=4.0, height=2.0, width=160, height_px=120, focal_px=125.0)
IDS = (11, 0, 1)


def test_floating_specks_are_contradicted_and_hidden_places_are_not_candidates():
    rects = box_scene()
    depths = {i: render(RIG[i], rects)[1] for i in IDS}
    cams = {i: RIG[i] for i in IDS}
    noisy = {i: d.copy() for i, d in depths.items()}
    noisy[0][80:100, 60:100] *= 0.9  # a patch floating 10 % in front of the surface
    support, _, conflicts, candidates = support_and_conflicts(noisy, cams, 0.01)
    has = depths[0] > 0
    patch = np.zeros_like(has)
    patch[80:100, 60:100] = True
    # The others see the true surface behind the floating patch: they contradict it.
    assert np.mean(conflicts[0][patch & has] >= 1) > 0.8
    assert np.mean(conflicts[0][~patch & has] == 0) > 0.9
    # Correct depths: the views that could confirm them mostly do.
    good = ~patch & has
    assert np.all(candidates[0][good] >= support[0][good])
    assert np.mean(support[0][good] == candidates[0][good]) > 0.8
    cfg = DenseConfig(max_conflict_share=0.5)
    score = np.ones_like(depths[0])
    keep = consistency_keep(noisy[0], support[0], conflicts[0], candidates[0], score, cfg)
    assert np.mean(keep[patch & has]) < 0.2 and np.mean(keep[good]) > 0.85
    # A share of the candidates: stricter than one supporting view.
    strict = DenseConfig(consistent_view_share=1.0)
    k2 = consistency_keep(noisy[0], support[0], conflicts[0], candidates[0], score, strict)
    base = consistency_keep(noisy[0], support[0], conflicts[0], candidates[0], score, DenseConfig())
    assert k2.sum() < base.sum() and np.all(base[k2])


def test_weak_depths_need_a_good_score():
    d = np.ones((2, 2), np.float32)
    support = np.array([[1, 2], [1, 0]], np.int16)
    zero = np.zeros((2, 2), np.int16)
    score = np.array([[0.6, 0.6], [0.9, 0.9]], np.float32)
    keep = consistency_keep(d, support, zero, support, score, DenseConfig(min_weak_ncc=0.8))
    assert keep.tolist() == [[False, True], [True, False]]


def test_depth_edges_are_found_on_the_far_side_of_discontinuities_only():
    d = np.full((20, 20), 2.0, np.float32)
    d[:, 10:] = 3.0
    d[:, :3] = 0.0  # a hole: its border is not an edge
    d[5, 5] = 2.01  # noise below the threshold
    edge = depth_edge_mask(d, 0.05)
    assert edge[:, 10].all()  # the far side's first column
    assert edge.sum() == 20  # the near side's rim is kept
    d[8, 15] = 2.7  # a streak step between the two levels
    edge = depth_edge_mask(d, 0.05)
    assert not edge[8, 15] and edge[7:10, 14:17].sum() == 8


def test_grazing_points_and_outliers_are_flagged():
    pts = np.array([[0, 0, 5.0], [0, 0, 5.0], [0, 0, 5.0]])
    normals = np.array([[0, 0, -1], [1, 0, 0], [0.5, 0, -0.866]], np.float32)
    vp = ViewPoints(
        camera_id=0,
        points3D=pts,
        colors=np.zeros((3, 3), np.uint8),
        normals=normals,
        num_views=np.ones(3, np.int16),
        score=np.ones(3, np.float32),
    )
    g = grazing_mask(vp, np.zeros(3), 80.0)
    assert g.tolist() == [False, True, False]
    kept = vp.select(~g)
    assert kept.points3D.shape == (2, 3) and not kept.inferred
    # A selection keeps the part's inferred flag (ground completion is filtered too).
    assert dataclasses.replace(vp, inferred=True).select(~g).inferred
    rng = np.random.default_rng(0)
    cloud = np.vstack([rng.uniform(0, 1, (2000, 3)) * [1, 1, 0.01], [[0.5, 0.5, 0.5]]])
    out = outlier_mask(cloud, 8, 3.0)
    assert out[-1] and out[:-1].mean() < 0.01
    assert not outlier_mask(cloud[:5], 8, 2.0).any()


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("consistent_view_share", 1.5),
        ("max_conflict_share", -0.1),
        ("min_weak_ncc", 1.0),
        ("depth_edge_rel", -1.0),
        ("max_grazing_deg", 0.0),
        ("outlier_k", -1),
        ("outlier_std", 0.0),
    ],
)
def test_filter_options_are_validated(field, value):
    with pytest.raises(ValueError, match=field):
        DenseConfig(**{field: value})


def test_the_agreement_tolerance_follows_the_measured_depth_noise():
    # Three parallel cameras 0.3 m apart facing a wall 5 m away: every view's depth is 5 m
    # everywhere, so the views' disagreement is the noise added to their depth maps.
    K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
    cams = {
        i: Camera(name=f"c{i}", width=320, height=240, K=K, R=np.eye(3), t=(-0.3 * i, 0, 0))
        for i in range(3)
    }
    rng = np.random.default_rng(3)

    def noisy(sigma: float) -> dict[int, np.ndarray]:
        return {
            i: (5.0 * (1 + sigma * rng.standard_normal((240, 320)))).astype(np.float32)
            for i in cams
        }

    # The median of |a - b| for a, b ~ N(0, s^2) is 0.954 s.
    for sigma in (0.0005, 0.002):
        noise, pairs = depth_noise(noisy(sigma), cams, 0.02)
        assert pairs > 500 and noise is not None
        assert noise == pytest.approx(0.954 * sigma, rel=0.1)
    cfg = DenseConfig()  # 4 x the noise, within [0.3 %, 1 %]
    tol, noise = agreement_tolerance(noisy(0.0005), cams, cfg)
    assert noise is not None and tol == cfg.consistency_rel_depth_min  # tight: the floor
    tol, noise = agreement_tolerance(noisy(0.0015), cams, cfg)
    assert noise is not None and tol == pytest.approx(4.0 * noise) and 0.004 < tol < 0.008
    tol, _ = agreement_tolerance(noisy(0.004), cams, cfg)
    assert tol == cfg.consistency_rel_depth  # as noisy as real video: the fixed tolerance
    # Off, or nothing to measure: the fixed tolerance.
    off = DenseConfig(consistency_noise_factor=0.0)
    assert agreement_tolerance(noisy(0.0005), cams, off) == (off.consistency_rel_depth, None)
    empty = {i: np.zeros((240, 320), np.float32) for i in cams}
    assert agreement_tolerance(empty, cams, cfg) == (cfg.consistency_rel_depth, None)
    with pytest.raises(ValueError, match="consistency_rel_depth_min"):
        DenseConfig(consistency_rel_depth_min=0.0)
