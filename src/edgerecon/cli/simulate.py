"""``edgerecon simulate``: run the online controller (Algorithm 1 + minor adjustment) on the
simulated pipeline and print per-task rows and a Table III-like summary."""

from __future__ import annotations

import argparse
from typing import Any

from edgerecon.cli._common import add_json_flag, console, emit_json, print_table
from edgerecon.optimize.controller import BisectionController, ControllerConfig
from edgerecon.optimize.simulator import (
    PipelineModel,
    SimulationResult,
    SimulatorConfig,
    simulate,
    true_optimum,
)
from edgerecon.types import EdgereconError


class SimulateError(EdgereconError, ValueError):
    """Bad simulate option."""


def _load_step(text: str) -> tuple[int, float]:
    try:
        task, factor = text.split(":")
        return int(task), float(factor)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"--load-step expects TASK:FACTOR (e.g. 100:1.5), got {text!r}"
        ) from None


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "simulate",
        help="run the online optimizer on a simulated pipeline",
        description="Drive the bisection controller (Algorithm 1, pruning rules, minor "
        "adjustment, re-search triggers) with a latency/quality model T(r, N'), Q(r, N') "
        "resembling the paper's Dance1 runs, and summarise like the paper's Table III.",
    )
    p.add_argument(
        "--deadline",  # no -d: that is evaluate's distance threshold
        type=float,
        nargs="+",
        required=True,
        metavar="S",
        help="deadline(s) Δt in seconds; one run (and summary column) per deadline",
    )
    p.add_argument("--tasks", type=int, default=100, help="tasks per run (default 100)")
    p.add_argument(
        "--noise", type=float, default=0.15, help="timing noise, +/- share (default 0.15)"
    )
    p.add_argument(
        "--quality-noise", type=float, default=0.02, help="quality noise, +/- share (0.02)"
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--cameras", type=int, default=7, help="cameras N of the rig (default 7)")
    p.add_argument(
        "--margin",
        type=float,
        default=0.0,
        help="acceptance margin in seconds during the search (the paper used 1.0)",
    )
    p.add_argument(
        "--adjust-window",
        type=int,
        default=5,
        help="tasks in the minor adjustment's running average (0 = all, as in the paper)",
    )
    p.add_argument(
        "--late-share",
        type=float,
        default=None,
        metavar="P",
        help="about this share of the adjusted tasks may run late ([controller] late_share; "
        "default: the average steered to the deadline)",
    )
    p.add_argument("--drift", type=float, default=0.0, help="load growth per task (e.g. 0.003)")
    p.add_argument(
        "--load-step",
        type=_load_step,
        action="append",
        default=[],
        metavar="TASK:FACTOR",
        help="step change of the load from TASK on (repeatable)",
    )
    p.add_argument("--no-rows", action="store_true", help="print only the summary")
    add_json_flag(p)
    p.set_defaults(func=run)


def _run_one(args: argparse.Namespace, deadline: float) -> tuple[SimulationResult, Any]:
    try:
        sim = SimulatorConfig(
            num_cameras=args.cameras,
            time_noise=args.noise,
            quality_noise=args.quality_noise,
            drift_per_task=args.drift,
            load_steps=tuple(args.load_step),
        )
        cfg = ControllerConfig(
            deadline_s=deadline,
            margin_s=args.margin,
            adjust_window=args.adjust_window,
            late_share=args.late_share,
        )
    except ValueError as exc:
        raise SimulateError(str(exc)) from None
    if args.tasks < 1:
        raise SimulateError(f"--tasks must be >= 1, got {args.tasks}")
    model = PipelineModel(sim)
    mapping = {n: tuple(range(n)) for n in range(3, sim.num_cameras + 1)}
    ctrl = BisectionController(cfg, mapping, sim.num_cameras)
    result = simulate(ctrl, model, args.tasks, seed=args.seed)
    opt = true_optimum(model, cfg.accept_limit_s, cfg.r_min, cfg.r_max, cfg.min_cameras)
    return result, opt


def run(args: argparse.Namespace) -> int:
    results = [(d, *_run_one(args, d)) for d in args.deadline]
    if args.json:
        emit_json(
            {
                "runs": [
                    {
                        "deadline_s": d,
                        "summary": res.summary.to_dict(),
                        "chosen": res.chosen,
                        "true_optimum": opt.__dict__,
                        "events": res.events,
                        "rows": [r.to_dict() for r in res.rows],
                    }
                    for d, res, opt in results
                ]
            }
        )
        return 0
    if not args.no_rows:
        for d, res, _ in results:
            print_table(
                f"deadline {d:g} s: per task",
                ["task", "phase", "r", "N'", "time s", "F", "miss"],
                [
                    [
                        r.task,
                        r.phase,
                        round(r.scale, 3),
                        r.num_cameras,
                        r.time_s,
                        r.quality,
                        "x" if r.miss else "",
                    ]
                    for r in res.rows
                ],
            )
    cols = ["", *[f"Δt = {d:g} s" for d, _, _ in results]]

    def line(name: str, fn: Any) -> list[Any]:
        return [name, *[fn(res, opt) for _, res, opt in results]]

    def fmt(v: float, unit: str = "") -> str:
        return "-" if v != v else f"{v:.3f}{unit}"

    rows = [
        line("avg. resolution scale (converged)", lambda r, o: fmt(r.summary.avg_scale)),
        line("# cameras (converged)", lambda r, o: r.summary.num_cameras),
        line("avg. processing time", lambda r, o: fmt(r.summary.avg_time_s, " s")),
        line("avg. time (converged)", lambda r, o: fmt(r.summary.avg_time_converged_s, " s")),
        line("time error (converged)", lambda r, o: f"{100 * r.summary.time_error:+.2f} %"),
        line("avg. F (online estimate)", lambda r, o: fmt(r.summary.avg_quality)),
        line("# configuration search steps", lambda r, o: r.summary.search_steps),
        line("# searches (re-searches + 1)", lambda r, o: r.summary.num_searches),
        line(
            "deadline misses (all / converged)",
            lambda r, o: (
                f"{r.summary.misses} / {r.summary.misses_converged} of {r.summary.tasks_converged}"
            ),
        ),
        line(
            "search chose (r, N')",
            lambda r, o: "-" if r.chosen is None else f"({r.chosen[0]:.3f}, {r.chosen[1]})",
        ),
        line(
            "noise-free optimum (r, N')",
            lambda r, o: f"({o.scale:.3f}, {o.num_cameras})" if o.feasible else "infeasible",
        ),
    ]
    print_table("online optimization on the simulator (cf. the paper's Table III)", cols, rows)
    console.print(
        f"tasks {args.tasks}, timing noise ±{100 * args.noise:g} %, seed {args.seed}, "
        f"margin {args.margin:g} s"
    )
    return 0
