"""Sparse reconstruction on the real rigs in ../shared/data (skipped when absent)."""

import numpy as np
import pytest

from edgerecon.io.dataset import open_dataset
from edgerecon.sparse import SparseConfig, reconstruct_sparse
from edgerecon.views import prepare_views
from tests.conftest import shared_data

pytestmark = pytest.mark.shared_data

#: README.txt of templeSparseRing: the object's tight bounding box (metres).
TEMPLE_BOX = np.array([[-0.073568, 0.021728, -0.012445], [0.028855, 0.181892, 0.062736]])


def load_views(name, time_index, scale=1.0):
    ds = open_dataset(shared_data(name))
    with ds.open_frames() as frames:
        return ds.rig, prepare_views(frames.read(time_index), ds.rig, scale)


def test_utrecht4cam_frame_200_wide_baselines():
    # openMVG finds 0 landmarks here and COLMAP's matching + known-pose triangulation 3.
    _rig, views = load_views("utrecht4cam", 200)
    rec = reconstruct_sparse(views, SparseConfig())
    assert rec.num_points >= 60
    assert np.median(rec.reprojection_error_px) < 1.0
    # every camera takes part, and matches come from several pairs
    assert rec.visibility.any(axis=0).all()
    assert sum(n > 10 for n in rec.stats["matches_per_pair"].values()) >= 4
    # Most points lie in the room: between the floor (z = 0, up is -z) and 4 m above it.
    z = rec.points3D[:, 2]
    assert np.mean((z < 100) & (z > -4000)) > 0.75


def test_temple_points_inside_the_published_bounding_box():
    _rig, views = load_views("middlebury_templeSparseRing", 0)
    rec = reconstruct_sparse(views, SparseConfig())
    assert rec.num_points >= 1000
    margin = 0.005  # 5 mm (the object is ~10 x 16 x 7.5 cm)
    inside = np.all(
        (rec.points3D >= TEMPLE_BOX[0] - margin) & (rec.points3D <= TEMPLE_BOX[1] + margin), axis=1
    )
    assert inside.mean() > 0.93
    assert np.median(rec.reprojection_error_px) < 0.7
