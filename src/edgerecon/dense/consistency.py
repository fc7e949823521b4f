"""Cross-view geometric consistency of depth maps.

A depth of view i at pixel p is supported by view j when the 3D point it defines projects
into j's image in front of j, and j's own depth at that pixel (nearest) agrees with the
point's depth in j within a relative tolerance. Depths with too few supporting views are
outliers (mismatches, occlusion artefacts) and are dropped before fusion.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry.camera import Camera
from edgerecon.types import DepthMap


def backproject_depth(
    camera: Camera, depth: DepthMap, rows: NDArray[np.intp], cols: NDArray[np.intp]
) -> NDArray[np.float64]:
    """(N, 3) world points of the pixels (rows, cols) of an undistorted depth map."""
    Kinv = np.linalg.inv(camera.K)
    z = depth[rows, cols].astype(np.float64)
    x = (Kinv[0, 0] * cols + Kinv[0, 1] * rows + Kinv[0, 2]) * z
    y = (Kinv[1, 1] * rows + Kinv[1, 2]) * z
    Xc = np.stack([x, y, z], axis=1)
    return (Xc - camera.t) @ camera.R


def support_counts(
    depths: Mapping[int, DepthMap], cameras: Mapping[int, Camera], rel_tol: float
) -> dict[int, NDArray[np.int16]]:
    """Per view, an (H, W) map of how many *other* views support each depth (0 where the
    view has no depth)."""
    out: dict[int, NDArray[np.int16]] = {}
    for i, depth_i in depths.items():
        count = np.zeros(depth_i.shape, np.int16)
        rows, cols = np.nonzero(depth_i > 0)
        if len(rows) == 0:
            out[i] = count
            continue
        X = backproject_depth(cameras[i], depth_i, rows, cols)
        support = np.zeros(len(rows), np.int16)
        for j, depth_j in depths.items():
            if j == i:
                continue
            support += agrees(X, cameras[j], depth_j, rel_tol)
        count[rows, cols] = support
        out[i] = count
    return out


def agrees(
    points3D: NDArray[np.float64], camera: Camera, depth: DepthMap, rel_tol: float
) -> NDArray[np.bool_]:
    """(N,) True where ``depth`` (of ``camera``) confirms the point's depth within rel_tol."""
    uv, z = camera.project(points3D)
    with np.errstate(invalid="ignore"):
        c = np.rint(uv[:, 0])
        r = np.rint(uv[:, 1])
        inside = (z > 0) & (c >= 0) & (c < camera.width) & (r >= 0) & (r < camera.height)
    ok = np.zeros(len(points3D), dtype=bool)
    idx = np.nonzero(inside)[0]
    d = depth[r[idx].astype(np.intp), c[idx].astype(np.intp)].astype(np.float64)
    ok[idx] = (d > 0) & (np.abs(d - z[idx]) <= rel_tol * z[idx])
    return ok
