"""The CUDA kernels of :mod:`edgerecon.dense.gpu` (imported only where they run: importing
this module needs numba's CUDA target, a GPU or ``NUMBA_ENABLE_CUDASIM=1``)."""

from __future__ import annotations

import math
from typing import Any

from numba import cuda as numba_cuda
from numba import float32

from edgerecon.dense.kernels import VAR_EPS

#: Typed loosely (numba's intrinsics confuse mypy); the simulator swaps this module too.
cuda: Any = numba_cuda

#: Most source views one reference can score against (a thread's local best-of list).
MAX_SOURCES = 16


@cuda.jit(device=True)
def sample(srcs: Any, s: int, sw: int, sh: int, x: float, y: float) -> Any:
    if not (x >= 0.0 and y >= 0.0 and x <= sw - 1 and y <= sh - 1):
        return 0.0, False
    x0 = min(int(x), sw - 2)
    y0 = min(int(y), sh - 2)
    fx = x - x0
    fy = y - y0
    v = (srcs[s, y0, x0] * (1.0 - fx) + srcs[s, y0, x0 + 1] * fx) * (1.0 - fy) + (
        srcs[s, y0 + 1, x0] * (1.0 - fx) + srcs[s, y0 + 1, x0 + 1] * fx
    ) * fy
    return v, True


@cuda.jit(device=True)
def score(
    ref: Any,
    mean: Any,
    var: Any,
    count: Any,
    srcs: Any,
    sizes: Any,
    src_ok: Any,
    active: Any,
    lo: Any,
    hi: Any,
    mode: int,
    H: Any,
    a: Any,
    b: Any,
    inv: Any,
    r: int,
    top_k: int,
    top_gap: float,
    y: int,
    x: int,
) -> float:
    """Aggregated NCC at (y, x) (``kernels._scores``; ``H`` one plane's (S, 3, 3))."""
    h = ref.shape[0]
    w = ref.shape[1]
    if x < lo[y] or x >= hi[y]:
        return -1.0
    best = cuda.local.array(MAX_SOURCES, float32)
    m = 0
    y_a = max(y - r, 0)
    y_b = min(y + r + 1, h)
    x_a = max(x - r, 0)
    x_b = min(x + r + 1, w)
    for s in range(srcs.shape[0]):
        if not src_ok[s, y, x]:
            continue
        sw = sizes[s, 0]
        sh = sizes[s, 1]
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        missing = False
        for yy in range(y_a, y_b):
            for xx in range(x_a, x_b):
                if not active[yy, xx]:
                    continue
                ok = False
                v = 0.0
                if mode == 0:
                    zw = H[s, 2, 0] * xx + H[s, 2, 1] * yy + H[s, 2, 2]
                    if zw > 1e-12:
                        u = (H[s, 0, 0] * xx + H[s, 0, 1] * yy + H[s, 0, 2]) / zw
                        q = (H[s, 1, 0] * xx + H[s, 1, 1] * yy + H[s, 1, 2]) / zw
                        v, ok = sample(srcs, s, sw, sh, u, q)
                else:
                    iv = inv[yy, xx]
                    den = a[s, 2, yy, xx] + iv * b[s, 2]
                    if den > 1e-12:
                        u = (a[s, 0, yy, xx] + iv * b[s, 0]) / den
                        q = (a[s, 1, yy, xx] + iv * b[s, 1]) / den
                        v, ok = sample(srcs, s, sw, sh, u, q)
                if not ok:
                    missing = True
                    break
                s0 += v
                s1 += v * v
                s2 += ref[yy, xx] * v
            if missing:
                break
        if missing:
            continue
        n = count[y, x]
        mj = s0 / n
        vj = max(s1 / n - mj * mj, 0.0) + VAR_EPS
        cov = s2 / n - mean[y, x] * mj
        val = cov / math.sqrt(var[y, x] * vj)
        j = m
        while j > 0 and best[j - 1] < val:
            best[j] = best[j - 1]
            j -= 1
        best[j] = val
        m += 1
    if m == 0:
        return -1.0
    kk = min(top_k, m)
    t = best[0]
    floor = best[0] - top_gap
    for j in range(1, kk):
        t += max(best[j], floor)
    return t / kk


@cuda.jit
def sweep(
    ref: Any,
    mean: Any,
    var: Any,
    count: Any,
    srcs: Any,
    sizes: Any,
    src_ok: Any,
    active: Any,
    lo: Any,
    hi: Any,
    Hs: Any,
    lams: Any,
    nray: Any,
    usable: Any,
    w_lo: Any,
    w_hi: Any,
    r: int,
    top_k: int,
    top_gap: float,
    dummy_a: Any,
    dummy_b: Any,
    dummy_inv: Any,
    best: Any,
    best_idx: Any,
    prev: Any,
    nxt: Any,
) -> None:
    x, y = cuda.grid(2)
    if y >= ref.shape[0] or x >= ref.shape[1]:
        return
    b_s = best[y, x]
    b_i = best_idx[y, x]
    b_p = prev[y, x]
    b_n = nxt[y, x]
    last = -1.0
    for p in range(lams.shape[0]):
        sc = score(
            ref, mean, var, count, srcs, sizes, src_ok, active, lo, hi, 0, Hs[p],
            dummy_a, dummy_b, dummy_inv, r, top_k, top_gap, y, x,
        )  # fmt: skip
        iv = lams[p] * nray[y, x]
        if not usable[y, x] or iv < w_lo[y, x] or iv > w_hi[y, x]:
            sc = -1.0
        if sc > b_s:
            b_s = sc
            b_i = p
            b_p = last if p > 0 else -1.0
            b_n = -1.0
        elif b_i == p - 1 and p > 0:
            b_n = sc
        last = sc
    best[y, x] = b_s
    best_idx[y, x] = b_i
    prev[y, x] = b_p
    nxt[y, x] = b_n


@cuda.jit
def evaluate(
    ref: Any,
    mean: Any,
    var: Any,
    count: Any,
    srcs: Any,
    sizes: Any,
    src_ok: Any,
    active: Any,
    lo: Any,
    hi: Any,
    dummy_H: Any,
    a: Any,
    b: Any,
    inv: Any,
    w_lo: Any,
    w_hi: Any,
    r: int,
    top_k: int,
    top_gap: float,
    out: Any,
) -> None:
    x, y = cuda.grid(2)
    if y >= ref.shape[0] or x >= ref.shape[1]:
        return
    iv = inv[y, x]
    if not (iv > w_lo[y, x] and iv < w_hi[y, x]):
        out[y, x] = -1.0
        return
    out[y, x] = score(
        ref, mean, var, count, srcs, sizes, src_ok, active, lo, hi, 1, dummy_H[0], a,
        b, inv, r, top_k, top_gap, y, x,
    )  # fmt: skip
