"""Source-view selection: coverage-aware choice on an arc of cameras."""

from __future__ import annotations

import numpy as np

from edgerecon.dense.neighbors import angle_weight, point_weights, select_sources
from edgerecon.geometry import Camera, look_at


def _arc(num: int = 7, spacing_deg: float = 15.0, radius: float = 3.6) -> list[Camera]:
    """Cameras on an arc around (0, 0, 1), all looking at it (like the synthetic arc7)."""
    cams = []
    for k in range(num):
        a = np.radians(-90.0 + (k - (num - 1) / 2) * spacing_deg)
        R, t = look_at((radius * np.cos(a), radius * np.sin(a), 1.9), (0.0, 0.0, 1.0))
        K = np.array([[800.0, 0, 319.5], [0, 800.0, 239.5], [0, 0, 1]])
        cams.append(Camera(name=f"c{k}", width=640, height=480, K=K, R=R, t=t))
    return cams


def test_angle_weight_prefers_moderate_angles():
    assert angle_weight(0.0) == 0.0
    assert angle_weight(5.0) == 0.5
    assert angle_weight(20.0) == angle_weight(45.0) == 1.0
    assert 0.0 < angle_weight(90.0) < angle_weight(60.0) < 1.0


def test_sources_cover_what_only_the_neighbour_sees():
    cams = _arc()
    ref = 6
    rng = np.random.default_rng(0)
    # Most sample points on the far wall (every camera sees them, under small angles from
    # the neighbours) and a patch on a side wall that only the end cameras 5 and 6 see.
    centre = np.c_[rng.uniform(-1.2, 1.2, 400), np.full(400, 4.0), rng.uniform(0.3, 2.5, 400)]
    wall = np.c_[np.full(60, -4.0), rng.uniform(1.0, 3.5, 60), rng.uniform(0.2, 2.0, 60)]
    samples = np.vstack([centre, wall])
    scores, weights = point_weights(cams[ref], cams, ref, samples)
    seen_wall = [j for j in range(len(cams)) if weights[j, 400:].mean() > 0.3]
    assert seen_wall == [5]
    assert weights[ref].sum() == 0 and len(scores) == len(cams) - 1
    # Ranked one by one, three sources that see the centre best; chosen together, the
    # neighbour that alone sees the wall is among them.
    ranked = select_sources(scores, 3, 2.0, 110.0)
    chosen = select_sources(scores, 3, 2.0, 110.0, weights=weights)
    assert 5 not in ranked
    assert 5 in chosen and len(chosen) == 3 and ref not in chosen
    # Deterministic, and limited by the angle bounds and the count.
    assert chosen == select_sources(scores, 3, 2.0, 110.0, weights=weights)
    assert select_sources(scores, 1, 2.0, 110.0, weights=weights) == chosen[:1]
    assert select_sources(scores, 3, 100.0, 110.0, weights=weights) == []


def test_sources_beyond_the_minimum_must_add_coverage():
    cams = _arc()
    rng = np.random.default_rng(1)
    samples = np.c_[rng.uniform(-1.2, 1.2, 400), np.full(400, 4.0), rng.uniform(0.3, 2.5, 400)]
    scores, weights = point_weights(cams[3], cams, 3, samples)
    every = select_sources(scores, 6, 2.0, 110.0, weights=weights)
    assert len(every) == 6
    # Gains of successive sources shrink (each covers what the earlier ones missed); a
    # threshold between two of them cuts the list there, never below the minimum count.
    missed = np.ones(weights.shape[1])
    gains = []
    for j in every:
        gains.append(float((missed * weights[j]).mean()))
        missed *= 1.0 - weights[j]
    assert np.all(np.diff(gains) <= 0)
    cut = (gains[2] + gains[3]) / 2
    assert gains[2] > gains[3]
    assert select_sources(scores, 6, 2.0, 110.0, weights=weights, min_gain=cut) == every[:3]
    assert (
        select_sources(scores, 6, 2.0, 110.0, weights=weights, min_gain=1.0, min_sources=2)
        == every[:2]
    )
    assert select_sources(scores, 2, 2.0, 110.0, weights=weights, min_gain=0.0) == every[:2]
