import math

import numpy as np
import pytest

from edgerecon.quality import evaluate_clouds, fscore
from edgerecon.types import PointCloud


def grid(n=20, spacing=0.01):
    g = np.stack(np.meshgrid(*[np.arange(n) * spacing] * 2, indexing="ij"), -1).reshape(-1, 2)
    return np.hstack([g, np.zeros((len(g), 1))])


def test_identical_clouds_score_one():
    pts = grid()
    (s,) = evaluate_clouds(pts, pts, 0.001)
    assert s.precision == s.recall == s.fscore == 1.0
    assert s.accuracy_mean == 0.0 and s.completeness_median == 0.0


def test_shift_beyond_threshold_scores_zero():
    pts = grid()
    shifted = pts + [0, 0, 0.05]
    s1, s2 = evaluate_clouds(shifted, pts, [0.01, 0.06])
    assert s1.fscore == 0.0
    assert s2.fscore == 1.0
    assert s1.accuracy_mean == pytest.approx(0.05)


def test_partial_overlap_precision_recall():
    ref = grid()  # 400 points
    pred = ref[:100]
    (s,) = evaluate_clouds(pred, ref, 0.001)
    assert s.precision == 1.0
    assert s.recall == pytest.approx(0.25)
    assert s.fscore == pytest.approx(2 * 0.25 / 1.25)
    outliers = np.vstack([pred, pred[:50] + [0, 0, 1.0]])
    (s,) = evaluate_clouds(outliers, ref, 0.001)
    assert s.precision == pytest.approx(100 / 150)


def test_empty_clouds_have_defined_scores():
    pts = grid(5)
    empty = np.zeros((0, 3))
    (s,) = evaluate_clouds(empty, pts, 0.01)
    assert (s.precision, s.recall, s.fscore) == (1.0, 0.0, 0.0)
    assert math.isinf(s.accuracy_mean) and s.to_dict()["accuracy_mean"] is None
    (s,) = evaluate_clouds(pts, empty, 0.01)
    assert (s.precision, s.recall, s.fscore) == (0.0, 1.0, 0.0)
    assert fscore(PointCloud.empty(), PointCloud.empty(), 0.01) == 1.0


def test_rejects_bad_threshold_and_nan():
    with pytest.raises(ValueError, match="threshold"):
        evaluate_clouds(grid(3), grid(3), 0.0)
    bad = grid(3)
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        evaluate_clouds(bad, grid(3), 0.1)


def test_distance_cutoff_is_exact_below_and_a_bounded_estimate_beyond():
    from edgerecon.quality.metrics import FAR_ERROR, evaluate_against, nearest_distances

    ref = np.zeros((1, 3))
    pred = np.array([[0.0, 0, 0.005], [0, 0, 10.0]])
    free = evaluate_clouds(pred, ref, 0.01)[0]
    cut = evaluate_clouds(pred, ref, 0.01, max_distance=1.0)[0]
    assert free.precision == cut.precision == 0.5 and free.recall == cut.recall == 1.0
    assert free.accuracy_mean == pytest.approx((0.005 + 10) / 2) == cut.accuracy_mean
    assert cut.max_distance == 1.0
    # A dense wall and points up to 3 m in front of it: exact up to the cut-off (0.1),
    # beyond it never below the truth and at most FAR_ERROR x 0.1 above it.
    rng = np.random.default_rng(0)
    wall = np.c_[rng.uniform(-2, 2, (40000, 2)), np.zeros(40000)]
    q = np.c_[rng.uniform(-1, 1, (500, 2)), rng.uniform(0, 3, 500)]
    exact = nearest_distances(q, wall)
    est = nearest_distances(q, wall, max_distance=0.1)
    near = exact <= 0.1
    np.testing.assert_array_equal(est[near], exact[near])
    assert np.all(est[~near] >= exact[~near] - 1e-12)
    assert np.all(est[~near] <= exact[~near] + FAR_ERROR * 0.1 + 1e-12)
    # Several references share the prediction's tree and give the same answers.
    a, b = evaluate_against(pred, [ref, ref + [0, 0, 10]], [0.01], max_distance=1.0)
    assert a[0] == cut and b[0].precision == 0.5
    with pytest.raises(ValueError, match="max_distance"):
        evaluate_clouds(pred, ref, 0.01, max_distance=0.001)


def test_nested_evaluation_equals_separate_ones():
    from edgerecon.quality.metrics import evaluate_against, evaluate_nested

    rng = np.random.default_rng(3)
    ref = rng.uniform(0, 1, (30000, 3))
    pred = ref[rng.integers(0, len(ref), 20000)] + rng.normal(0, 0.01, (20000, 3))
    pred[:500] += 2.0  # far points: estimates
    subset = rng.random(len(ref)) < 0.6
    nested = evaluate_nested(pred, ref, [subset], [0.01, 0.02], max_distance=0.02)
    separate = evaluate_against(pred, [ref, ref[subset]], [0.01, 0.02], max_distance=0.02)
    for a, b in zip(nested, separate, strict=True):
        for x, y in zip(a, b, strict=True):
            assert x.precision == y.precision and x.recall == y.recall
            assert x.accuracy_median == pytest.approx(y.accuracy_median)
            assert x.completeness_mean == pytest.approx(y.completeness_mean)
