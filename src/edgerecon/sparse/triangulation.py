"""Multi-view triangulation with known cameras, vectorised over points.

Observations are a dense ``(T, V, 2)`` table of pixels with a ``(T, V)`` mask (V, the number of
views of a task, is small), so points observed by any number of views are solved together:

* linear triangulation (DLT): per point, the 4x4 normal matrix ``A^T A`` of the stacked rows
  ``x P_3 - P_1, y P_3 - P_2`` (normalised image coordinates, world coordinates centred on the
  cameras and scaled by their spread for conditioning) and its smallest eigenvector
  (batched ``eigh``);
* refinement: damped Gauss-Newton steps on the pixel reprojection error, 3x3 systems batched,
  a step is kept only where it lowers the point's cost;
* measures for the filters: per-observation reprojection error and depth, the largest angle
  between two observing rays.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry.camera import Camera

FloatArray = NDArray[np.float64]


def _normaliser(cameras: Sequence[Camera]) -> tuple[FloatArray, float]:
    centres = np.array([c.center for c in cameras])
    c0 = centres.mean(axis=0)
    s = float(np.median(np.linalg.norm(centres - c0, axis=1)))
    return c0, (s if s > 0 else 1.0)


def _stack(cameras: Sequence[Camera], c0: FloatArray, s: float) -> tuple[FloatArray, FloatArray]:
    """Rotations (V, 3, 3) and translations (V, 3) in the normalised world frame."""
    R = np.array([c.R for c in cameras])
    t = np.array([(c.R @ c0 + c.t) / s for c in cameras])
    return R, t


def triangulate_dlt(
    cameras: Sequence[Camera], points2D: FloatArray, observed: NDArray[np.bool_]
) -> FloatArray:
    """(T, 3) linear triangulation of (T, V, 2) pixels observed where ``observed`` (T, V);
    NaN for points with fewer than two observations or at infinity."""
    T, V = observed.shape
    if T == 0:
        return np.zeros((0, 3))
    c0, s = _normaliser(cameras)
    R, t = _stack(cameras, c0, s)
    P = np.concatenate([R, t[:, :, None]], axis=2)  # (V, 3, 4)
    Kinv = np.array([np.linalg.inv(c.K) for c in cameras])
    uv1 = np.concatenate([np.nan_to_num(points2D), np.ones((T, V, 1))], axis=2)
    xn = np.einsum("vij,tvj->tvi", Kinv, uv1)  # normalised coordinates, z = 1
    rows_x = xn[:, :, 0, None] * P[None, :, 2] - P[None, :, 0]  # (T, V, 4)
    rows_y = xn[:, :, 1, None] * P[None, :, 2] - P[None, :, 1]
    w = observed.astype(np.float64)[:, :, None]
    rows_x *= w
    rows_y *= w
    A = np.einsum("tvi,tvj->tij", rows_x, rows_x) + np.einsum("tvi,tvj->tij", rows_y, rows_y)
    _, vecs = np.linalg.eigh(A)
    h = vecs[:, :, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        X = h[:, :3] / h[:, 3:4]
    bad = (observed.sum(axis=1) < 2) | (np.abs(h[:, 3]) < 1e-12) | ~np.all(np.isfinite(X), 1)
    X[bad] = np.nan
    return X * s + c0


def project_all(cameras: Sequence[Camera], points3D: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Pixels (T, V, 2) and depths (T, V) of (T, 3) points in every (undistorted) camera."""
    R = np.array([c.R for c in cameras])
    t = np.array([c.t for c in cameras])
    K = np.array([c.K for c in cameras])
    Xc = np.einsum("vij,tj->tvi", R, points3D) + t[None]
    z = Xc[:, :, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xn = Xc[:, :, 0] / z
        yn = Xc[:, :, 1] / z
    u = K[None, :, 0, 0] * xn + K[None, :, 0, 1] * yn + K[None, :, 0, 2]
    v = K[None, :, 1, 1] * yn + K[None, :, 1, 2]
    return np.stack([u, v], axis=2), z


def reprojection_errors(
    cameras: Sequence[Camera],
    points3D: FloatArray,
    points2D: FloatArray,
    observed: NDArray[np.bool_],
) -> tuple[FloatArray, FloatArray]:
    """Per-observation reprojection error in pixels and depth, both (T, V) with NaN where not
    observed (the error is ``inf`` for observations behind the camera)."""
    uv, z = project_all(cameras, points3D)
    with np.errstate(invalid="ignore"):
        err = np.linalg.norm(uv - points2D, axis=2)
        err = np.where(z > 0, err, np.inf)
    err = np.where(observed, err, np.nan)
    depth = np.where(observed, z, np.nan)
    return err, depth


def _cost(
    cameras: Sequence[Camera], X: FloatArray, pts: FloatArray, obs: NDArray[np.bool_]
) -> FloatArray:
    err, _ = reprojection_errors(cameras, X, pts, obs)
    return np.where(obs, err, 0.0) ** 2 @ np.ones(obs.shape[1])


def refine_points(
    cameras: Sequence[Camera],
    points3D: FloatArray,
    points2D: FloatArray,
    observed: NDArray[np.bool_],
    iterations: int = 5,
) -> FloatArray:
    """Gauss-Newton refinement of (T, 3) points on the squared pixel reprojection error of
    their observations (points in front of all observing cameras; others are left as they are).
    A step is kept only where it lowers the cost; points stop iterating once it stalls."""
    X = np.array(points3D, dtype=np.float64, copy=True)
    T = X.shape[0]
    if T == 0 or iterations == 0:
        return X
    R = np.array([c.R for c in cameras])
    t = np.array([c.t for c in cameras])
    Kp = np.array([c.K[:2, :2] for c in cameras])  # (V, 2, 2) pixel from normalised
    pp = np.array([c.K[:2, 2] for c in cameras])  # (V, 2) principal points
    R0, R1, R2 = R[None, :, 0], R[None, :, 1], R[None, :, 2]  # (1, V, 3)
    pts_all = np.nan_to_num(points2D)
    cost_all = _cost(cameras, X, pts_all, observed)
    active = np.flatnonzero(np.all(np.isfinite(X), axis=1))
    for _ in range(iterations):
        if len(active) == 0:
            break
        Xa, obs, pts, cost = X[active], observed[active], pts_all[active], cost_all[active]
        w = obs.astype(np.float64)
        Xc = np.einsum("vij,tj->tvi", R, Xa) + t[None]
        z = Xc[:, :, 2]
        in_front = np.all((z > 0) | ~obs, axis=1)
        zs = np.where(z > 0, z, 1.0)
        xn = Xc[:, :, 0] / zs
        yn = Xc[:, :, 1] / zs
        u = Kp[None, :, 0, 0] * xn + Kp[None, :, 0, 1] * yn + pp[None, :, 0]
        v = Kp[None, :, 1, 1] * yn + pp[None, :, 1]
        ru = (u - pts[:, :, 0]) * w
        rv = (v - pts[:, :, 1]) * w
        # d(xn, yn)/dX = ([R0 - xn R2], [R1 - yn R2]) / z, then pixels through K's 2x2 part.
        wz = (w / zs)[:, :, None]
        dx = (R0 - xn[:, :, None] * R2) * wz
        dy = (R1 - yn[:, :, None] * R2) * wz
        Ju = Kp[None, :, 0, 0, None] * dx + Kp[None, :, 0, 1, None] * dy  # (t, V, 3)
        Jv = Kp[None, :, 1, 1, None] * dy
        H = np.einsum("tvi,tvj->tij", Ju, Ju) + np.einsum("tvi,tvj->tij", Jv, Jv)
        g = np.einsum("tvi,tv->ti", Ju, ru) + np.einsum("tvi,tv->ti", Jv, rv)
        damp = 1e-9 * np.trace(H, axis1=1, axis2=2) + 1e-300
        H = H + damp[:, None, None] * np.eye(3)
        solvable = in_front & (np.linalg.det(H) > 0)
        delta = np.zeros_like(Xa)
        if np.any(solvable):
            delta[solvable] = -np.linalg.solve(H[solvable], g[solvable][:, :, None])[:, :, 0]
        X_new = Xa + delta
        new_cost = _cost(cameras, X_new, pts, obs)
        better = solvable & (new_cost < cost)
        X[active[better]] = X_new[better]
        cost_all[active[better]] = new_cost[better]
        # Keep iterating only where the step still bought something.
        active = active[better & (new_cost < cost * (1 - 1e-9))]
    return X


def max_triangulation_angle_deg(
    cameras: Sequence[Camera], points3D: FloatArray, observed: NDArray[np.bool_]
) -> FloatArray:
    """(T,) largest angle in degrees between the rays of two observing cameras of each point
    (0 for points with fewer than two observations)."""
    T = observed.shape[0]
    if T == 0:
        return np.zeros(0)
    centres = np.array([c.center for c in cameras])
    out = np.zeros(T)
    step = max(1, (1 << 21) // observed.shape[1] ** 2)  # bounds the (T, V, V) cosines
    for s in range(0, T, step):
        rays = points3D[s : s + step, None, :] - centres[None]  # (t, V, 3)
        with np.errstate(invalid="ignore", divide="ignore"):
            rays /= np.linalg.norm(rays, axis=2, keepdims=True)
        cos = np.einsum("tai,tbi->tab", rays, rays)
        obs = observed[s : s + step]
        cos = np.where(obs[:, :, None] & obs[:, None, :], cos, 1.0)
        cos = np.nan_to_num(cos, nan=1.0)
        out[s : s + step] = np.degrees(np.arccos(np.clip(cos.min(axis=(1, 2)), -1.0, 1.0)))
    return out
