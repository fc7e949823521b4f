"""The GPU kernels against the CPU kernels on one random level: ``python -m
tests.dense.gpu_check [--size W H] [--json]``. The tests run it in numba's CUDA simulator
(``NUMBA_ENABLE_CUDASIM=1``) on a tiny level; on a machine with a CUDA GPU it checks the
real device at any size."""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

import numpy as np

from edgerecon.dense import gpu, kernels


def level(w: int, h: int, sources: int, radius: int, seed: int = 0) -> dict[str, Any]:
    """A reference crop, its window statistics and ``sources`` source images that are noisy,
    shifted copies of it; some pixels inactive, some sources masked, some samples outside."""
    rng = np.random.default_rng(seed)
    base = rng.random((h + 40, w + 40)).astype(np.float32)
    base = np.cumsum(np.cumsum(base, 0), 1)  # smooth texture
    base = (base - base.mean()) / base.std() * 40
    ref = np.ascontiguousarray(base[20 : 20 + h, 20 : 20 + w], np.float32)
    mean, var, count = kernels.window_stats(ref, radius)
    srcs = np.zeros((sources, h + 6, w + 6), np.float32)
    sizes = np.zeros((sources, 2), np.int64)
    for s in range(sources):
        sh, sw = h + 6 - s, w + 6 - 2 * s
        dy, dx = 18 + s, 17 - s
        srcs[s, :sh, :sw] = base[dy : dy + sh, dx : dx + sw] + rng.normal(0, 3, (sh, sw))
        sizes[s] = (sw, sh)
    active = np.ones((h, w), bool)
    active[: h // 4, : w // 3] = False
    active[h // 2, :] = False
    src_ok = rng.random((sources, h, w)) > 0.05
    src_ok &= active[None]
    # Per-pixel projection terms: source s sees (x, y) at (x + 3 + s + iv, y - 2 + iv / 2).
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    a = np.zeros((sources, 3, h, w), np.float32)
    b = np.zeros((sources, 3), np.float32)
    for s in range(sources):
        a[s, 0], a[s, 1], a[s, 2] = u + 3 + s, v - 2, 1.0
        b[s] = (1.0, 0.5, 0.0)
    return {
        "ref": ref, "mean": mean, "var": var, "count": count, "srcs": srcs, "sizes": sizes,
        "src_ok": src_ok, "active": active, "a": a, "b": b, "radius": radius, "rng": rng,
    }  # fmt: skip


def compare(w: int = 24, h: int = 18, sources: int = 3, planes: int = 6, radius: int = 2) -> dict:
    """Max differences of the scores, and the share of pixels whose winning plane differs."""
    L = level(w, h, sources, radius)
    rng = L.pop("rng")
    top_k, top_gap = 2, 0.15
    # Planes: homographies that shift each source by a plane-dependent offset.
    lams = np.linspace(0.5, 1.5, planes)
    Hs = np.zeros((planes, sources, 3, 3))
    for p, lam in enumerate(lams):
        for s in range(sources):
            Hs[p, s] = np.eye(3)
            Hs[p, s, 0, 2] = 2 + s + 3 * (lam - 1.0)
            Hs[p, s, 1, 2] = -2 + 1.5 * (lam - 1.0) + 0.01 * p
            Hs[p, s, 2, 0] = 1e-4 * s
    nray = (1.0 + 0.1 * rng.random((h, w))).astype(np.float32)
    usable = rng.random((h, w)) > 0.02
    w_lo = np.full((h, w), 0.3, np.float32)
    w_hi = np.full((h, w), 1.9, np.float32)
    w_hi[: h // 3, -w // 4 :] = 0.9  # some planes outside the bounds
    args = (L["ref"], L["mean"], L["var"], L["count"], L["srcs"], L["sizes"], L["src_ok"])

    def fresh() -> list[np.ndarray]:
        return [
            np.full((h, w), -np.inf, np.float32),
            np.zeros((h, w), np.int32),
            np.full((h, w), -1.0, np.float32),
            np.full((h, w), -1.0, np.float32),
        ]

    cpu = fresh()
    t0 = time.perf_counter()
    kernels.sweep(
        *args, L["active"], Hs, lams, nray, usable, w_lo, w_hi, radius, top_k, top_gap, *cpu,
        0, h,
    )  # fmt: skip
    inv = (0.6 + 0.8 * rng.random((h, w))).astype(np.float32)
    out_cpu = np.empty((h, w), np.float32)
    kernels.evaluate(
        *args, L["active"], L["a"], L["b"], inv, w_lo, w_hi, radius, top_k, top_gap, out_cpu,
        0, h,
    )  # fmt: skip
    t_cpu = time.perf_counter() - t0
    scorer = gpu.CudaScorer(*args, L["active"], radius, L["a"], L["b"])
    dev = fresh()
    t0 = time.perf_counter()
    scorer.sweep(Hs, lams, nray, usable, w_lo, w_hi, top_k, top_gap, *dev)
    out_gpu = scorer.evaluate(inv, w_lo, w_hi, top_k, top_gap)
    t_gpu = time.perf_counter() - t0
    same_idx = cpu[1] == dev[1]
    return {
        "device": gpu.cuda_status()[1],
        "size": [w, h],
        "sources": sources,
        "planes": planes,
        "sweep_best_max_diff": float(np.abs(cpu[0] - dev[0]).max()),
        "sweep_idx_differs": float(1.0 - same_idx.mean()),
        "sweep_neighbours_max_diff": float(
            max(np.abs(cpu[2] - dev[2])[same_idx].max(), np.abs(cpu[3] - dev[3])[same_idx].max())
        ),
        "evaluate_max_diff": float(np.abs(out_cpu - out_gpu).max()),
        "evaluate_scored": int((out_cpu > -1).sum()),
        "evaluate_unscored_same": bool(np.array_equal(out_cpu == -1, out_gpu == -1)),
        "seconds_cpu": t_cpu,
        "seconds_gpu_first_call": t_gpu,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--size", type=int, nargs=2, default=(24, 18), metavar=("W", "H"))
    ap.add_argument("--sources", type=int, default=3)
    ap.add_argument("--planes", type=int, default=6)
    ap.add_argument("--json", action="store_true")
    ns = ap.parse_args()
    res = compare(ns.size[0], ns.size[1], ns.sources, ns.planes)
    print(json.dumps(res) if ns.json else "\n".join(f"{k}: {v}" for k, v in res.items()))


if __name__ == "__main__":
    main()
