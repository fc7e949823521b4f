"""reconstruct_dense flags exactly the points the ground-plane completion adds."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial import cKDTree

from edgerecon.dense import DenseConfig, reconstruct_dense
from edgerecon.views import View
from tests.conftest import ring_rig
from tests.dense.scene import Rect, box_scene, render

RIG = ring_rig(12, radius=4.0, height=2.0, width=320, height_px=240, focal_px=250.0)
IDS = (10, 11, 0, 1, 2)
pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")  # rays parallel to a rect


@pytest.fixture(scope="module")
def runs():
    """The box scene on a blank floor with four textured tiles (the plane is fitted to their
    stereo points), reconstructed with and without ground completion."""
    rects = box_scene()
    tex = rects[0].texture
    n = tex.shape[0]
    blank = np.full_like(tex, int(np.median(tex)))
    # Tiles of 0.6 m at (+-1.2, +-1.2) m: texel k is at 6 k / n - 3 m.
    for cx in (-1.2, 1.2):
        for cy in (-1.2, 1.2):
            r0, c0 = int((cy - 0.3 + 3) / 6 * n), int((cx - 0.3 + 3) / 6 * n)
            r1, c1 = r0 + n // 10, c0 + n // 10
            blank[r0:r1, c0:c1] = tex[r0:r1, c0:c1]
    rects[0] = Rect(rects[0].origin, rects[0].u, rects[0].v, blank)
    views = []
    for i in IDS:
        image, _ = render(RIG[i], rects)
        views.append(View(camera_id=i, camera=RIG[i], image=image))
    config = DenseConfig(resolution_level=0, num_threads=1)
    on = reconstruct_dense(views, config, up=(0, 0, 1))
    off = reconstruct_dense(
        views, dataclasses.replace(config, ground_completion=False), up=(0, 0, 1)
    )
    return on, off


def test_inferred_points_are_the_completed_ones(runs):
    on, off = runs
    cloud = on.cloud
    plane = on.stats["ground_plane"]
    assert plane is not None
    flag = cloud.inferred
    assert flag.sum() > 200  # the blank band was completed ...
    assert on.stats["inferred_points"] == flag.sum() == on.stats["ground"]["completed_points"]
    assert on.stats["ground"]["completed_depths"] >= flag.sum()
    # ... every inferred point lies exactly on the fitted plane ...
    h = cloud.points3D @ np.asarray(plane["normal"]) - plane["offset"]
    assert np.abs(h[flag]).max() < 1e-6
    # ... and on the floor's blank part: never under the cube (its textured sides do not
    # match the floor's pattern), on the textured tiles only at a few pixels stereo left
    # (the pattern test confirms them; they lie on the floor too).
    P = cloud.points3D[flag]
    tile = (np.abs(np.abs(P[:, 0]) - 1.2) < 0.28) & (np.abs(np.abs(P[:, 1]) - 1.2) < 0.28)
    cube = (np.abs(P[:, 0]) < 0.38) & (np.abs(P[:, 1]) < 0.38)
    assert not cube.any()
    assert tile.sum() < 0.005 * len(P)
    # Without completion nothing is inferred; completion leaves the measured points alone
    # (the same voxels, the same positions) except those it drops below the plane.
    assert off.cloud.num_inferred == 0 and "inferred" in off.cloud.attributes
    measured = cloud.points3D[~flag]
    d, _ = cKDTree(off.cloud.points3D).query(measured)
    assert np.mean(d < 1e-9) > 0.995
    band = 3.0 * on.stats["voxel_size"]
    hoff = off.cloud.points3D @ np.asarray(plane["normal"]) - plane["offset"]
    expected = int((hoff >= -band).sum())  # completion drops stereo points below the plane
    assert abs(len(measured) - expected) <= 0.002 * expected


def test_voxel_grid_is_fixed_in_the_world():
    # Fusion's voxels do not depend on which other points are fused: a subset keyed alone
    # is partitioned as it is within the whole (completion never moves measured points).
    from edgerecon.dense import kernels

    X = np.random.default_rng(0).uniform(-2, 3, (20000, 3))
    whole = kernels.voxel_keys(X, 0.05)
    part = kernels.voxel_keys(X[::3] + 0.0, 0.05)
    _, a = np.unique(whole[::3], return_inverse=True)
    _, b = np.unique(part, return_inverse=True)
    np.testing.assert_array_equal(a, b)
    # Corners at multiples of the edge: points just either side of 0.05 differ.
    k = kernels.voxel_keys(np.array([[0.0499, 0, 0], [0.0501, 0, 0], [0.0, 0, 0]]), 0.05)
    assert k[0] == k[2] != k[1]
