"""Ground completion on a floor with two levels: a blank floor (z = 0) and a blank deck 15 cm
higher. Neither level may be completed at the other's height."""

from __future__ import annotations

import numpy as np
import pytest

from edgerecon.dense.planes import Plane, complete_with_plane, keep_off_levels, level_map
from tests.conftest import ring_rig
from tests.dense.scene import Rect, noise_texture, render

RIG = ring_rig(12, radius=4.0, height=2.0, width=240, height_px=180, focal_px=190.0)
IDS = (10, 11, 0, 1, 2)
DECK_H = 0.15
DECK = 0.8  # half width: the deck covers |x|, |y| < 0.8
pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")  # rays parallel to a rect


def _rect(origin, u, v, texture) -> Rect:
    return Rect(np.asarray(origin, float), np.asarray(u, float), np.asarray(v, float), texture)


def _scene() -> list[Rect]:
    grey = np.full((64, 64, 3), 90, np.uint8)  # both levels blank and the same grey
    d, h = DECK, DECK_H
    return [
        _rect((-3, -3, 0), (6, 0, 0), (0, 6, 0), grey),
        _rect((-d, -d, h), (2 * d, 0, 0), (0, 2 * d, 0), grey),
        _rect((-d, -d, 0), (2 * d, 0, 0), (0, 0, h), noise_texture(64, 1)),
        _rect((-d, d, 0), (2 * d, 0, 0), (0, 0, h), noise_texture(64, 2)),
        _rect((-d, -d, 0), (0, 2 * d, 0), (0, 0, h), noise_texture(64, 3)),
        _rect((d, -d, 0), (0, 2 * d, 0), (0, 0, h), noise_texture(64, 4)),
    ]


def _world(cam, depth):
    rows, cols = np.indices(depth.shape)
    return cam.backproject(np.c_[cols.ravel(), rows.ravel()], depth.ravel()).reshape(
        *depth.shape, 3
    )


@pytest.fixture(scope="module")
def two_levels():
    """Images, exact depths, 'stereo' depths (a sparse fifth of the pixels, as if a faint
    texture had been matched there) and the measured points with their normals."""
    rects = _scene()
    images, truth, measured, pts, nrm = {}, {}, {}, [], []
    for i in IDS:
        images[i], truth[i] = render(RIG[i], rects)
        rows, cols = np.indices(truth[i].shape)
        sparse = (rows + 2 * cols) % 5 == 0
        measured[i] = np.where(sparse, truth[i], 0).astype(np.float32)
        X = _world(RIG[i], measured[i])[measured[i] > 0]
        flat = (np.abs(X[:, 2]) < 1e-4) | (np.abs(X[:, 2] - DECK_H) < 1e-4)
        n = np.where(flat[:, None], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]).astype(np.float32)
        pts.append(X)
        nrm.append(n)
    P, N = np.concatenate(pts), np.concatenate(nrm)
    return images, truth, measured, P, N


def _complete(two_levels, z, levels):
    images, _, measured, P, N = two_levels
    plane = Plane(normal=(0.0, 0.0, 1.0), offset=z, support=1000, rms=0.0)
    lm = None
    if levels:
        lm = level_map(plane, P, N, np.full(len(P), 3), band=0.03, cell=0.25, min_points=5)
    refused: dict[int, int] = {}
    out = complete_with_plane(
        plane, measured, {i: RIG[i] for i in IDS}, images,
        {i: np.ones(d.shape, bool) for i, d in measured.items()}, {i: 20.0 for i in IDS},
        0.01, 20.0, 1,
    )  # fmt: skip
    if lm is not None:
        out, refused = keep_off_levels(lm, out, {i: RIG[i] for i in IDS})
    return {i: _world(RIG[i], d)[d > 0] for i, (d, _) in out.items()}, lm, refused


def _in_deck(X, margin=0.0):
    return (np.abs(X[:, 0]) < DECK - margin) & (np.abs(X[:, 1]) < DECK - margin)


def test_level_map_finds_the_deck(two_levels):
    *_, P, N = two_levels
    plane = Plane(normal=(0.0, 0.0, 1.0), offset=0.0, support=1000, rms=0.0)
    lm = level_map(plane, P, N, np.full(len(P), 3), band=0.03, cell=0.25, min_points=5)
    raised = lm.raised > lm.band
    assert raised.any() and not lm.lower.any()
    assert np.allclose(lm.raised[raised], DECK_H, atol=1e-3)
    # Deck cells are raised, floor cells far from the deck are not.
    deck = np.array([[0.1, 0.1, 0.0], [-0.6, 0.5, 0.0]])
    floor = np.array([[2.0, 0.0, 0.0], [1.5, -1.5, 0.0]])
    assert (lm.raised[lm.cells(deck)] > 0.1).all()
    assert (lm.raised[lm.cells(floor)] == 0).all()
    assert lm.stats()["cells_raised"] == int(raised.sum())
    # Seen from the deck's level, the floor is a lower level.
    top = Plane(normal=(0.0, 0.0, 1.0), offset=DECK_H, support=1000, rms=0.0)
    lm2 = level_map(top, P, N, np.full(len(P), 3), band=0.03, cell=0.25, min_points=5)
    assert lm2.lower[lm2.cells(floor)].all() and not lm2.lower[lm2.cells(deck)].any()


def test_floor_is_not_completed_under_the_deck(two_levels):
    before, _, _ = _complete(two_levels, 0.0, levels=False)
    after, lm, refused = _complete(two_levels, 0.0, levels=True)
    # Without the level map the blank deck is painted at floor height (the bug) ...
    assert sum(int(_in_deck(X, 0.05).sum()) for X in before.values()) > 500
    # ... with it, not one completed floor point lies in the deck's footprint.
    assert sum(int(_in_deck(X).sum()) for X in after.values()) == 0
    assert sum(refused.values()) > 500 and lm.stats()["cells_raised"] > 0
    # The open floor is still completed.
    _, truth, measured, *_ = two_levels
    for i in IDS:
        Xt = _world(RIG[i], truth[i])
        open_floor = (truth[i] > 0) & (measured[i] == 0) & (np.abs(Xt[..., 2]) < 1e-4)
        far = open_floor & (np.abs(Xt[..., :2]).max(axis=-1) > DECK + 0.5)
        assert len(after[i]) > 0.6 * far.sum()
        assert np.allclose(after[i][:, 2], 0.0, atol=1e-6)


def test_deck_level_does_not_spread_over_the_floor(two_levels):
    before, _, _ = _complete(two_levels, DECK_H, levels=False)
    after, lm, _ = _complete(two_levels, DECK_H, levels=True)
    assert sum(int((~_in_deck(X, -0.3)).sum()) for X in before.values()) > 500
    # With the level map: nothing outside the deck (the floor is a lower level); the deck
    # itself is completed at its own height.
    assert sum(int((~_in_deck(X, -0.3)).sum()) for X in after.values()) == 0
    assert sum(int(_in_deck(X, 0.05).sum()) for X in after.values()) > 500
    assert lm.stats()["cells_lower"] > 0 and lm.stats()["cells_raised"] == 0


def test_a_blank_deck_measured_only_at_its_rim_is_raised_throughout():
    rng = np.random.default_rng(0)
    floor = np.c_[rng.uniform(-3, 3, (20000, 2)), np.zeros(20000)]
    floor = floor[~_in_deck(floor)]
    # Deck points only on a 0.3 m rim; nothing measured in its middle (a blank top).
    rim = np.c_[rng.uniform(-DECK, DECK, (8000, 2)), np.full(8000, DECK_H)]
    rim = rim[~_in_deck(rim, 0.3)]
    P = np.vstack([floor, rim])
    N = np.tile(np.float32([0, 0, 1]), (len(P), 1))
    plane = Plane(normal=(0.0, 0.0, 1.0), offset=0.0, support=1000, rms=0.0)
    lm = level_map(plane, P, N, np.full(len(P), 3), band=0.03, cell=0.2, min_points=5)
    centre = np.array([[0.0, 0.0, 0.0], [0.3, -0.3, 0.0]])
    assert np.allclose(lm.raised[lm.cells(centre)], DECK_H, atol=1e-6)
    # A floor point under the blank middle is refused from any camera above the deck.
    assert lm.refused(centre, np.array([4.0, 0.0, 2.0])).all()
    assert not lm.refused(np.array([[2.5, 2.5, 0.0]]), np.array([4.0, 0.0, 2.0])).any()
    # Just behind the deck as the camera sees it: the ray passes under the deck's top (the
    # pixel shows the deck); just in front of it: the floor is seen.
    behind, front = np.array([[-1.0, 0.0, 0.0]]), np.array([[1.1, 0.0, 0.0]])
    assert lm.refused(behind, np.array([4.0, 0.0, 2.0])).all()
    assert not lm.refused(front, np.array([4.0, 0.0, 2.0])).any()
