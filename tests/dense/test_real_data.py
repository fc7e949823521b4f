"""Dense reconstruction of the real datasets in ../shared/data (skipped when absent)."""

from __future__ import annotations

import numpy as np
import pytest

from edgerecon.dense import DenseConfig, reconstruct_dense
from edgerecon.io.dataset import open_dataset
from edgerecon.views import prepare_views
from tests.conftest import shared_data

pytestmark = pytest.mark.shared_data

#: The temple's published tight bounding box (README.txt of templeSparseRing), metres.
TEMPLE_BOX = (np.array([-0.073568, 0.021728, -0.012445]), np.array([0.028855, 0.181892, 0.062736]))


def _views(name: str, t: int, camera_ids=None, scale: float = 1.0):
    ds = open_dataset(shared_data(name))
    with ds.open_frames() as source:
        frames = source.read(t)
    return ds, prepare_views(frames, ds.rig, scale, camera_ids=camera_ids)


def test_temple_points_lie_on_the_object():
    ds, views = _views("middlebury_templeSparseRing", 0, camera_ids=list(range(0, 16, 2)))
    res = reconstruct_dense(views, DenseConfig(), up=ds.rig.up)
    P = res.cloud.points3D
    lo, hi = TEMPLE_BOX
    inside = np.all((P >= lo) & (P <= hi), axis=1)
    assert len(P) > 30_000
    # The rest is mostly the dark support surface under the temple and silhouette fringes.
    assert inside.mean() > 0.6
    assert inside.sum() > 25_000


def test_utrecht_floor_is_flat_and_the_person_is_there():
    ds, views = _views("utrecht4cam", 200)
    res = reconstruct_dense(views, DenseConfig(), up=ds.rig.up)
    P = res.cloud.points3D
    z = P[:, 2]  # millimetres, the board's Z points down: the floor is z = 0
    floor = np.abs(z) < 100
    assert floor.sum() > 5000
    assert np.median(np.abs(z[floor])) < 40
    # Stereo alone (confidence > 0) already finds some floor, and nothing hangs below it.
    assert np.sum(floor & (res.cloud.confidence > 0)) > 300
    assert np.mean(z > 100) < 0.01
    # The seated person (0.3-1.7 m above the floor, around x = 0.3 m, y = -0.1 m).
    person = (z < -300) & (z > -1800) & (np.linalg.norm(P[:, :2] - [300, -70], axis=1) < 700)
    assert person.sum() > 300
