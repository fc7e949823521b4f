"""Camera selection on the visibility matrix of a real sparse cloud (Middlebury temple ring,
16 views; skipped when ../shared/data is absent)."""

from __future__ import annotations

import numpy as np
import pytest

from edgerecon.io.dataset import open_dataset
from edgerecon.optimize import CameraSelector, SelectionConfig, aggregate_patterns
from edgerecon.optimize import selection as sel
from edgerecon.sparse import reconstruct_sparse
from edgerecon.views import prepare_views
from tests.conftest import shared_data


@pytest.fixture(scope="module")
def temple_visibility() -> np.ndarray:
    ds = open_dataset(shared_data("middlebury_templeSparseRing"))
    with ds.open_frames() as frames:
        fs = frames.read(0)
    rec = reconstruct_sparse(prepare_views(fs, ds.rig, 0.5))
    return rec.visibility_matrix(len(ds.rig))


@pytest.mark.shared_data
def test_exact_and_heuristic_solvers_on_a_real_sparse_cloud(temple_visibility):
    vis = temple_visibility
    assert vis.shape[1] == 16 and vis.shape[0] > 200
    exact = CameraSelector(vis).mapping()
    assert exact.criterion == "visibility"
    assert exact(16) == tuple(range(16))
    covered = [exact.selection(k).covered for k in range(3, 17)]
    assert covered == sorted(covered) and covered[-1] == exact.num_coverable
    cpsat = CameraSelector(
        vis, SelectionConfig(solver="cpsat", max_key_points=0, cpsat_work_limit=None)
    )
    ls = CameraSelector(vis, SelectionConfig(solver="local_search"))
    for k in (3, 6, 10):
        assert cpsat.selection(k).camera_ids == exact(k)  # same optimum, same tie-break
        assert ls.selection(k).covered >= 0.98 * exact.selection(k).covered


@pytest.mark.shared_data
def test_kmeans_key_points_lose_little_on_a_real_sparse_cloud(temple_visibility):
    full = aggregate_patterns(temple_visibility)
    exact = sel._brute_force_all(full, 2)
    worst = {}
    for kp in (64, 128):
        red = sel.reduce_patterns_kmeans(full, kp)
        approx = sel._brute_force_all(red, 2)
        worst[kp] = max(
            1 - sel._pattern_coverage(full, approx[k][0], 2) / exact[k][1] for k in range(3, 17)
        )
    assert worst[128] < 0.02  # measured 0.55 % (139 distinct patterns, 638 points at r = 0.5)
    assert worst[64] < 0.06  # measured 4.0 %
    # the default budget (256) holds every distinct pattern of a real cloud: no loss at all
    assert sel.reduce_patterns_kmeans(full, 256) is full or full.num_patterns > 256
