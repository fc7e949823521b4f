"""The ``edgerecon`` command line: one subcommand per module in this package.

Each module ``edgerecon.cli.<name>`` (not starting with an underscore) defines
``register(subparsers)``, which adds its subcommand and sets ``func`` on it; ``func(args)``
returns the process exit code. Subcommands only parse arguments and call the library.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import pkgutil
import sys
from collections.abc import Sequence

from rich.markup import escape

from edgerecon import __version__, progress
from edgerecon.cli._common import console, error_console
from edgerecon.types import EdgereconError

logger = logging.getLogger("edgerecon")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="edgerecon",
        description="Multi-view 3D reconstruction of dynamic scenes on edge devices.",
    )
    parser.add_argument("--version", action="version", version=f"edgerecon {__version__}")
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)"
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    names = sorted(m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_"))
    for name in names:
        module = importlib.import_module(f"{__name__}.{name}")
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(
        level=level, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr
    )
    # Progress bars only on an interactive terminal and never when JSON goes to stdout.
    progress.enable(error_console.is_terminal and not getattr(args, "json", False))
    try:
        return int(args.func(args) or 0)
    except (EdgereconError, ValueError) as exc:
        # Bad input (files, calibration, option values): a message, not a traceback (-vv
        # shows the traceback for debugging).
        if args.verbose >= 2:
            raise
        # Never wrapped (paths stay whole in logs) and never read as rich markup.
        error_console.print(
            f"[bold red]error:[/] {escape(str(exc))}", highlight=False, soft_wrap=True
        )
        return 2
    except KeyboardInterrupt:
        error_console.print("[yellow]interrupted[/]")
        return 130


__all__ = ["build_parser", "console", "main"]
