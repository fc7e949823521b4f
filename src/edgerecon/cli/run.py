"""``edgerecon run``: the online system on a dataset, task by task, within a deadline."""

from __future__ import annotations

import argparse
import math
from typing import Any

from edgerecon.cli._common import add_json_flag, console, emit_json, print_table
from edgerecon.cli._config import (
    add_config_flag,
    load_config,
    online_configs,
    run_options_table,
    write_effective,
)
from edgerecon.cli._live import TaskDisplay
from edgerecon.cli.reconstruct import parse_cameras
from edgerecon.io.dataset import open_dataset
from edgerecon.runtime import FrameRange, RunSummary, SessionOptions, TaskMetrics
from edgerecon.runtime.config import SPARSE_SCOPES
from edgerecon.runtime.online import run_online


def add_online_arguments(p: argparse.ArgumentParser) -> None:
    """Options shared by ``run`` and ``demo``."""
    p.add_argument(
        "--deadline",
        type=float,
        required=False,
        metavar="S",
        help="deadline per task in seconds (the average critical path aims at it); required "
        "by run unless --config's [runtime] sets deadline_s",
    )
    add_config_flag(p)
    p.add_argument("--frames", default=None, help="timestamps A:B:STEP (default: the whole stream)")
    p.add_argument(
        "--engine",
        choices=("embedded", "ray"),
        default="embedded",
        help="embedded: both roles in this process (default); ray: actors on a Ray cluster",
    )
    p.add_argument(
        "--address",
        default=None,
        help="Ray cluster address (e.g. 'auto' or HEAD_IP:6379); default: a private "
        "local Ray instance on 127.0.0.1",
    )
    p.add_argument(
        "--policy",
        choices=("all", "newest"),
        default="all",
        help="all: every listed timestamp is a task; newest: frames arrive in real "
        "time and each task takes the newest one",
    )
    p.add_argument(
        "--fixed",
        type=float,
        default=None,
        metavar="SCALE",
        help="no optimizer: run every task at this scale (with --cameras)",
    )
    p.add_argument("--cameras", default=None, help="camera ids for --fixed (default: all)")
    p.add_argument(
        "--no-background-updates",
        action="store_true",
        help="the back-end never rebuilds the background",
    )
    p.add_argument(
        "--sparse-scope",
        choices=SPARSE_SCOPES,
        default="foreground",
        help="foreground: SfM of the foreground masks only, after they arrive (default); "
        "scene: the paper's SfM of the whole frames, then the split",
    )
    p.add_argument("--no-clouds", action="store_true", help="do not write per-task clouds")
    p.add_argument(
        "--resume", action="store_true", help="continue after the last task recorded in --out"
    )
    p.add_argument(
        "--inject-fault",
        default=None,
        metavar="TASK:KIND[:SECONDS]",
        help="drill: before task TASK, make the back-end stall (KIND=stall), crash "
        "(crash) or, with Ray, kill its process (kill)",
    )


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run",
        help="run the online system (front-end + back-end) on a dataset",
        description="Reconstruct a stream task by task within a deadline: the optimizer picks "
        "the image scale and cameras, the back-end computes masks, golden references and "
        "backgrounds. Writes metrics.jsonl, per-task merged clouds and summary.json.",
    )
    p.add_argument("--dataset", required=True, help="dataset folder")
    p.add_argument("--out", "-o", required=True, help="output folder")
    add_online_arguments(p)
    add_json_flag(p)
    p.set_defaults(func=run)


def parse_fault(text: str | None) -> tuple[int, str, float] | None:
    if not text:
        return None
    parts = text.split(":")
    if len(parts) not in (2, 3) or parts[1] not in ("stall", "crash", "kill"):
        raise ValueError(f"--inject-fault must be TASK:stall|crash|kill[:SECONDS], got {text!r}")
    return int(parts[0]), parts[1], float(parts[2]) if len(parts) == 3 else 30.0


def task_row(m: TaskMetrics) -> list[Any]:
    if m.status != "ok":
        return [m.task, m.time_index, "FAILED", "", "", "", "", "", "", m.error[:40]]
    f_on = "-" if m.online_fscore is None else f"{m.online_fscore:.3f}"
    f_off = "-" if m.offline_fscore is None else f"{m.offline_fscore:.3f}"
    return [
        m.task,
        m.time_index,
        m.phase,
        f"{m.scale:.2f}",
        m.num_cameras,
        f"{m.critical_path_s:.2f}",
        "yes" if m.deadline_met else "NO",
        f_on,
        f_off,
        f"v{m.bg_version}" + (" degraded" if m.degraded else ""),
    ]


TASK_COLUMNS = [
    "task",
    "time",
    "phase",
    "r",
    "N'",
    "T (s)",
    "met",
    "F online",
    "F offline",
    "background",
]


def live_printer(enabled: bool, total: int | None = None) -> TaskDisplay:
    """The task rows and the status line (task i/N, ETA) of a run: a context manager and
    the ``on_task`` callback (see ``cli._live``)."""
    widths = [4, 6, 7, 5, 3, 7, 4, 8, 9, 20]
    return TaskDisplay(columns=TASK_COLUMNS, widths=widths, row=task_row, total=total, rows=enabled)


def num_tasks(args: argparse.Namespace, dataset: Any) -> int | None:
    """How many tasks ``--frames`` makes (at most, with --policy newest)."""
    try:
        frames = FrameRange.parse(args.frames) if args.frames else FrameRange()
    except ValueError:
        return None
    return len(frames.indices(dataset.num_frames)) or None


def print_summary(title: str, s: RunSummary) -> None:
    def f(x: float | None, fmt: str = ".3f") -> str:
        return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, fmt)

    rows = [
        ("deadline (s)", f(s.deadline_s, ".2f")),
        ("avg. resolution scale", f(s.avg_scale, ".2f")),
        ("# cameras (avg / last subset)", f"{f(s.avg_cameras, '.1f')} / {s.cameras_used}"),
        ("avg. processing time (s)", f(s.avg_time_s, ".2f")),
        ("avg. time after convergence (s)", f(s.avg_time_converged_s, ".2f")),
        ("deadline misses after convergence", s.deadline_misses_converged),
        ("avg. F-score of FG (online)", f(s.avg_online_fscore)),
        ("avg. F-score of FG (vs ground truth)", f(s.avg_offline_fscore)),
        ("# backgrounds pushed", s.backgrounds_pushed),
        ("# configuration search steps", s.search_steps),
        ("tasks / failed / degraded", f"{s.tasks} / {s.failed} / {s.degraded}"),
        ("frames dropped (newest policy)", s.frames_dropped),
        ("wall time (s)", f(s.wall_s, ".1f")),
    ]
    print_table(title, ["metric", "value"], rows)
    if s.stage_means_s:
        print_table(
            "critical path per task (mean seconds)",
            ["stage", "seconds"],
            sorted(s.stage_means_s.items(), key=lambda kv: -kv[1]),
        )


def build_options(
    args: argparse.Namespace, dataset: Any, gt_threshold: float | None
) -> SessionOptions:
    return SessionOptions(
        frames=FrameRange.parse(args.frames) if args.frames else FrameRange(),
        policy=args.policy,
        write_clouds=not args.no_clouds,
        ground_truth_threshold=gt_threshold if dataset.ground_truth is not None else None,
        resume=args.resume,
        fault=parse_fault(args.inject_fault),
    )


def run(args: argparse.Namespace) -> int:
    dataset = open_dataset(args.dataset)
    config, controller_config = online_configs(args, load_config(args))
    fixed = None
    if args.fixed is not None:
        fixed = (args.fixed, parse_cameras(args.cameras, dataset.rig))
    options = build_options(args, dataset, config.eval_threshold_for(dataset.rig))
    with live_printer(not args.json, num_tasks(args, dataset)) as on_task:
        summary, metrics = run_online(
            dataset,
            config,
            options,
            args.out,
            engine=args.engine,
            address=args.address,
            fixed=fixed,
            controller_config=controller_config,
            on_task=on_task,
        )
    effective = {"runtime": config, "controller": controller_config, "run": run_options_table(args)}
    write_effective(args.out, "run", effective)
    if args.json:
        emit_json({"summary": summary.to_dict(), "tasks": [m.to_dict() for m in metrics]})
    else:
        print_summary(f"{dataset.name}: online run, deadline {config.deadline_s:g} s", summary)
        console.print(f"outputs in {args.out}")
    return 0
