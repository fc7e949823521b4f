"""``edgerecon view``: watch a run (finished or running) in the browser."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
from collections.abc import Iterator
from typing import Any

from edgerecon.cli._common import add_json_flag, console, error_console
from edgerecon.viewer.colors import COLORINGS


def add_view_arguments(p: argparse.ArgumentParser, *, prefix: str = "") -> None:
    """The viewer's host and port (``run`` and ``demo`` use ``prefix="view-"``)."""
    p.add_argument(
        f"--{prefix}host",
        default="127.0.0.1",
        help="interface the viewer binds (default 127.0.0.1: this machine only; 0.0.0.0 "
        "serves the network)",
    )
    p.add_argument(
        f"--{prefix}port",
        type=int,
        default=8080,
        help="viewer port (default 8080; the next free one when taken)",
    )
    p.add_argument(
        f"--{prefix}points",
        type=int,
        default=150_000,
        help="most points drawn per cloud (default 150000)",
    )


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "view",
        help="watch a run in the browser (finished or still running)",
        description="Serve a run folder (edgerecon run --out DIR) to a browser: the newest "
        "merged cloud with switchable colourings, the cameras with the task's subset "
        "highlighted, the task's configuration, latency and quality, a chart over the "
        "tasks and a slider to replay them. Follows a running run as it writes tasks.",
    )
    p.add_argument("run_dir", help="run folder (the --out of edgerecon run / demo's DIR/run)")
    add_view_arguments(p)
    p.add_argument(
        "--coloring",
        choices=tuple(COLORINGS),
        default="rgb",
        help="initial colouring (the viewer's menu switches it)",
    )
    p.add_argument(
        "--nice",
        type=int,
        default=0,
        help="lower this process's CPU priority by this much (run --view uses 10)",
    )
    p.add_argument("--parent-pid", type=int, default=None, help=argparse.SUPPRESS)
    add_json_flag(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from edgerecon.viewer.server import ViewerConfig, require_viser, serve_run

    require_viser()
    if args.nice:
        os.nice(args.nice)
    config = ViewerConfig(
        host=args.host, port=args.port, point_budget=args.points, coloring=args.coloring
    )
    # Started next to a run (run --view), the folder may not exist yet: it is followed
    # from the moment it does.
    if args.parent_pid is None and not os.path.isdir(args.run_dir):
        raise ValueError(f"run folder not found: {args.run_dir}")
    viewer = serve_run(args.run_dir, config)
    if args.json:
        sys.stdout.write(json.dumps({"url": viewer.url, "port": viewer.port}) + "\n")
        sys.stdout.flush()
    else:
        console.print(f"viewer of {args.run_dir} at {viewer.url} (Ctrl-C to stop)")
    viewer.serve_forever(parent_pid=args.parent_pid)
    return 0


def add_live_view_arguments(p: argparse.ArgumentParser) -> None:
    """``--view`` and its options, for ``run`` and ``demo``."""
    p.add_argument(
        "--view",
        action="store_true",
        help="watch the run in the browser while it runs (a viewer process at lower "
        "priority; needs the [viewer] extra)",
    )
    add_view_arguments(p, prefix="view-")


@contextlib.contextmanager
def live_viewer(args: argparse.Namespace, run_dir: str | os.PathLike[str]) -> Iterator[Any]:
    """With ``--view``: a viewer process on ``run_dir`` for the duration of the block
    (``edgerecon view RUN_DIR`` shows the finished run again)."""
    if not getattr(args, "view", False):
        yield None
        return
    if getattr(args, "no_clouds", False):
        raise ValueError("--view shows the tasks' clouds: it cannot be used with --no-clouds")
    from edgerecon.viewer.process import start_viewer_process

    proc = start_viewer_process(
        run_dir, host=args.view_host, port=args.view_port, points=args.view_points
    )
    out = error_console if args.json else console
    out.print(f"viewer at {proc.url} (after the run: edgerecon view {run_dir})")
    try:
        yield proc
    finally:
        proc.stop()
