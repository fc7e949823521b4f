"""Compiled (numba) inner loops of the plane sweep and the depth refinement.

Each kernel fuses, per pixel, the resampling of a source image (bilinear), the windowed
sums of the NCC (separable running sums over truncated windows at the crop borders) and the
aggregation over sources. The equivalent NumPy/OpenCV code makes ~20 passes over full-size
temporaries per hypothesis and source and is memory-bound; measured on these 2-core machines
(1920x1080 arc, 7 views) the fused kernels are several times faster (see ``depth``'s module
docstring). Kernels release the GIL, so reference views run in parallel Python threads.

Conventions: images are float32 grey with the mean grey subtracted (``cost.to_grey``);
windows are ``(2 r + 1)^2`` pixels, truncated at the image border (the reference statistics
use the same truncated windows, so NCC stays exact there); a window with any sample outside
the source image (or behind the source camera) has no NCC (-inf in the aggregation).
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

F32 = NDArray[np.float32]

#: Variance floor (grey levels squared) that keeps NCC finite on flat windows.
VAR_EPS = np.float32(1e-3)
_NEG = np.float32(-np.inf)

_jit = nb.njit(
    nogil=True,
    cache=True,
    fastmath={"nsz", "arcp", "contract", "afn", "reassoc"},
    error_model="numpy",
)


@_jit
def _box_sums4(a: F32, b: F32, c: F32, d: F32, r: int, sa: F32, sb: F32, sc: F32, sd: F32) -> None:
    """Window sums of four images (truncated windows), written to sa..sd."""
    h, w = a.shape
    ta = np.empty((h, w), np.float32)
    tb = np.empty((h, w), np.float32)
    tc = np.empty((h, w), np.float32)
    td = np.empty((h, w), np.float32)
    # Vertical running sums (float64 accumulators per column).
    acc = np.zeros((4, w), np.float64)
    for y in range(min(r, h)):
        for x in range(w):
            acc[0, x] += a[y, x]
            acc[1, x] += b[y, x]
            acc[2, x] += c[y, x]
            acc[3, x] += d[y, x]
    for y in range(h):
        yi = y + r
        if yi < h:
            for x in range(w):
                acc[0, x] += a[yi, x]
                acc[1, x] += b[yi, x]
                acc[2, x] += c[yi, x]
                acc[3, x] += d[yi, x]
        yo = y - r - 1
        if yo >= 0:
            for x in range(w):
                acc[0, x] -= a[yo, x]
                acc[1, x] -= b[yo, x]
                acc[2, x] -= c[yo, x]
                acc[3, x] -= d[yo, x]
        for x in range(w):
            ta[y, x] = acc[0, x]
            tb[y, x] = acc[1, x]
            tc[y, x] = acc[2, x]
            td[y, x] = acc[3, x]
    # Horizontal running sums.
    for y in range(h):
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        s3 = 0.0
        for x in range(min(r, w)):
            s0 += ta[y, x]
            s1 += tb[y, x]
            s2 += tc[y, x]
            s3 += td[y, x]
        for x in range(w):
            xi = x + r
            if xi < w:
                s0 += ta[y, xi]
                s1 += tb[y, xi]
                s2 += tc[y, xi]
                s3 += td[y, xi]
            xo = x - r - 1
            if xo >= 0:
                s0 -= ta[y, xo]
                s1 -= tb[y, xo]
                s2 -= tc[y, xo]
                s3 -= td[y, xo]
            sa[y, x] = s0
            sb[y, x] = s1
            sc[y, x] = s2
            sd[y, x] = s3


@_jit
def window_stats(img: F32, r: int) -> tuple[F32, F32, F32]:
    """(mean, variance + VAR_EPS, window pixel count) over truncated windows."""
    h, w = img.shape
    ones = np.ones((h, w), np.float32)
    sq = img * img
    s1 = np.empty((h, w), np.float32)
    s2 = np.empty((h, w), np.float32)
    n = np.empty((h, w), np.float32)
    dummy = np.empty((h, w), np.float32)
    _box_sums4(img, sq, ones, ones, r, s1, s2, n, dummy)
    mean = s1 / n
    var = np.maximum(s2 / n - mean * mean, np.float32(0.0)) + VAR_EPS
    return mean, var.astype(np.float32), n


@_jit
def _sample(src: F32, sw: int, sh: int, x: float, y: float) -> tuple[float, bool]:
    if not (x >= 0.0 and y >= 0.0 and x <= sw - 1 and y <= sh - 1):
        return 0.0, False
    x0 = min(int(x), sw - 2)
    y0 = min(int(y), sh - 2)
    fx = x - x0
    fy = y - y0
    v = (src[y0, x0] * (1.0 - fx) + src[y0, x0 + 1] * fx) * (1.0 - fy) + (
        src[y0 + 1, x0] * (1.0 - fx) + src[y0 + 1, x0 + 1] * fx
    ) * fy
    return v, True


@_jit
def _spans(active: NDArray[np.bool_]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Per row, the first and one past the last active column (lo >= hi: none)."""
    h, w = active.shape
    lo = np.full(h, w, np.int64)
    hi = np.zeros(h, np.int64)
    for y in range(h):
        for x in range(w):
            if active[y, x]:
                lo[y] = x
                break
        for x in range(w - 1, -1, -1):
            if active[y, x]:
                hi[y] = x + 1
                break
    return lo, hi


@_jit
def _scores(
    ref: F32,
    mean: F32,
    var: F32,
    count: F32,
    srcs: F32,
    sizes: NDArray[np.int64],
    src_ok: NDArray[np.bool_],
    active: NDArray[np.bool_],
    mode: int,
    H: NDArray[np.float64],
    a: F32,
    b: NDArray[np.float32],
    inv: F32,
    r: int,
    top_k: int,
    top_gap: float,
    out: F32,
    row0: int,
    row1: int,
) -> None:
    """Aggregated NCC of one hypothesis per pixel, streamed row by row, for the output rows
    ``row0 <= y < row1`` (a band reads the rows within ``r`` of it and writes only its own,
    so that bands can run in parallel and give the same result as one call).

    ``mode`` 0: source s sees pixel (x, y) at ``H[s] (x, y, 1)`` (a plane's homography);
    ``mode`` 1: at ``(a[s, :2] + inv b[s, :2]) / (a[s, 2] + inv b[s, 2])`` (per-pixel
    inverse depth). The resampled rows live in a ring buffer of ``2 r + 1`` rows per source
    and the vertical window sums are updated incrementally, so the working set stays in the
    cache (the separable-filter version over whole images was memory-bound).

    Only ``active`` pixels are sampled and summed, and only windows inside each row's span
    of active pixels are scored (-1 elsewhere): pass the pixels to score dilated by the
    window radius (``src_ok`` False elsewhere), and the cost follows their area, not the
    crop's. A window whose pixels are all active sums exactly what it would sum with every
    pixel active (each active sample is added when its row enters and removed when it
    leaves); other windows are never scored."""
    h, w = ref.shape
    S = srcs.shape[0]
    n_ring = 2 * r + 1
    lo, hi = _spans(active)
    ringJ = np.zeros((S, n_ring, w), np.float32)
    ringB = np.zeros((S, n_ring, w), np.float32)
    acc = np.zeros((S, 4, w), np.float64)
    row_ncc = np.empty((S, w), np.float32)
    best = np.empty(S, np.float32)
    first_in = max(0, row0 - r)  # first row that enters a window
    for y in range(first_in - r, row1):
        # Row yi = y + r enters the window of output row y; row y - r - 1 leaves it.
        yi = y + r
        slot = yi % n_ring
        yo = yi - n_ring
        for s in range(S):
            if yo >= first_in:
                for x in range(lo[yo], hi[yo]):
                    if not active[yo, x]:
                        continue
                    j = ringJ[s, slot, x]
                    acc[s, 0, x] -= j
                    acc[s, 1, x] -= j * j
                    acc[s, 2, x] -= ref[yo, x] * j
                    acc[s, 3, x] -= ringB[s, slot, x]
            if yi < h:
                sw = sizes[s, 0]
                sh = sizes[s, 1]
                src = srcs[s]
                for x in range(lo[yi], hi[yi]):
                    if not active[yi, x]:
                        continue
                    ok = False
                    v = 0.0
                    if mode == 0:
                        zw = H[s, 2, 0] * x + H[s, 2, 1] * yi + H[s, 2, 2]
                        if zw > 1e-12:
                            u = (H[s, 0, 0] * x + H[s, 0, 1] * yi + H[s, 0, 2]) / zw
                            q = (H[s, 1, 0] * x + H[s, 1, 1] * yi + H[s, 1, 2]) / zw
                            v, ok = _sample(src, sw, sh, u, q)
                    else:
                        iv = inv[yi, x]
                        den = a[s, 2, yi, x] + iv * b[s, 2]
                        if den > 1e-12:
                            u = (a[s, 0, yi, x] + iv * b[s, 0]) / den
                            q = (a[s, 1, yi, x] + iv * b[s, 1]) / den
                            v, ok = _sample(src, sw, sh, u, q)
                    bv = 0.0 if ok else 1.0
                    ringJ[s, slot, x] = v
                    ringB[s, slot, x] = bv
                    acc[s, 0, x] += v
                    acc[s, 1, x] += v * v
                    acc[s, 2, x] += ref[yi, x] * v
                    acc[s, 3, x] += bv
        if y < row0:
            continue
        x0 = lo[y]
        x1 = hi[y]
        for x in range(w):
            if x < x0 or x >= x1:
                out[y, x] = -1.0
        if x0 >= x1:
            continue
        # Horizontal running sums of the column sums -> NCC of row y for every source, over
        # the row's active span.
        for s in range(S):
            s0 = 0.0
            s1 = 0.0
            s2 = 0.0
            s3 = 0.0
            for x in range(max(x0 - r - 1, 0), min(x0 + r, w)):
                s0 += acc[s, 0, x]
                s1 += acc[s, 1, x]
                s2 += acc[s, 2, x]
                s3 += acc[s, 3, x]
            for x in range(x0, x1):
                xi = x + r
                if xi < w:
                    s0 += acc[s, 0, xi]
                    s1 += acc[s, 1, xi]
                    s2 += acc[s, 2, xi]
                    s3 += acc[s, 3, xi]
                xo = x - r - 1
                if xo >= 0:
                    s0 -= acc[s, 0, xo]
                    s1 -= acc[s, 1, xo]
                    s2 -= acc[s, 2, xo]
                    s3 -= acc[s, 3, xo]
                if s3 > 0.5 or not src_ok[s, y, x]:
                    row_ncc[s, x] = _NEG
                else:
                    n = count[y, x]
                    mj = s0 / n
                    vj = max(s1 / n - mj * mj, 0.0) + VAR_EPS
                    cov = s2 / n - mean[y, x] * mj
                    row_ncc[s, x] = cov / np.sqrt(var[y, x] * vj)
        # Mean of the top_k finite scores, each at least the best one minus top_gap.
        for x in range(x0, x1):
            m = 0
            for s in range(S):
                v = row_ncc[s, x]
                if v > _NEG:
                    j = m
                    while j > 0 and best[j - 1] < v:
                        best[j] = best[j - 1]
                        j -= 1
                    best[j] = v
                    m += 1
            if m == 0:
                out[y, x] = -1.0
            else:
                kk = min(top_k, m)
                t = best[0]
                floor = best[0] - top_gap
                for j in range(1, kk):
                    t += max(best[j], floor)
                out[y, x] = t / kk


@_jit
def sweep(
    ref: F32,
    mean: F32,
    var: F32,
    count: F32,
    srcs: F32,
    sizes: NDArray[np.int64],
    src_ok: NDArray[np.bool_],
    active: NDArray[np.bool_],
    homographies: NDArray[np.float64],
    lams: NDArray[np.float64],
    nray: F32,
    usable: NDArray[np.bool_],
    w_lo: F32,
    w_hi: F32,
    r: int,
    top_k: int,
    top_gap: float,
    best: F32,
    best_idx: NDArray[np.int32],
    prev: F32,
    nxt: F32,
    row0: int,
    row1: int,
) -> None:
    """Plane sweep of one plane family, winner-take-all with neighbours for sub-plane fits,
    on the rows ``row0 <= y < row1`` (see ``_scores``).

    ``homographies[p, s]`` maps crop pixels to source s for plane p (lambda ``lams[p]``);
    ``srcs[s, :sizes[s, 1], :sizes[s, 0]]`` are the source images. A plane's score at a
    pixel is -1 where ``usable`` is False or its inverse depth ``lams[p] * nray`` is outside
    ``[w_lo, w_hi]``. Updates ``best``/``best_idx`` (initialise best to -inf) and stores the
    scores of the planes before and after the best one in ``prev``/``nxt`` (-1 if none)."""
    h, w = ref.shape
    P = lams.shape[0]
    score = np.empty((h, w), np.float32)
    last = np.full((h, w), np.float32(-1.0))
    dummy_a = np.zeros((1, 3, 1, 1), np.float32)
    dummy_b = np.zeros((1, 3), np.float32)
    dummy_inv = np.zeros((1, 1), np.float32)
    for p in range(P):
        lam = lams[p]
        _scores(
            ref, mean, var, count, srcs, sizes, src_ok, active, 0, homographies[p], dummy_a,
            dummy_b, dummy_inv, r, top_k, top_gap, score, row0, row1,
        )  # fmt: skip
        for y in range(row0, row1):
            for x in range(w):
                sc = score[y, x]
                inv = lam * nray[y, x]
                if not usable[y, x] or inv < w_lo[y, x] or inv > w_hi[y, x]:
                    sc = -1.0
                if sc > best[y, x]:
                    best[y, x] = sc
                    best_idx[y, x] = p
                    prev[y, x] = last[y, x] if p > 0 else -1.0
                    nxt[y, x] = -1.0
                elif best_idx[y, x] == p - 1 and p > 0:
                    nxt[y, x] = sc
                last[y, x] = sc


@_jit
def evaluate(
    ref: F32,
    mean: F32,
    var: F32,
    count: F32,
    srcs: F32,
    sizes: NDArray[np.int64],
    src_ok: NDArray[np.bool_],
    active: NDArray[np.bool_],
    a: F32,
    b: NDArray[np.float32],
    inv: F32,
    w_lo: F32,
    w_hi: F32,
    r: int,
    top_k: int,
    top_gap: float,
    out: F32,
    row0: int,
    row1: int,
) -> None:
    """Aggregated NCC of the per-pixel inverse-depth hypotheses ``inv`` on the rows
    ``row0 <= y < row1`` (see ``_scores``).

    Source s sees pixel (x, y) at ``(a[s, :2] + inv b[s, :2]) / (a[s, 2] + inv b[s, 2])``.
    Scores are -1 where ``inv`` is outside ``(w_lo, w_hi)``."""
    w = ref.shape[1]
    dummy_H = np.zeros((1, 3, 3), np.float64)
    _scores(
        ref, mean, var, count, srcs, sizes, src_ok, active, 1, dummy_H, a, b, inv, r, top_k,
        top_gap, out, row0, row1,
    )  # fmt: skip
    for y in range(row0, row1):
        for x in range(w):
            iv = inv[y, x]
            if not (iv > w_lo[y, x] and iv < w_hi[y, x]):
                out[y, x] = -1.0


# ================================================================================= fusion
@_jit
def _cam_point(depth: F32, Kinv: NDArray[np.float64], y: int, x: int) -> tuple[float, float, float]:
    z = depth[y, x]
    return (
        (Kinv[0, 0] * x + Kinv[0, 1] * y + Kinv[0, 2]) * z,
        (Kinv[1, 1] * y + Kinv[1, 2]) * z,
        z,
    )


@_jit
def _tangent(
    depth: F32, Kinv: NDArray[np.float64], y: int, x: int, dy: int, dx: int, max_rel: float
) -> tuple[float, float, float, bool]:
    """Finite difference of the back-projected points along (dy, dx), central where both
    neighbours are on the same surface (no depth jump), one-sided otherwise."""
    h, w = depth.shape
    z = depth[y, x]
    ya, xa, yb, xb = y - dy, x - dx, y + dy, x + dx
    ok_a = 0 <= ya < h and 0 <= xa < w and depth[ya, xa] > 0
    ok_b = 0 <= yb < h and 0 <= xb < w and depth[yb, xb] > 0
    if ok_a:
        ok_a = abs(depth[ya, xa] - z) <= max_rel * z
    if ok_b:
        ok_b = abs(depth[yb, xb] - z) <= max_rel * z
    if not ok_a and not ok_b:
        return 0.0, 0.0, 0.0, False
    if ok_a:
        pa = _cam_point(depth, Kinv, ya, xa)
    else:
        pa = _cam_point(depth, Kinv, y, x)
    if ok_b:
        pb = _cam_point(depth, Kinv, yb, xb)
    else:
        pb = _cam_point(depth, Kinv, y, x)
    return pb[0] - pa[0], pb[1] - pa[1], pb[2] - pa[2], True


@_jit
def view_points(
    depth: F32,
    keep: NDArray[np.bool_],
    Kinv: NDArray[np.float64],
    R: NDArray[np.float64],
    t: NDArray[np.float64],
    stride: int,
    max_rel: float,
) -> tuple[NDArray[np.float64], NDArray[np.float32], NDArray[np.int64]]:
    """World points, world unit normals (facing the camera) and flat pixel indices of the
    ``keep`` pixels of a depth map. Normals are the cross product of the tangents at
    ``stride`` pixels (skipping depth jumps); without tangents, the direction to the camera."""
    h, w = depth.shape
    n = 0
    for y in range(h):
        for x in range(w):
            if keep[y, x]:
                n += 1
    pts = np.empty((n, 3), np.float64)
    nrm = np.empty((n, 3), np.float32)
    idx = np.empty(n, np.int64)
    k = 0
    for y in range(h):
        for x in range(w):
            if not keep[y, x]:
                continue
            cx, cy, cz = _cam_point(depth, Kinv, y, x)
            ux, uy, uz, oku = _tangent(depth, Kinv, y, x, 0, stride, max_rel)
            vx, vy, vz, okv = _tangent(depth, Kinv, y, x, stride, 0, max_rel)
            nx = uy * vz - uz * vy
            ny = uz * vx - ux * vz
            nz = ux * vy - uy * vx
            norm = np.sqrt(nx * nx + ny * ny + nz * nz)
            if oku and okv and norm > 1e-20:
                nx /= norm
                ny /= norm
                nz /= norm
                if nx * cx + ny * cy + nz * cz > 0:
                    nx, ny, nz = -nx, -ny, -nz
            else:
                cn = np.sqrt(cx * cx + cy * cy + cz * cz)
                nx, ny, nz = -cx / cn, -cy / cn, -cz / cn
            # world = R^T (X_cam - t); normals rotate with R^T.
            px, py, pz = cx - t[0], cy - t[1], cz - t[2]
            for i in range(3):
                pts[k, i] = R[0, i] * px + R[1, i] * py + R[2, i] * pz
                nrm[k, i] = R[0, i] * nx + R[1, i] * ny + R[2, i] * nz
            idx[k] = y * w + x
            k += 1
    return pts, nrm, idx


@_jit
def merge_sorted(
    order: NDArray[np.int64],
    starts: NDArray[np.int64],
    X: NDArray[np.float64],
    C: NDArray[np.uint8],
    N: NDArray[np.float32],
    V: NDArray[np.int32],
    S: NDArray[np.float32],
) -> tuple[
    NDArray[np.float64],
    NDArray[np.uint8],
    NDArray[np.float32],
    NDArray[np.int32],
    NDArray[np.float32],
]:
    """Per run of ``order`` (voxels, from ``starts``): mean position, colour, normal
    (renormalised; the first member's where the sum cancels), max views, mean score."""
    m = starts.shape[0]
    total = order.shape[0]
    P = np.empty((m, 3), np.float64)
    Co = np.empty((m, 3), np.uint8)
    No = np.empty((m, 3), np.float32)
    Vo = np.empty(m, np.int32)
    So = np.empty(m, np.float32)
    for g in range(m):
        a = starts[g]
        b = starts[g + 1] if g + 1 < m else total
        sx = sy = sz = 0.0
        c0 = c1 = c2 = 0.0
        n0 = n1 = n2 = 0.0
        vmax = 0
        ss = 0.0
        for j in range(a, b):
            i = order[j]
            sx += X[i, 0]
            sy += X[i, 1]
            sz += X[i, 2]
            c0 += C[i, 0]
            c1 += C[i, 1]
            c2 += C[i, 2]
            n0 += N[i, 0]
            n1 += N[i, 1]
            n2 += N[i, 2]
            vmax = max(vmax, V[i])
            ss += S[i]
        cnt = b - a
        P[g, 0] = sx / cnt
        P[g, 1] = sy / cnt
        P[g, 2] = sz / cnt
        Co[g, 0] = np.uint8(min(255.0, c0 / cnt + 0.5))
        Co[g, 1] = np.uint8(min(255.0, c1 / cnt + 0.5))
        Co[g, 2] = np.uint8(min(255.0, c2 / cnt + 0.5))
        nn = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        if nn < 1e-3 * cnt:
            i = order[a]
            n0, n1, n2 = N[i, 0], N[i, 1], N[i, 2]
            nn = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        No[g, 0] = n0 / nn
        No[g, 1] = n1 / nn
        No[g, 2] = n2 / nn
        Vo[g] = vmax
        So[g] = ss / cnt
    return P, Co, No, Vo, So


@_jit
def voxel_keys(X: NDArray[np.float64], voxel: float) -> NDArray[np.int64]:
    """One int64 key per point: its voxel of edge ``voxel`` in a grid fixed in the world
    (corners at integer multiples of ``voxel``), numbered over the points' box. A point falls
    into the same voxel whatever other points are keyed with it."""
    n = X.shape[0]
    inv = 1.0 / voxel
    lo = np.empty(3)
    hi = np.empty(3)
    for i in range(3):
        lo[i] = np.floor(X[0, i] * inv) if n else 0.0
        hi[i] = lo[i]
    for k in range(n):
        for i in range(3):
            v = np.floor(X[k, i] * inv)
            if v < lo[i]:
                lo[i] = v
            if v > hi[i]:
                hi[i] = v
    span1 = np.int64(hi[1] - lo[1]) + 1
    span2 = np.int64(hi[2] - lo[2]) + 1
    keys = np.empty(n, np.int64)
    for k in range(n):
        kx = np.int64(np.floor(X[k, 0] * inv) - lo[0])
        ky = np.int64(np.floor(X[k, 1] * inv) - lo[1])
        kz = np.int64(np.floor(X[k, 2] * inv) - lo[2])
        keys[k] = (kx * span1 + ky) * span2 + kz
    return keys
