"""``edgerecon report``: PNG figures and a one-page summary of one or more runs."""

from __future__ import annotations

import argparse
from pathlib import Path

from edgerecon.cli._common import add_json_flag, console, emit_json, print_table


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "report",
        help="plot a run: latency vs deadline, r and N', quality, background versions",
        description="Write PNG figures of runs (edgerecon run --out DIR) in the shape of the "
        "paper's: per-task latency against the deadline, image scale and cameras over "
        "tasks, online and offline quality, background versions, stage breakdown, and a "
        "one-page summary. Several runs (e.g. deadlines 5, 7.5, 10 s) share each figure.",
    )
    p.add_argument("run_dirs", nargs="+", metavar="RUN_DIR", help="run folder(s)")
    p.add_argument(
        "--out",
        "-o",
        default=None,
        help="folder of the figures (default: RUN_DIR/report of the first run)",
    )
    add_json_flag(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from edgerecon.report import write_report

    out = Path(args.out) if args.out else Path(args.run_dirs[0]) / "report"
    paths = write_report(args.run_dirs, out)
    if args.json:
        emit_json({"figures": {k: str(v) for k, v in paths.items()}})
    else:
        print_table("figures", ["figure", "file"], [(k, str(v)) for k, v in paths.items()])
        console.print(f"open {paths['summary']} for the one-page summary")
    return 0
