"""Camera selection (problem P2): solver time and covered points per size, with the gap to the
best solution known (an exact solver where one finishes, else a long CP-SAT run warm-started
from local search, and the best of every solver tried).

    python benchmarks/bench_camera_selection.py                 # all sections, ~5 min
    python benchmarks/bench_camera_selection.py --section large --long 60
    python benchmarks/bench_camera_selection.py --json out.json

Sections: ``small`` (exact solvers against each other, N = 7..14), ``brute`` (the subset-sum
brute force for the whole mapping pi(N'), N = 12..22), ``large`` (N = 30, P = 5,000: local
search, key-point reductions, auto, against a long run), ``real`` (the k-means reduction on
the sparse cloud of a real or synthetic scene, when one is given with --visibility).
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import subprocess
import sys
import time
from dataclasses import replace
from typing import Any

import numpy as np

from edgerecon.optimize import selection as sel
from edgerecon.optimize.selection import CameraSelector, SelectionConfig, aggregate_patterns
from edgerecon.optimize.simulator import random_visibility, synthetic_visibility

ROWS: list[dict[str, Any]] = []


def row(**kw: Any) -> None:
    ROWS.append(kw)
    gap = kw.get("gap_pct")
    print(
        f"{kw['section']:6s} {kw['kind']:6s} N={kw['N']:3d} P={kw['P']:6d} N'={kw.get('k', '-')!s:>4s} "
        f"{kw['solver']:26s} {kw['seconds']:8.3f}s covered={kw.get('covered', '-')!s:>6s} "
        f"gap={'-' if gap is None else f'{gap:.2f}%':>7s} {kw.get('note', '')}",
        flush=True,
    )


def instance(kind: str, n: int, p: int, seed: int) -> np.ndarray:
    if kind == "ring":
        return synthetic_visibility(n, p, seed=seed)[0]
    return random_visibility(n, p, density=0.25, seed=seed)


def timed(fn: Any, *args: Any, **kw: Any) -> tuple[Any, float]:
    t0 = time.perf_counter()
    out = fn(*args, **kw)
    return out, time.perf_counter() - t0


def section_small(args: argparse.Namespace) -> None:
    for kind in ("ring", "random"):
        for n in (7, 10, 12, 14):
            vis = instance(kind, n, 5000, seed=n)
            k = n // 2
            t0 = time.perf_counter()
            ref = CameraSelector(vis, SelectionConfig(solver="brute_force")).selection(k)
            dt = time.perf_counter() - t0
            row(
                section="small",
                kind=kind,
                N=n,
                P=5000,
                k=k,
                solver="brute_force (all N')",
                seconds=dt,
                covered=ref.covered,
                gap_pct=0.0,
            )
            solvers = [("cpsat", {}), ("milp", {"milp_formulation": "strong"})]
            if n <= 7:
                solvers.append(("milp", {"milp_formulation": "naive"}))
            for name, extra in solvers:
                cfg = SelectionConfig(
                    solver=name,
                    max_key_points=0,
                    time_limit_s=args.limit,
                    cpsat_work_limit=None,
                    **extra,
                )
                s, dt = timed(CameraSelector(vis, cfg).selection, k)
                label = name + (f" ({extra['milp_formulation']})" if extra else "")
                row(
                    section="small",
                    kind=kind,
                    N=n,
                    P=5000,
                    k=k,
                    solver=label,
                    seconds=dt,
                    covered=s.covered,
                    gap_pct=100 * (1 - s.covered / ref.covered),
                    note="optimal" if s.optimal else "not proven",
                )
            s, dt = timed(CameraSelector(vis, SelectionConfig(solver="local_search")).selection, k)
            row(
                section="small",
                kind=kind,
                N=n,
                P=5000,
                k=k,
                solver="local_search",
                seconds=dt,
                covered=s.covered,
                gap_pct=100 * (1 - s.covered / ref.covered),
            )


def section_brute(args: argparse.Namespace) -> None:
    for n in (12, 16, 18, 20, 22):
        vis = instance("ring", n, 5000, seed=n)
        t0 = time.perf_counter()
        sl = CameraSelector(vis, SelectionConfig(solver="brute_force", brute_force_max_cameras=22))
        m = sl.mapping()
        dt = time.perf_counter() - t0
        row(
            section="brute",
            kind="ring",
            N=n,
            P=5000,
            k="all",
            solver="brute_force (mapping)",
            seconds=dt,
            covered=m.selection(n // 2).covered,
            gap_pct=0.0,
            note=f"{len(m.sizes)} sizes",
        )


def best_known(vis: np.ndarray, k: int, long_s: float, start: tuple[int, ...]) -> tuple[int, str]:
    """Best covered count a long exact run finds: exact enumeration when affordable, else
    CP-SAT for ``long_s`` seconds (2 workers, wall clock) warm-started from ``start``."""
    pat = aggregate_patterns(vis)
    n = vis.shape[1]
    if math.comb(n, k) * pat.num_patterns <= 1_000_000_000:
        _cols, cov, _ = sel._enumerate_exact(pat, k, 2)
        return cov, "exact (enumeration)"
    cfg = SelectionConfig(time_limit_s=long_s, cpsat_work_limit=None, num_workers=2)
    _cols, cov, proven, bound = sel._cpsat_solve(pat, k, 2, cfg, hint=start)
    return cov, f"CP-SAT {long_s:.0f}s {'optimal' if proven else f'bound {bound}'}"


def section_large(args: argparse.Namespace) -> None:
    n, p = 30, 5000
    for kind in ("ring", "random"):
        vis = instance(kind, n, p, seed=args.seed)
        pat = aggregate_patterns(vis)
        print(
            f"# {kind}: {pat.num_patterns} distinct coverable patterns, "
            f"{pat.total_weight} coverable points",
            flush=True,
        )
        for k in args.sizes:
            results: dict[str, tuple[int, float, tuple[int, ...]]] = {}
            ls = CameraSelector(vis, SelectionConfig(solver="local_search"))
            s, dt = timed(ls.selection, k)
            results["local_search"] = (s.covered, dt, s.camera_ids)
            for kp in args.key_points:
                cfg = SelectionConfig(solver="cpsat", max_key_points=kp)
                t0 = time.perf_counter()
                selector = CameraSelector(vis, cfg)
                work = selector._working()
                cols, _, _, _ = sel._cpsat_solve(work, k, 2, cfg, hint=None)
                dt = time.perf_counter() - t0
                ids = tuple(sorted(cols))
                results[f"keypoints {kp} + CP-SAT (no hint)"] = (sel.coverage(vis, ids), dt, ids)
            for kp in args.key_points:
                cfg = SelectionConfig(max_key_points=kp)
                t0 = time.perf_counter()
                s = CameraSelector(vis, cfg).selection(k)
                dt = time.perf_counter() - t0
                results[f"auto (kp {kp}): {s.solver}"] = (s.covered, dt, s.camera_ids)
            start = max(results.values(), key=lambda x: x[0])[2]
            ref, how = best_known(vis, k, args.long, start)
            ref = max(ref, max(v[0] for v in results.values()))
            for name, (cov, dt, _) in results.items():
                row(
                    section="large",
                    kind=kind,
                    N=n,
                    P=p,
                    k=k,
                    solver=name,
                    seconds=dt,
                    covered=cov,
                    gap_pct=100 * (1 - cov / ref),
                    note=f"ref {ref} ({how})",
                )


def section_real(args: argparse.Namespace) -> None:
    """Loss of the k-means key-point reduction alone: the reduced problem solved exactly
    (brute force), its answer scored on the full visibility, against the exact answer."""
    if not args.visibility:
        vis_sets = [("synthetic ring 16x20000", synthetic_visibility(16, 20000, seed=3)[0])]
    else:
        vis_sets = [(path, np.load(path).astype(bool)) for path in args.visibility]
    for name, vis in vis_sets:
        n = vis.shape[1]
        full = aggregate_patterns(vis)
        exact = sel._brute_force_all(full, 2)
        for kp in args.key_points:
            t0 = time.perf_counter()
            red = sel.reduce_patterns_kmeans(full, kp)
            dt = time.perf_counter() - t0
            approx = sel._brute_force_all(red, 2)
            gaps = []
            for k in range(3, n + 1):
                ref = exact[k][1]
                cov = sel._pattern_coverage(full, approx[k][0], 2)
                gaps.append(100 * (1 - cov / ref) if ref else 0.0)
            row(
                section="real",
                kind="kmeans",
                N=n,
                P=vis.shape[0],
                k="all",
                solver=f"keypoints {kp} (exact on them)",
                seconds=dt,
                covered=red.num_patterns,
                gap_pct=max(gaps),
                note=f"max gap over N'=3..{n}, mean {np.mean(gaps):.2f}%, "
                f"{full.num_patterns} patterns; covered column = key patterns; {name}",
            )


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--section", nargs="+", default=["small", "brute", "large", "real"])
    ap.add_argument("--limit", type=float, default=1.0, help="per-solve time limit (s)")
    ap.add_argument("--long", type=float, default=30.0, help="long reference run (s)")
    ap.add_argument("--sizes", type=int, nargs="+", default=[5, 10, 15, 20, 25])
    ap.add_argument("--key-points", type=int, nargs="+", default=[64, 256])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--visibility", nargs="*", help=".npy (P x N bool) visibility matrices")
    ap.add_argument("--json", help="write rows and environment to this file")
    args = ap.parse_args()
    for name in args.section:
        {
            "small": section_small,
            "brute": section_brute,
            "large": section_large,
            "real": section_real,
        }[name](args)
    if args.json:
        try:
            commit = subprocess.run(
                ["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=False
            ).stdout.strip()
        except OSError:
            commit = ""
        import ortools
        import scipy

        with open(args.json, "w") as f:
            json.dump(
                {
                    "commit": commit,
                    "python": sys.version,
                    "machine": platform.machine(),
                    "numpy": np.__version__,
                    "scipy": scipy.__version__,
                    "ortools": ortools.__version__,
                    "rows": ROWS,
                },
                f,
                indent=1,
            )
    return 0


if __name__ == "__main__":
    _ = replace
    raise SystemExit(main())
