"""Depth ranges of reference views: from sparse points, from given bounds, or from the
geometry of the rig (where the view frusta overlap).

A depth range ``(near, far)`` is along the reference camera's optical axis, in rig units.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry.camera import Camera

logger = logging.getLogger(__name__)

DepthRange = tuple[float, float]


def scene_scale(cameras: Sequence[Camera]) -> float:
    """Median distance between the camera centres (the rig's natural length scale)."""
    c = np.array([cam.center for cam in cameras])
    if len(c) < 2:
        return 1.0
    d = np.linalg.norm(c[:, None] - c[None], axis=2)
    value = float(np.median(d[np.triu_indices(len(c), 1)]))
    return value if value > 0 else 1.0


def range_from_points(
    camera: Camera, points3D: NDArray[np.float64], margin_rel: float, min_points: int
) -> DepthRange | None:
    """Depth range of the points that project into ``camera``'s image in front of it, from
    their 1st to 99th depth percentiles widened by ``margin_rel``; None if fewer than
    ``min_points`` qualify."""
    if len(points3D) == 0:
        return None
    uv, depth = camera.project(points3D)
    ok = (depth > 0) & camera.in_image(uv)
    if int(ok.sum()) < min_points:
        return None
    lo, hi = np.percentile(depth[ok], [1.0, 99.0])
    near = float(lo) * (1.0 - margin_rel)
    far = float(hi) * (1.0 + margin_rel)
    if not (near > 0 and far > near):
        return None
    return near, far


def sample_pixels(camera: Camera, nx: int = 12, ny: int = 9) -> NDArray[np.float64]:
    """(nx * ny, 2) pixels on a regular grid inside the image (5 % margin)."""
    xs = np.linspace(0.05, 0.95, nx) * (camera.width - 1)
    ys = np.linspace(0.05, 0.95, ny) * (camera.height - 1)
    gx, gy = np.meshgrid(xs, ys)
    return np.stack([gx.ravel(), gy.ravel()], axis=1)


def frustum_range(
    camera: Camera,
    others: Sequence[Camera],
    max_depth: float,
    min_rel_baseline: float = 0.3,
    num_depths: int = 96,
    min_views: int = 2,
) -> DepthRange | None:
    """Depths at which the reference's rays are seen by at least ``min_views`` other cameras
    (fewer when the rig has fewer: rings of many cameras then keep only the shared core).

    Samples a pixel grid and log-spaced depths up to ``max_depth``; returns the smallest and
    largest visible depth (None when no other camera sees any sample). Depths below
    ``min_rel_baseline`` times the median distance to the other cameras are excluded: in a rig
    whose cameras see each other, the space right in front of a lens is geometrically visible
    but never holds the scene, and including it would multiply the sweep planes."""
    if not others:
        return None
    typical = float(np.median([np.linalg.norm(o.center - camera.center) for o in others]))
    pix = sample_pixels(camera)
    rays = camera.pixel_rays(pix)  # (P, 3) camera frame, z = 1
    depths = np.geomspace(max_depth * 1e-3, max_depth, num_depths)
    Xc = rays[None, :, :] * depths[:, None, None]  # (D, P, 3)
    Xw = (Xc.reshape(-1, 3) - camera.t) @ camera.R
    count = np.zeros(len(Xw), dtype=np.int32)
    for other in others:
        uv, z = other.project(Xw)
        count += (z > 0) & other.in_image(uv)
    need = max(1, min(min_views, len(others) - 1))
    seen2 = (count >= need).reshape(len(depths), len(pix))
    rows = np.nonzero(seen2.any(axis=1))[0]
    if len(rows) == 0:
        return None
    near = float(depths[rows[0] - 1]) if rows[0] > 0 else float(depths[0])
    near = max(near, min_rel_baseline * typical)
    far = float(depths[rows[-1]])
    if far <= near:
        return None
    return near, far
