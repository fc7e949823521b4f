"""The online controller on the simulator: Table III-like statistics over seeds.

    python benchmarks/bench_controller.py               # ~1 min
    python benchmarks/bench_controller.py --seeds 50 --tasks 300 --json out.json

Sections:
* ``table3``: per deadline (5 / 7.5 / 10 s, the paper's Dance1 runs) and acceptance margin
  (0 and the paper's 1 s): search steps, chosen configuration against the noise-free optimum
  (same N' share, quality regret), mean time after convergence vs Δt, deadline misses.
* ``exact``: noise-free random models — the search finds the optimum within tau.
* ``adjust``: the minor adjustment's running average (paper: all tasks; ours: 5) and target.
* ``triggers``: load steps (x0.7, x1.4, x2) — re-search delay; false re-searches without one.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
from typing import Any

import numpy as np

from edgerecon.optimize import (
    BisectionController,
    ControllerConfig,
    PipelineModel,
    SimulatorConfig,
    run_simulation,
    true_optimum,
)

ROWS: list[dict[str, Any]] = []


def emit(section: str, **kw: Any) -> None:
    ROWS.append({"section": section, **kw})
    print(
        f"{section:9s} "
        + "  ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in kw.items()),
        flush=True,
    )


def table3(args: argparse.Namespace) -> None:
    sim = SimulatorConfig(time_noise=args.noise)
    model = PipelineModel(sim)
    for margin in (0.0, 1.0):
        for deadline in (5.0, 7.5, 10.0):
            cfg = ControllerConfig(deadline_s=deadline, margin_s=margin)
            opt = true_optimum(model, deadline)
            steps, same_n, regret, err, miss, conv, searches, scale, ncam = ([] for _ in range(9))
            for seed in range(args.seeds):
                res = run_simulation(deadline, args.tasks, seed=seed, simulator=sim, controller=cfg)
                s = res.summary
                steps.append(s.search_steps)
                searches.append(s.num_searches)
                if s.tasks_converged:
                    err.append(s.time_error)
                    miss.append(s.misses_converged / s.tasks_converged)
                    conv.append(s.tasks_converged)
                    scale.append(s.avg_scale)
                    ncam.append(s.num_cameras)
                    same_n.append(s.num_cameras == opt.num_cameras)
                    # regret of the converged configuration on the noise-free model
                    after = [r for r in res.rows if r.task >= (s.converged_task or 0)]
                    q = np.mean([model.quality(r.scale, r.num_cameras) for r in after])
                    regret.append(1 - q / opt.quality)
            emit(
                "table3",
                deadline_s=deadline,
                margin_s=margin,
                steps_mean=float(np.mean(steps)),
                steps_min=int(np.min(steps)),
                steps_max=int(np.max(steps)),
                opt=f"({opt.scale:.3f},{opt.num_cameras})",
                avg_scale=float(np.mean(scale)),
                cams_mode=int(np.bincount(ncam).argmax()),
                same_N_share=float(np.mean(same_n)),
                quality_regret_pct=100 * float(np.mean(regret)),
                time_err_pct_mean=100 * float(np.mean(err)),
                time_err_pct_max=100 * float(np.max(np.abs(err))),
                miss_pct_converged=100 * float(np.mean(miss)),
                searches_mean=float(np.mean(searches)),
            )


def exact(args: argparse.Namespace) -> None:
    rng = np.random.default_rng(0)
    ok = total = 0
    steps = []
    for _ in range(args.models):
        n = int(rng.integers(3, 13))
        sim = SimulatorConfig(
            num_cameras=n,
            base_s=float(rng.uniform(0, 3)),
            per_camera_s=float(rng.uniform(0.2, 2)),
            camera_exponent=float(rng.uniform(0.5, 1.8)),
            quality_scale_exponent=float(rng.uniform(0.2, 1.5)),
            quality_camera_exponent=float(rng.uniform(0, 1.5)),
            time_noise=0,
            quality_noise=0,
        )
        model = PipelineModel(sim)
        deadline = float(rng.uniform(model.time_s(0.3, 3), model.time_s(1.0, n) * 1.2))
        cfg = ControllerConfig(deadline_s=deadline)
        ctrl = BisectionController(cfg, {k: tuple(range(k)) for k in range(3, n + 1)}, n)
        for i in range(500):
            c = ctrl.next_config()
            t, q = model.sample(c.scale, c.num_cameras, i, rng)
            ctrl.observe(t, 1.0 if c.phase == "golden" else q)
            if ctrl.phase == "adjust":
                break
        opt = true_optimum(model, deadline, num_cameras=n)
        if not opt.feasible:
            continue
        total += 1
        steps.append(ctrl.search_steps)
        ch = ctrl.chosen
        floor = model.quality(max(0.3, opt.scale - cfg.tau), opt.num_cameras)
        ok += ch is not None and model.quality(ch.scale, ch.num_cameras) >= floor - 1e-12
    emit(
        "exact",
        feasible_models=total,
        optimum_within_tau=ok,
        steps_mean=float(np.mean(steps)),
        steps_max=int(np.max(steps)),
    )


def adjust(args: argparse.Namespace) -> None:
    for window in (0, 5, 10):
        for target in (1.0, 0.9):
            err, miss, rstd = [], [], []
            for deadline in (5.0, 7.5, 10.0):
                cfg = ControllerConfig(
                    deadline_s=deadline, adjust_window=window, adjust_target=target
                )
                for seed in range(args.seeds):
                    res = run_simulation(
                        deadline,
                        args.tasks,
                        seed=seed,
                        controller=cfg,
                        simulator=SimulatorConfig(time_noise=args.noise),
                    )
                    s = res.summary
                    if s.tasks_converged:
                        err.append(s.time_error)
                        miss.append(s.misses_converged / s.tasks_converged)
                        rstd.append(np.std([r.scale for r in res.rows[-s.tasks_converged :]]))
            emit(
                "adjust",
                window=window,
                target=target,
                time_err_pct_mean=100 * float(np.mean(err)),
                time_err_pct_max=100 * float(np.max(np.abs(err))),
                miss_pct=100 * float(np.mean(miss)),
                r_std=float(np.mean(rstd)),
            )


def triggers(args: argparse.Namespace) -> None:
    false = []
    for deadline in (5.0, 7.5, 10.0):
        for seed in range(args.seeds):
            res = run_simulation(
                deadline, args.tasks, seed=seed, simulator=SimulatorConfig(time_noise=args.noise)
            )
            false.append(sum(e["reason"] in ("drift", "slower") for e in res.events))
    emit(
        "triggers",
        load="x1 (none)",
        tasks=args.tasks * len(false),
        drift_or_slower_researches=int(np.sum(false)),
    )
    for factor in (0.7, 1.2, 1.4, 2.0):
        delays, errs = [], []
        for seed in range(args.seeds):
            sim = SimulatorConfig(time_noise=args.noise, load_steps=((100, factor),))
            res = run_simulation(7.5, max(args.tasks, 250), seed=seed, simulator=sim)
            ev = [e for e in res.events if e["task"] >= 100]
            delays.append(ev[0]["task"] - 100 if ev else -1)
            if res.summary.tasks_converged >= 20:
                errs.append(res.summary.time_error)
        detected = [d for d in delays if d >= 0]
        emit(
            "triggers",
            load=f"x{factor} at task 100",
            detected=f"{len(detected)}/{len(delays)}",
            delay_median=float(np.median(detected)) if detected else float("nan"),
            final_time_err_pct_max=100 * float(np.max(np.abs(errs))),
        )


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--section", nargs="+", default=["table3", "exact", "adjust", "triggers"])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--tasks", type=int, default=200)
    ap.add_argument("--models", type=int, default=500, help="random models in 'exact'")
    ap.add_argument("--noise", type=float, default=0.15)
    ap.add_argument("--json")
    args = ap.parse_args()
    for name in args.section:
        {"table3": table3, "exact": exact, "adjust": adjust, "triggers": triggers}[name](args)
    if args.json:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=False
        ).stdout.strip()
        with open(args.json, "w") as f:
            json.dump(
                {
                    "commit": commit,
                    "python": sys.version,
                    "machine": platform.machine(),
                    "numpy": np.__version__,
                    "args": vars(args),
                    "rows": ROWS,
                },
                f,
                indent=1,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
