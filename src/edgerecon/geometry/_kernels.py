"""Compiled (numba) rigid transforms and projection of points to pixels.

``Camera.project`` is called thousands of times per task by the scene stage (hull voxels,
photo-check samples, splats) on 10^4-10^5 points; in NumPy the perspective division, the
Brown-Conrady distortion and the intrinsics take ~25 passes over full-length temporaries.
Fused here into one pass per point (the rigid transform included, no camera-frame array),
with NumPy's operation order and no fastmath, so the pixels are the NumPy code's bit for bit
(tested).

The rigid transform is a loop too, not ``points @ R.T``: OpenBLAS runs that (N, 3) x (3, 3)
product on its own threads, which then spin waiting for the next call, on a 2-core machine
against the scene stage's and the other role's threads (caliscope_charuco at 1920x1080: the
scene stage's CPU 990 -> 793 ms per task, wall 642 -> 572 ms).
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

_Rows = tuple[float, float, float, float, float, float, float, float, float, float, float, float]


@nb.njit(inline="always")
def _rows(R: NDArray[np.float64], t: NDArray[np.float64]) -> _Rows:
    """R's and t's entries as scalars (the loops keep them in registers)."""
    return (
        R[0, 0], R[0, 1], R[0, 2], t[0],
        R[1, 0], R[1, 1], R[1, 2], t[1],
        R[2, 0], R[2, 1], R[2, 2], t[2],
    )  # fmt: skip


@nb.njit(inline="always")
def _transform(m: _Rows, x: float, y: float, z: float) -> tuple[float, float, float]:
    """``R @ (x, y, z) + t``, each row summed left to right (NumPy's
    ``R[:, 0] * x + R[:, 1] * y + R[:, 2] * z + t`` bit for bit)."""
    return (
        m[0] * x + m[1] * y + m[2] * z + m[3],
        m[4] * x + m[5] * y + m[6] * z + m[7],
        m[8] * x + m[9] * y + m[10] * z + m[11],
    )


@nb.njit(inline="always")
def _intrinsics(
    K: NDArray[np.float64], dist: NDArray[np.float64]
) -> tuple[tuple[float, float, float, float, float], tuple[float, float, float, float, float]]:
    """K's (0,0), (0,1), (0,2), (1,1), (1,2) and k1, k2, p1, p2, k3 as scalars."""
    return (K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]), (
        dist[0],
        dist[1],
        dist[2],
        dist[3],
        dist[4],
    )


@nb.njit(inline="always", error_model="numpy")
def _pixel(
    x: float,
    y: float,
    depth: float,
    k: tuple[float, float, float, float, float],
    d: tuple[float, float, float, float, float],
    distorted: bool,
) -> tuple[float, float]:
    """The pixel of one camera-frame point (NaN when not in front of the camera): divided by
    depth, distorted (``distorted``: the ``_intrinsics``' k1, k2, p1, p2, k3), through K.
    Points near the camera's plane give inf / NaN pixels, as in NumPy."""
    if not depth > 0:
        return np.nan, np.nan
    xn = x / depth
    yn = y / depth
    if distorted:
        k1, k2, p1, p2, k3 = d
        r2 = xn * xn + yn * yn
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
        yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
        xn, yn = xd, yd
    return k[0] * xn + k[1] * yn + k[2], k[3] * yn + k[4]


@nb.njit(nogil=True, cache=True)
def rigid_transform(
    pts: NDArray[np.float64],
    R: NDArray[np.float64],
    t: NDArray[np.float64],
    out: NDArray[np.float64],
) -> None:
    """``out = pts @ R.T + t`` for (N, 3) ``pts`` (``_transform`` per row)."""
    m = _rows(R, t)
    for i in range(pts.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = _transform(m, pts[i, 0], pts[i, 1], pts[i, 2])


@nb.njit(nogil=True, cache=True, error_model="numpy")
def project_world_points(
    pts: NDArray[np.float64],
    R: NDArray[np.float64],
    t: NDArray[np.float64],
    K: NDArray[np.float64],
    dist: NDArray[np.float64],
    distorted: bool,
    uv: NDArray[np.float64],
    depth: NDArray[np.float64],
) -> None:
    """The (N, 3) world points ``pts`` through the camera (R, t, K, dist): pixels to ``uv``
    (N, 2), NaN for points not in front of it, depths along its axis to ``depth`` (N,)."""
    m = _rows(R, t)
    k, d = _intrinsics(K, dist)
    for i in range(pts.shape[0]):
        xc, yc, zc = _transform(m, pts[i, 0], pts[i, 1], pts[i, 2])
        uv[i, 0], uv[i, 1] = _pixel(xc, yc, zc, k, d, distorted)
        depth[i] = zc


@nb.njit(nogil=True, cache=True, error_model="numpy")
def nearest_pixels_world(
    pts: NDArray[np.float64],
    R: NDArray[np.float64],
    t: NDArray[np.float64],
    K: NDArray[np.float64],
    dist: NDArray[np.float64],
    distorted: bool,
    width: int,
    height: int,
    uv: NDArray[np.float64],
    depth: NDArray[np.float64],
    u: NDArray[np.intp],
    v: NDArray[np.intp],
    inside: NDArray[np.bool_],
) -> None:
    """``project_world_points``, then whether each pixel lies in the image in front of the
    camera (``Camera.in_image``'s bounds) and its nearest pixel (rounded half to even,
    clipped into the image; (0, 0) for a point not inside), in the same pass."""
    m = _rows(R, t)
    k, d = _intrinsics(K, dist)
    hi_u = width - 0.5
    hi_v = height - 0.5
    for i in range(pts.shape[0]):
        xc, yc, zc = _transform(m, pts[i, 0], pts[i, 1], pts[i, 2])
        pu, pv = _pixel(xc, yc, zc, k, d, distorted)
        uv[i, 0] = pu
        uv[i, 1] = pv
        depth[i] = zc
        ok = zc > 0 and pu >= -0.5 and pu <= hi_u and pv >= -0.5 and pv <= hi_v
        inside[i] = ok
        if ok:
            u[i] = min(max(int(np.rint(pu)), 0), width - 1)
            v[i] = min(max(int(np.rint(pv)), 0), height - 1)
        else:
            u[i] = 0
            v[i] = 0
