"""Cross-view geometric consistency of depth maps.

A depth of view i at pixel p is supported by view j when the 3D point it defines projects
into j's image in front of j, and j's own depth at that pixel (nearest) agrees with the
point's depth in j within a relative tolerance. Depths with too few supporting views are
outliers (mismatches, occlusion artefacts) and are dropped before fusion.

The tolerance is measured, not only set (:func:`agreement_tolerance`): the views' depth noise
is the median relative difference of view pairs that agree within twice the configured
tolerance, and views are held to 4x that, within [0.3 %, 1 %]. Synthetic renders and sharp,
well-calibrated captures agree to 0.05-0.1 % (arc7, demo, the object preset) and get 0.3-0.4 %;
real video agrees to 0.45-0.65 % (caliscope_charuco, utrecht4cam, the Middlebury temple) and
keeps 1 %.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.dense.config import DenseConfig
from edgerecon.dense.cost import F32
from edgerecon.geometry.camera import Camera
from edgerecon.threads import thread_map
from edgerecon.types import DepthMap

#: Pairs :func:`agreement_tolerance` needs to measure the noise.
MIN_NOISE_PAIRS = 500


def depth_noise(
    depths: Mapping[int, DepthMap],
    cameras: Mapping[int, Camera],
    window: float,
    stride: int = 8,
) -> tuple[float | None, int]:
    """The views' depth noise: the median relative difference ``|d_j - Z| / Z`` between a
    view's depth (Z, in j) and view j's depth where the point lands, over the view pairs
    that agree within ``window``, and how many pairs it is taken over (None when there are
    none). Every ``stride``-th pixel of every ``stride``-th row is used."""
    diffs = []
    for i, depth_i in depths.items():
        sub = depth_i[::stride, ::stride]
        rows, cols = np.nonzero(sub > 0)
        if len(rows) == 0:
            continue
        u = (cols * stride).astype(np.float32)[:, None]
        v = (rows * stride).astype(np.float32)[:, None]
        z = sub[rows, cols].astype(np.float32)[:, None]
        for j, depth_j in depths.items():
            if j == i:
                continue
            _, _, M, c = _transfer(cameras[i], cameras[j])
            ok, Z, Zs, mx, my, _ = _land(M, c, u, v, z)
            dj = _sample(depth_j, mx, my, cv2.INTER_NEAREST)
            rel = np.abs(dj - Z) / Zs
            diffs.append(rel[ok & (dj > 0) & (rel <= window)])
    found = np.concatenate(diffs) if diffs else np.zeros(0, np.float32)
    return (float(np.median(found)) if len(found) else None), len(found)


def agreement_tolerance(
    depths: Mapping[int, DepthMap], cameras: Mapping[int, Camera], config: DenseConfig
) -> tuple[float, float | None]:
    """The relative depth tolerance within which views agree, and the measured depth noise
    (:func:`depth_noise`, None when not measured).

    ``config.consistency_noise_factor`` times the noise, within
    [``consistency_rel_depth_min``, ``consistency_rel_depth``]: views that agree far more
    tightly than the fixed tolerance (sharp, well calibrated captures) are held to their own
    agreement; real video (noise 0.45-0.65 % at the working resolution) keeps the fixed one.
    The noise is taken within twice the fixed tolerance; with fewer than
    ``MIN_NOISE_PAIRS`` pairs the fixed tolerance is used."""
    fixed = config.consistency_rel_depth
    if config.consistency_noise_factor <= 0 or config.consistency_rel_depth_min >= fixed:
        return fixed, None
    noise, pairs = depth_noise(depths, cameras, 2.0 * fixed)
    if noise is None or pairs < MIN_NOISE_PAIRS:
        return fixed, noise
    tol = config.consistency_noise_factor * noise
    return float(min(max(tol, config.consistency_rel_depth_min), fixed)), noise


def support_counts(
    depths: Mapping[int, DepthMap],
    cameras: Mapping[int, Camera],
    rel_tol: float,
    partners: Mapping[int, Sequence[int]] | None = None,
    num_threads: int = 1,
) -> tuple[dict[int, NDArray[np.int16]], dict[int, DepthMap]]:
    """Per view, an (H, W) map of how many *other* views support each depth (0 where the
    view has no depth), and the depth map averaged over the supporting views.
    ``partners[i]`` limits the views checked for view i (default: all).

    The weighted average is taken along each reference ray: view j's depth ``d_j`` at the pixel where
    the reference point lands defines the point of the ray whose depth in j is ``d_j``
    (``s = (d_j - c_2) / (M_2 . [u, v, 1])``); averaging these with the reference depth cuts
    the depth noise of points seen by several views (about 1/sqrt(n)).

    Vectorised over the pixels with a depth: for views i and j, pixel (u, v) of depth z in i
    lands in j at ``z M [u, v, 1] + c`` with ``M = K_j R_ji K_i^-1`` and ``c = K_j t_ji``;
    j's depth there is read with a nearest-neighbour ``cv2.remap``. Views are checked on
    ``num_threads`` threads (NumPy and OpenCV release the GIL)."""

    out, averaged, _, _ = support_and_conflicts(depths, cameras, rel_tol, partners, num_threads)
    return out, averaged


def support_and_conflicts(
    depths: Mapping[int, DepthMap],
    cameras: Mapping[int, Camera],
    rel_tol: float,
    partners: Mapping[int, Sequence[int]] | None = None,
    num_threads: int = 1,
    max_reproj_px: float = 0.0,
) -> tuple[
    dict[int, NDArray[np.int16]],
    dict[int, DepthMap],
    dict[int, NDArray[np.int16]],
    dict[int, NDArray[np.int16]],
]:
    """:func:`support_counts` plus, per view, (H, W) maps of how many other views
    *contradict* each depth (the point lands in j's image in front of the surface j measured
    there: space that j sees through, a floating speck or a streak unless j's own depth is the
    wrong one) and how many *could have confirmed* it (the point lands in j's image, in front
    of j, not behind a surface j measured: j agrees, contradicts or has no depth there).
    ``max_reproj_px`` > 0 also asks an agreeing view's point to reproject within that many
    pixels of the reference pixel (COLMAP's fusion test; the relative depth tolerance alone
    is many pixels wide at close range)."""

    def one(i: int) -> tuple[NDArray[np.int16], DepthMap, NDArray[np.int16], NDArray[np.int16]]:
        others = [j for j in (depths if partners is None else partners.get(i, ())) if j != i]
        return _support_view(i, depths, cameras, rel_tol, others, max_reproj_px)

    results = thread_map(one, depths, num_threads)
    out = {i: r[0] for i, r in zip(depths, results, strict=True)}
    averaged = {i: r[1] for i, r in zip(depths, results, strict=True)}
    conflicts = {i: r[2] for i, r in zip(depths, results, strict=True)}
    candidates = {i: r[3] for i, r in zip(depths, results, strict=True)}
    return out, averaged, conflicts, candidates


def _support_view(
    i: int,
    depths: Mapping[int, DepthMap],
    cameras: Mapping[int, Camera],
    rel_tol: float,
    others: Sequence[int],
    max_reproj_px: float = 0.0,
) -> tuple[NDArray[np.int16], DepthMap, NDArray[np.int16], NDArray[np.int16]]:
    """``support_and_conflicts`` of view i against the views ``others``."""
    depth_i = depths[i]
    h, w = depth_i.shape
    support = np.zeros((h, w), np.int16)
    conflicts = np.zeros((h, w), np.int16)
    candidates = np.zeros((h, w), np.int16)
    averaged = depth_i.astype(np.float32).copy()
    # Only the pixels with a depth (a few percent of the image for a foreground), as
    # (N, 1) arrays.
    rows, cols = np.nonzero(depth_i > 0)
    if len(rows) > 0:
        u = cols.astype(np.float32)[:, None]
        v = rows.astype(np.float32)[:, None]
        z = depth_i[rows, cols].astype(np.float32)[:, None]
        count = np.zeros(z.shape, np.int16)
        conflict = np.zeros(z.shape, np.int16)
        seen = np.zeros(z.shape, np.int16)
        total = z.copy()
        weight = np.ones(z.shape, np.float32)
        cam_i = cameras[i]
        for j in others:
            if j not in depths:
                continue
            cam_j = cameras[j]
            R, t, M, c = _transfer(cam_i, cam_j)
            ok, Z, Zs, mx, my, m2 = _land(M, c, u, v, z)
            dj = _sample(depths[j], mx, my, cv2.INTER_NEAREST)
            agree = ok & (dj > 0) & (np.abs(dj - Z) <= rel_tol * Z)
            if max_reproj_px > 0:
                # j's point (its nearest pixel at its depth) seen from i again.
                Mb = (cam_i.K @ R.T @ np.linalg.inv(cam_j.K)).astype(np.float32)
                cb = (-cam_i.K @ R.T @ t).astype(np.float32)
                pu, pv = np.rint(mx), np.rint(my)
                Xb = dj * (Mb[0, 0] * pu + Mb[0, 1] * pv + Mb[0, 2]) + cb[0]
                Yb = dj * (Mb[1, 0] * pu + Mb[1, 1] * pv + Mb[1, 2]) + cb[1]
                Zb = dj * (Mb[2, 0] * pu + Mb[2, 1] * pv + Mb[2, 2]) + cb[2]
                with np.errstate(divide="ignore", invalid="ignore"):
                    err2 = (Xb / Zb - u) ** 2 + (Yb / Zb - v) ** 2
                agree &= (Zb > 0) & (err2 <= max_reproj_px**2)
            count += agree
            conflict += ok & (dj > 0) & (dj > (1 + rel_tol) * Z)
            hj, wj_ = depths[j].shape
            inside = ok & (mx > -0.5) & (mx < wj_ - 0.5) & (my > -0.5) & (my < hj - 0.5)
            seen += agree | (inside & ~((dj > 0) & (dj < (1 - rel_tol) * Z)))
            # For the average, j's depth interpolated at the exact landing point (the nearest
            # pixel's depth is off by up to half a pixel's depth gradient on slanted
            # surfaces); near holes and edges the interpolation mixes in other depths and
            # fails the tolerance, and the nearest depth is used instead.
            dl = _sample(depths[j], mx, my, cv2.INTER_LINEAR)
            dj = np.where(np.abs(dl - Z) <= rel_tol * Z, dl, dj)
            # s_j = (d_j - c_2) / m_2 amplifies j's depth error by Z / (m_2 z): weight by the
            # inverse square of that factor (1 for nearby views, ~0 for grazing rays).
            with np.errstate(divide="ignore", invalid="ignore"):
                gain = np.where(agree, m2 * z / Zs, 0.0)
                wj = np.clip(gain, 0.0, 1.0) ** 2
                sj = np.where(wj > 0, (dj - c[2]) / np.where(m2 != 0, m2, 1.0), 0.0)
            total += (wj * sj).astype(np.float32)
            weight += wj.astype(np.float32)
        avg = total / weight
        # The average stays within the agreement tolerance of the view's own depth.
        avg = np.clip(avg, z * (1 - rel_tol), z * (1 + rel_tol))
        support[rows, cols] = count[:, 0]
        conflicts[rows, cols] = conflict[:, 0]
        candidates[rows, cols] = seen[:, 0]
        averaged[rows, cols] = avg[:, 0]
    return support, averaged, conflicts, candidates


def _transfer(
    cam_i: Camera, cam_j: Camera
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float32], NDArray[np.float32]]:
    """From view i to view j: the relative pose (R, t) and the pixel transfer of a depth,
    ``M = K_j R K_i^-1`` and ``c = K_j t``."""
    R = cam_j.R @ cam_i.R.T
    t = cam_j.t - R @ cam_i.t
    M = (cam_j.K @ R @ np.linalg.inv(cam_i.K)).astype(np.float32)
    c = (cam_j.K @ t).astype(np.float32)
    return R, t, M, c


def _land(
    M: F32, c: F32, u: F32, v: F32, z: F32
) -> tuple[NDArray[np.bool_], F32, F32, F32, F32, F32]:
    """Where the (N, 1) pixels (u, v) of depth z of view i land in view j (``_transfer``):
    in front of j (ok), their depth in j (Z; Zs = Z with 1 where not ok), the landing
    point (mx, my; far outside where not ok) and the ray factor ``m2`` (Z = z m2 + c_2)."""
    X = z * (M[0, 0] * u + M[0, 1] * v + M[0, 2]) + c[0]
    Y = z * (M[1, 0] * u + M[1, 1] * v + M[1, 2]) + c[1]
    m2 = M[2, 0] * u + M[2, 1] * v + M[2, 2]
    Z = z * m2 + c[2]
    ok = Z > 0
    Zs = np.where(ok, Z, 1.0)
    mx = np.where(ok, X / Zs, -1e6).astype(np.float32)
    my = np.where(ok, Y / Zs, -1e6).astype(np.float32)
    return ok, Z, Zs, mx, my, m2


#: Width of the map images that ``_sample`` hands to ``cv2.remap`` (which needs sides
#: below 32767).
_SAMPLE_WIDTH = 1024


def _sample(
    image: DepthMap, mx: NDArray[np.float32], my: NDArray[np.float32], interpolation: int
) -> NDArray[np.float32]:
    """``image`` at the (N, 1) points (mx, my) (0 outside), via ``cv2.remap`` on maps folded
    into rows of ``_SAMPLE_WIDTH``."""
    n = mx.shape[0]
    rows = -(-n // _SAMPLE_WIDTH)
    pad = rows * _SAMPLE_WIDTH - n
    fx = np.pad(mx[:, 0], (0, pad), constant_values=-1e6).reshape(rows, _SAMPLE_WIDTH)
    fy = np.pad(my[:, 0], (0, pad), constant_values=-1e6).reshape(rows, _SAMPLE_WIDTH)
    out = cv2.remap(image, fx, fy, interpolation, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return np.asarray(out, np.float32).reshape(-1)[:n, None]
