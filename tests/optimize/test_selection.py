"""Camera selection (P2): exact solvers against a naive enumeration and each other, tie-breaks,
the no-point fallbacks, large-N behaviour and input errors."""

from __future__ import annotations

import json
import math
from itertools import combinations

import numpy as np
import pytest

from edgerecon.optimize import (
    CameraMapping,
    CameraSelector,
    SelectionConfig,
    aggregate_patterns,
    camera_mapping,
    coverage,
    geometric_visibility,
    random_visibility,
    reduce_patterns_kmeans,
    select_cameras,
    synthetic_visibility,
    visibility_from_points,
)
from edgerecon.types import DataError
from tests.conftest import ring_rig


def naive_best(vis: np.ndarray, k: int, min_views: int = 2) -> tuple[int, tuple[int, ...]]:
    """Reference: every subset in lexicographic order, first maximum wins."""
    best, best_ids = -1, ()
    for ids in combinations(range(vis.shape[1]), k):
        cov = int(np.count_nonzero(vis[:, list(ids)].sum(axis=1) >= min_views))
        if cov > best:
            best, best_ids = cov, ids
    return best, best_ids


def random_instance(rng: np.random.Generator, max_n: int = 10, max_p: int = 60) -> np.ndarray:
    n = int(rng.integers(3, max_n + 1))
    p = int(rng.integers(0, max_p + 1))
    return rng.random((p, n)) < rng.uniform(0.1, 0.7)


def test_known_answer_small_matrix():
    # cameras 0,1 share 3 points, 2,3 share 2, camera 4 sees nothing useful
    vis = np.array(
        [
            [1, 1, 0, 0, 0],
            [1, 1, 0, 0, 0],
            [1, 1, 1, 0, 0],
            [0, 0, 1, 1, 0],
            [0, 0, 1, 1, 0],
            [0, 0, 0, 0, 1],
        ],
        bool,
    )
    m = camera_mapping(vis)
    assert m(3) == (0, 1, 2)  # 3 points; (0,1,x) ties at 3 for x in {2,3,4}: lowest ids
    assert m.selection(3).covered == 3
    assert m(4) == (0, 1, 2, 3)
    assert m.selection(4).covered == 5
    assert m(5) == (0, 1, 2, 3, 4)
    assert m.num_coverable == 5
    assert m.coverage_fraction(3) == pytest.approx(0.6)
    assert m.sizes == [5, 4, 3]


def test_brute_force_matches_naive_on_hundreds_of_instances():
    rng = np.random.default_rng(0)
    for _ in range(300):
        vis = random_instance(rng)
        sel = CameraSelector(vis, SelectionConfig(solver="brute_force"))
        for k in range(3, vis.shape[1] + 1):
            cov, ids = naive_best(vis, k)
            s = sel.selection(k)
            assert (s.covered, s.camera_ids) == (cov, ids)
            assert s.optimal and s.solver == "brute_force"
            assert coverage(vis, s.camera_ids) == s.covered


@pytest.mark.parametrize("solver", ["cpsat", "milp", "enumerate"])
def test_exact_solvers_agree_with_brute_force(solver):
    rng = np.random.default_rng({"cpsat": 1, "milp": 2, "enumerate": 3}[solver])
    for _ in range(120):
        vis = random_instance(rng, max_n=12 if solver != "milp" else 9, max_p=40)
        n = vis.shape[1]
        k = int(rng.integers(3, n + 1))
        ref = CameraSelector(vis, SelectionConfig(solver="brute_force")).selection(k)
        s = CameraSelector(vis, SelectionConfig(solver=solver, max_key_points=0)).selection(k)
        assert s.covered == ref.covered, (solver, vis.shape, k)
        assert s.camera_ids == ref.camera_ids, (solver, vis.shape, k)  # same tie-break
        assert s.optimal


def test_milp_strong_formulation_is_exact_too():
    rng = np.random.default_rng(7)
    cfg = SelectionConfig(solver="milp", milp_formulation="strong", max_key_points=0)
    for _ in range(30):
        vis = random_instance(rng, max_n=8, max_p=30)
        k = int(rng.integers(3, vis.shape[1] + 1))
        ref = naive_best(vis, k)
        s = select_cameras(vis, k, cfg)
        assert (s.covered, s.camera_ids) == ref


def test_min_views_three():
    rng = np.random.default_rng(4)
    for _ in range(40):
        vis = random_instance(rng, max_n=8, max_p=40)
        k = int(rng.integers(3, vis.shape[1] + 1))
        s = select_cameras(vis, k, SelectionConfig(min_views=3))
        assert (s.covered, s.camera_ids) == naive_best(vis, k, min_views=3)


def test_local_search_is_near_optimal_and_never_above_optimum():
    rng = np.random.default_rng(5)
    gaps = []
    for seed in range(10):
        vis = synthetic_visibility(14, 1500, seed=seed)[0]
        exact = CameraSelector(vis, SelectionConfig(solver="brute_force"))
        ls = CameraSelector(vis, SelectionConfig(solver="local_search"))
        for k in (4, 7, 10):
            e, h = exact.selection(k).covered, ls.selection(k).covered
            assert h <= e
            gaps.append(1 - h / e)
    assert max(gaps) < 0.03
    assert np.mean(gaps) < 0.005
    _ = rng


def test_auto_above_brute_force_limit_uses_heuristics_within_two_percent():
    vis = synthetic_visibility(21, 3000, seed=11)[0]
    exact = CameraSelector(
        vis, SelectionConfig(solver="brute_force", brute_force_max_cameras=22)
    ).mapping()
    auto = CameraSelector(vis, SelectionConfig(brute_force_max_cameras=20))
    for k in (3, 6, 10, 15, 20):
        s = auto.selection(k)
        ref = exact.selection(k)
        assert s.solver in ("enumerate", "local_search")
        if s.solver == "enumerate":  # exact: identical answer
            assert (s.covered, s.camera_ids) == (ref.covered, ref.camera_ids)
        assert s.covered >= 0.98 * ref.covered
        assert s.covered <= ref.covered


def test_keypoint_reduction_is_used_by_the_ilp_and_never_hurts():
    vis = synthetic_visibility(16, 3000, seed=2)[0]
    pat = aggregate_patterns(vis)
    assert pat.num_patterns > 64
    cfg = SelectionConfig(solver="cpsat", max_key_points=64)
    sel = CameraSelector(vis, cfg)
    ls = CameraSelector(vis, SelectionConfig(solver="local_search"))
    for k in (5, 9):
        s = sel.selection(k)
        assert s.solver == "cpsat+keypoints"
        assert not s.optimal or s.covered == pat.total_weight
        assert s.covered >= ls.selection(k).covered  # the full-data local search competes
    assert sel.mapping([5, 9]).num_key_points == 64


def test_kmeans_reduction_properties():
    vis = random_visibility(12, 2000, 0.3, seed=3)
    pat = aggregate_patterns(vis)
    red = reduce_patterns_kmeans(pat, 50, seed=0)
    assert red.num_patterns <= 50
    assert red.total_weight == pat.total_weight  # every point lands in one key pattern
    again = reduce_patterns_kmeans(pat, 50, seed=0)
    assert np.array_equal(red.masks, again.masks) and np.array_equal(red.weights, again.weights)
    assert reduce_patterns_kmeans(pat, pat.num_patterns) is pat  # nothing to reduce


def test_aggregation_counts_and_drops_uncoverable_rows():
    vis = np.array([[1, 1, 0], [1, 1, 0], [0, 1, 1], [1, 0, 0], [0, 0, 0]], bool)
    pat = aggregate_patterns(vis)
    assert pat.num_patterns == 2
    assert sorted(pat.weights.tolist()) == [1, 2]
    assert pat.total_weight == 3


def test_available_cameras_restrict_the_choice():
    rng = np.random.default_rng(8)
    vis = rng.random((300, 8)) < 0.4
    vis[:, 2] = True  # camera 2 sees everything: the best camera, but it is unavailable
    avail = [0, 1, 3, 4, 5, 6, 7]
    m = camera_mapping(vis, available=avail)
    assert m.candidates == tuple(avail)
    assert max(m.sizes) == 7
    sub = vis[:, avail]
    for k in m.sizes:
        assert 2 not in m(k)
        cov, ids = naive_best(sub, k)
        assert m.selection(k).covered == cov
        assert m(k) == tuple(avail[i] for i in ids)


def test_no_points_with_geometry_uses_virtual_orientations():
    rig = ring_rig(8)
    centers = rig.centers
    dirs = np.array([c.viewing_direction for c in rig])
    m = camera_mapping(np.zeros((0, 8), bool), camera_centers=centers, viewing_directions=dirs)
    assert m.criterion == "geometric"
    geo = camera_mapping(geometric_visibility(centers, dirs))
    for k in (3, 4, 5):
        assert m(k) == geo(k)
        assert m.selection(k).covered > 0
        # two-view coverage: no chosen camera is useless, i.e. more than 90 degrees (two ring
        # steps) from every other chosen camera
        ids = set(m(k))
        assert all(any((i + d) % 8 in ids for d in (-2, -1, 1, 2)) for i in ids)


def test_points_seen_once_count_as_no_points():
    vis = np.eye(5, dtype=bool)  # every point seen by a single camera
    m = camera_mapping(vis)
    assert m.criterion == "none"
    assert m(3) == (0, 1, 2)
    assert m.selection(3).covered == 0


def test_no_points_no_geometry_picks_lowest_ids(caplog):
    with caplog.at_level("WARNING"):
        m = camera_mapping(np.zeros((0, 6), bool))
    assert m.criterion == "none"
    assert [m(k) for k in (3, 4)] == [(0, 1, 2), (0, 1, 2, 3)]
    assert "ties" in caplog.text


def test_geometric_visibility_shape_and_facing():
    rig = ring_rig(5)
    vis = geometric_visibility(rig.centers, np.array([c.viewing_direction for c in rig]))
    assert vis.shape == (512, 5)
    assert 0.1 < vis.mean() < 0.6
    # a camera looking away from the scene sees nothing
    dirs = np.array([c.viewing_direction for c in rig])
    dirs[0] = -dirs[0]
    assert not geometric_visibility(rig.centers, dirs)[:, 0].any()


def test_visibility_from_points_projection_and_normals():
    rig = ring_rig(4)
    pts = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 100.0]])  # centre of the scene; far above
    vis = visibility_from_points(pts, list(rig))
    assert vis[0].all()
    assert not vis[1].any()
    # a normal facing camera 0 only: cameras around the ring see the point's back side
    c0 = rig[0].center - pts[0]
    n0 = c0 / np.linalg.norm(c0)
    vis_n = visibility_from_points(pts[:1], list(rig), normals=n0[None], max_angle_deg=60)
    assert vis_n[0, 0] and not vis_n[0, 2]


def test_mapping_roundtrip_and_reproducibility():
    vis = synthetic_visibility(24, 2000, seed=1)[0]
    cfg = SelectionConfig()
    a = camera_mapping(vis, cfg, sizes=[3, 8, 12])
    b = camera_mapping(vis, cfg, sizes=[3, 8, 12])
    assert [a(k) for k in a.sizes] == [b(k) for k in b.sizes]
    c = CameraMapping.from_dict(json.loads(json.dumps(a.to_dict())))
    assert [c(k) for k in c.sizes] == [a(k) for k in a.sizes]
    assert c.selection(8).covered == a.selection(8).covered
    with pytest.raises(ValueError, match="no camera subset of size 5"):
        a(5)


def test_brute_force_handles_twenty_cameras_fast():
    vis = synthetic_visibility(20, 5000, seed=4)[0]
    m = camera_mapping(vis)
    assert m.sizes == list(range(20, 2, -1))
    assert all(m.selection(k).solver == "brute_force" for k in m.sizes)
    covered = [m.selection(k).covered for k in sorted(m.sizes)]
    assert covered == sorted(covered)  # more cameras never cover fewer points


def test_bad_inputs_are_clear_errors():
    with pytest.raises(DataError, match="2-D"):
        camera_mapping(np.zeros(5, bool))
    with pytest.raises(DataError, match="0/1"):
        camera_mapping(np.full((3, 4), 2))
    with pytest.raises(DataError, match="at least 3 available cameras"):
        camera_mapping(np.ones((3, 4), bool), available=[0, 1])
    with pytest.raises(DataError, match="out of range"):
        camera_mapping(np.ones((3, 4), bool), available=[0, 1, 7])
    with pytest.raises(ValueError, match="out of range"):
        select_cameras(np.ones((3, 4), bool), 5)
    with pytest.raises(ValueError, match="solver"):
        SelectionConfig(solver="gurobi")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="max_key_points"):
        SelectionConfig(max_key_points=1)
    with pytest.raises(ValueError, match="brute force over"):
        CameraSelector(np.ones((2, 27), bool), SelectionConfig(solver="brute_force")).selection(3)
    assert math.isfinite(SelectionConfig().time_limit_s)
