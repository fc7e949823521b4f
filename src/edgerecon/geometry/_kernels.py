"""Compiled (numba) projection of camera-frame points to pixels.

``Camera.project`` is called thousands of times per task by the scene stage (hull voxels,
photo-check samples, splats) on 10^4-10^5 points; in NumPy the perspective division, the
Brown-Conrady distortion and the intrinsics take ~25 passes over full-length temporaries.
Fused here into one pass per point, with NumPy's operation order and no fastmath, so the
pixels are the NumPy code's bit for bit (tested).
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray


@nb.njit(nogil=True, cache=True, error_model="numpy")
def project_camera_points(
    xc: NDArray[np.float64],
    K: NDArray[np.float64],
    dist: NDArray[np.float64],
    distorted: bool,
    uv: NDArray[np.float64],
) -> None:
    """Pixels of the (N, 3) camera-frame points ``xc`` written to ``uv`` (N, 2): divided
    by depth, distorted (``distorted``: k1, k2, p1, p2, k3 of ``dist``), through ``K``; NaN
    for points not in front of the camera (depth <= 0 or NaN). Points near the camera's
    plane give inf / NaN pixels, as in NumPy."""
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    two_p1 = 2 * p1
    two_p2 = 2 * p2
    k00, k01, k02, k11, k12 = K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]
    for i in range(xc.shape[0]):
        depth = xc[i, 2]
        if not depth > 0:
            uv[i, 0] = np.nan
            uv[i, 1] = np.nan
            continue
        xn = xc[i, 0] / depth
        yn = xc[i, 1] / depth
        if distorted:
            r2 = xn * xn + yn * yn
            radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            xd = xn * radial + two_p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
            yd = yn * radial + p1 * (r2 + 2 * yn * yn) + two_p2 * xn * yn
            xn, yn = xd, yd
        uv[i, 0] = k00 * xn + k01 * yn + k02
        uv[i, 1] = k11 * yn + k12
