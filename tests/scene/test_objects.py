"""Object clustering: known answers on small masks."""

from __future__ import annotations

import numpy as np
import pytest

from edgerecon.scene.objects import ObjectConfig, find_objects, silhouette_score
from tests.scene._scenes import square_mask


def _person(h: int, w: int, x: int, y: int, scale: int = 1) -> np.ndarray:
    """A crude upright silhouette: head, body, two legs (one component)."""
    m = np.zeros((h, w), bool)
    s = scale
    m[y : y + 8 * s, x + 4 * s : x + 10 * s] = True  # head
    m[y + 8 * s : y + 30 * s, x : x + 14 * s] = True  # body
    m[y + 30 * s : y + 50 * s, x + 1 * s : x + 5 * s] = True  # legs
    m[y + 30 * s : y + 50 * s, x + 9 * s : x + 13 * s] = True
    return m


def test_two_separated_blobs_give_two_objects() -> None:
    m = _person(120, 200, 20, 30) | _person(120, 200, 140, 40)
    seg = find_objects(m)
    assert seg.num_objects == 2
    assert seg.silhouette > 0.5
    ids = {int(seg.labels[50, 25]), int(seg.labels[60, 145])}
    assert ids == {1, 2}
    assert seg.objects[0].area_px >= seg.objects[1].area_px
    np.testing.assert_array_equal(seg.foreground, m)


def test_one_silhouette_is_one_object_even_when_tall() -> None:
    seg = find_objects(_person(200, 100, 30, 10, scale=3))
    assert seg.num_objects == 1
    assert np.isnan(seg.silhouette)


def test_fragments_close_to_each_other_are_one_object() -> None:
    m = _person(120, 200, 50, 20)
    m[62:64, :] = False  # the mask breaks across the legs: 2 px gap
    assert (np.diff(m[:, 52].astype(int)) != 0).sum() >= 2
    seg = find_objects(m)
    assert seg.num_objects == 1


def test_no_foreground_gives_no_objects() -> None:
    seg = find_objects(np.zeros((40, 50), bool))
    assert seg.num_objects == 0
    assert not seg.roi_mask().any()
    assert seg.labels.shape == (40, 50) and not seg.labels.any()


def test_more_regions_than_max_objects_are_grouped_by_kmeans() -> None:
    # Two clusters of three squares each, far apart: with k_max = 2 they form 2 objects.
    m = np.zeros((100, 300), bool)
    for x0 in (10, 200):
        for dx in (0, 30, 60):
            m |= square_mask(100, 300, x0 + dx, 40, 12)
    assert find_objects(m, ObjectConfig(max_objects=6)).num_objects == 6
    seg = find_objects(m, ObjectConfig(max_objects=2))
    assert seg.num_objects == 2
    assert seg.labels[45, 15] == seg.labels[45, 75] != seg.labels[45, 205]


def test_roi_is_bbox_plus_margin_clipped() -> None:
    m = square_mask(100, 100, 2, 40, 20)
    seg = find_objects(m, ObjectConfig(roi_margin_fraction=0.5, roi_margin_px=0))
    (obj,) = seg.objects
    assert obj.bbox == (2, 40, 20, 20)
    assert obj.roi == (0, 30, 32, 40)  # margin 10 px, clipped at x = 0
    assert obj.centroid == pytest.approx((11.5, 49.5))
    assert seg.roi_mask().sum() == 32 * 40


def test_silhouette_score_known_answer() -> None:
    pts = np.array([[0.0, 0.0], [0.0, 1.0], [10.0, 0.0], [10.0, 1.0]])
    # a = 1, b = mean(10, sqrt(101)) for every point
    b = (10.0 + np.sqrt(101.0)) / 2
    assert silhouette_score(pts, np.array([0, 0, 1, 1])) == pytest.approx((b - 1.0) / b)
    assert np.isnan(silhouette_score(pts, np.zeros(4, int)))
    # A bad clustering scores lower.
    assert silhouette_score(pts, np.array([0, 1, 0, 1])) < 0


def test_object_config_validation() -> None:
    with pytest.raises(ValueError, match="max_objects"):
        ObjectConfig(max_objects=0)


def test_small_fragment_joins_the_nearest_object_but_not_a_far_one() -> None:
    m = _person(200, 400, 100, 40, scale=2)  # ~1900 px
    foot = square_mask(200, 400, 150, 148, 4)  # 16 px, 18 px below the body
    far = square_mask(200, 400, 380, 10, 4)  # 16 px, far away
    seg = find_objects(m | foot)
    assert seg.num_objects == 1
    seg = find_objects(m | foot | far)
    assert seg.num_objects == 2
    assert seg.labels[150, 151] == seg.labels[60, 110] != seg.labels[11, 381]


def test_component_inside_another_ones_hole_does_not_crash() -> None:
    """Regression (two-person capture): a blob seen through a ring-shaped silhouette (arms
    around a hole) has no outer outline of its own; the run died in ``_component_gaps``."""
    m = np.zeros((120, 160), bool)
    m[20:100, 30:130] = True
    m[35:85, 45:115] = False  # the hole
    m[50:70, 70:90] = True  # another person's part, seen through it
    m[10:14, 150:154] = True  # a third, far fragment so that grouping runs
    seg = find_objects(m)
    assert seg.num_objects >= 1
    inner = seg.labels[60, 80]
    ring = seg.labels[25, 40]
    assert inner > 0 and ring > 0
    assert (seg.labels > 0).sum() == m.sum()


def test_component_gaps_are_the_nearest_outline_distances() -> None:
    """The compiled pairwise gaps against a k-d tree's nearest-neighbour distances between
    every two components' outline pixels (blobs of random shapes, one inside a hole)."""
    import cv2
    from scipy.spatial import cKDTree

    from edgerecon.scene.objects import _component_gaps

    rng = np.random.default_rng(3)
    m = np.zeros((180, 240), np.uint8)
    for _ in range(14):
        cv2.ellipse(
            m,
            (int(rng.integers(10, 230)), int(rng.integers(10, 170))),
            (int(rng.integers(2, 18)), int(rng.integers(2, 18))),
            float(rng.uniform(0, 180)),
            0,
            360,
            1,
            -1,
        )
    m[60:120, 100:160] = 1
    m[75:105, 115:145] = 0
    m[85:95, 125:135] = 1  # inside the hole: only an inner outline around it
    n, cc = cv2.connectedComponents(m, connectivity=8, ltype=cv2.CV_32S)
    assert n - 1 >= 5
    gaps = _component_gaps(cc, n - 1)
    contours, _ = cv2.findContours(m, cv2.RETR_LIST, cv2.CHAIN_APPROX_SIMPLE)
    pts = np.concatenate([c.reshape(-1, 2) for c in contours])
    owner = cc[pts[:, 1], pts[:, 0]] - 1
    for i in range(n - 1):
        tree = cKDTree(pts[owner == i])
        for j in range(n - 1):
            if i != j:
                assert gaps[i, j] == tree.query(pts[owner == j], k=1)[0].min()
    assert np.array_equal(gaps, gaps.T) and not np.diag(gaps).any()
