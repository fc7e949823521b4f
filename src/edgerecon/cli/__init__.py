"""The ``edgerecon`` command line: one subcommand per module in this package.

Each module ``edgerecon.cli.<name>`` (not starting with an underscore) defines
``register(subparsers)``, which adds its subcommand and sets ``func`` on it; ``func(args)``
returns the process exit code. Subcommands only parse arguments and call the library.

Global options (``-v``, ``-q``, ``--log-file``) are accepted before or after the
subcommand. Log lines carry a timestamp; ``--log-file`` gets every INFO line (DEBUG with
``-vv``) with the date, whatever the terminal shows. A mistyped subcommand or option gets
a "did you mean" suggestion.
"""

from __future__ import annotations

import argparse
import difflib
import importlib
import logging
import pkgutil
import re
import sys
from collections.abc import Sequence
from typing import Any, NoReturn

from rich.markup import escape
from rich.text import Text

from edgerecon import __version__, progress
from edgerecon.cli._common import console, error_console
from edgerecon.cli._config import explicit_dests
from edgerecon.types import EdgereconError

logger = logging.getLogger("edgerecon")

_CHOICE = re.compile(r"invalid choice: '([^']*)' \(choose from (.*)\)")


class Parser(argparse.ArgumentParser):
    """``ArgumentParser`` whose errors suggest the closest subcommand, choice or option."""

    _words: Sequence[str] = ()

    def parse_known_args(self, args: Any = None, namespace: Any = None) -> Any:
        self._words = list(sys.argv[1:] if args is None else args)
        return super().parse_known_args(args, namespace)

    def error(self, message: str) -> NoReturn:
        m = _CHOICE.search(message)
        if m:
            choices = re.findall(r"'([^']*)'", m.group(2))
            close = difflib.get_close_matches(m.group(1), choices, n=1, cutoff=0.5)
            if not close:
                close = [c for c in choices if c.startswith(m.group(1))][:1]
            if close:
                message += f"; did you mean '{close[0]}'?"
        elif message.startswith("unrecognized arguments:"):
            message += suggest_options(self._for_words(), message.split(":", 1)[1].split())
        elif message.startswith("the following arguments are required"):
            # A mistyped option often causes this: suggest from the words given.
            message += suggest_options(self, self._words)
        super().error(message)

    def _for_words(self) -> argparse.ArgumentParser:
        """The subcommand's parser when the words name one (its options are the ones to
        suggest), else this parser."""
        for action in self._actions:
            if isinstance(action, argparse._SubParsersAction):
                for w in self._words:
                    if w in action.choices:
                        return action.choices[w]
        return self


def suggest_options(parser: argparse.ArgumentParser, words: Sequence[str]) -> str:
    """'; did you mean --x?' for the first unknown option with a close known one."""
    known = [o for a in parser._actions for o in a.option_strings if o.startswith("--")]
    for w in words:
        if w.startswith("--") and w.split("=")[0] not in known:
            close = difflib.get_close_matches(w.split("=")[0], known, n=1, cutoff=0.6)
            if close:
                return f"; did you mean {close[0]}?"
    return ""


def _add_global_options(p: argparse.ArgumentParser, sub: bool) -> None:
    # In a subcommand the options keep their own destinations (argparse copies a
    # subcommand's namespace over the main one) and main() combines both.
    suffix = "_sub" if sub else ""
    default = argparse.SUPPRESS if sub else None
    g = p.add_argument_group("global options (before or after the subcommand)")
    g.add_argument(
        "-v",
        "--verbose",
        action="count",
        dest="verbose" + suffix,
        default=argparse.SUPPRESS if sub else 0,
        help="more log output (-vv for debug)",
    )
    g.add_argument(
        "-q",
        "--quiet",
        action="store_true",
        dest="quiet" + suffix,
        default=argparse.SUPPRESS if sub else False,
        help="only errors; no progress or phase lines",
    )
    g.add_argument(
        "--log-file",
        dest="log_file" + suffix,
        default=default,
        metavar="PATH",
        help="also write the log (timestamped, INFO and up; DEBUG with -vv) to PATH",
    )


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="edgerecon",
        description="Multi-view 3D reconstruction of dynamic scenes on edge devices.",
    )
    parser.add_argument("--version", action="version", version=f"edgerecon {__version__}")
    _add_global_options(parser, sub=False)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    sub.required = True
    names = sorted(m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_"))
    for name in names:
        module = importlib.import_module(f"{__name__}.{name}")
        module.register(sub)
    for p in sub.choices.values():
        _add_global_options(p, sub=True)
    return parser


class _ConsoleHandler(logging.Handler):
    """Log records printed through the rich console, so that they appear above a live
    display instead of breaking into it."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            # While a live display owns the terminal, print through its console (a second
            # console would write between its refreshes); stderr redirected: write there.
            live = progress.live_console() if error_console.is_terminal else None
            target = live if live is not None else error_console
            target.print(Text(self.format(record)), soft_wrap=True, highlight=False)
        except Exception:  # pragma: no cover - logging must never raise
            self.handleError(record)


def setup_logging(verbose: int, quiet: bool, log_file: str | None) -> None:
    """Handlers on the root logger: the terminal (WARNING, INFO with -v, DEBUG with -vv,
    ERROR with -q) and optionally a file (INFO, or DEBUG with -vv)."""
    root = logging.getLogger()
    for h in list(root.handlers):
        if getattr(h, "_edgerecon", False):
            root.removeHandler(h)
            h.close()
    level = logging.ERROR if quiet else logging.WARNING - 10 * min(verbose, 2)
    term = _ConsoleHandler(level)
    term.setFormatter(
        logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s", "%H:%M:%S")
    )
    handlers: list[logging.Handler] = [term]
    if log_file:
        file_level = logging.DEBUG if verbose >= 2 else logging.INFO
        fh = logging.FileHandler(log_file, encoding="utf-8")
        fh.setLevel(file_level)
        fh.setFormatter(
            logging.Formatter(
                "%(asctime)s.%(msecs)03d %(levelname)s %(threadName)s %(name)s: %(message)s",
                "%Y-%m-%d %H:%M:%S",
            )
        )
        handlers.append(fh)
    for h in handlers:
        h._edgerecon = True  # type: ignore[attr-defined]
        root.addHandler(h)
    root.setLevel(min(h.level for h in handlers))
    # Third-party debug chatter stays out of -vv and log files.
    for noisy in ("numba", "matplotlib", "PIL", "asyncio", "urllib3"):
        logging.getLogger(noisy).setLevel(logging.WARNING)


def _global(args: argparse.Namespace, name: str, default: Any) -> Any:
    value = getattr(args, name, default)
    sub = getattr(args, name + "_sub", None)
    if name == "verbose":
        return int(value or 0) + int(sub or 0)
    if name == "quiet":
        return bool(value) or bool(sub)
    return sub if sub is not None else value


def main(argv: Sequence[str] | None = None) -> int:
    from edgerecon.runtime.memory import tune_malloc

    tune_malloc()  # before any command starts threads or processes (runtime.memory)
    parser = build_parser()
    words = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(words)
    args._explicit = explicit_dests(parser, words)
    verbose = _global(args, "verbose", 0)
    quiet = _global(args, "quiet", False)
    try:
        setup_logging(verbose, quiet, _global(args, "log_file", None))
    except OSError as exc:
        error_console.print(f"[bold red]error:[/] --log-file: {escape(str(exc))}", highlight=False)
        return 2
    args.verbose, args.quiet = verbose, quiet
    json_out = bool(getattr(args, "json", False))
    # Progress bars, spinners and phase lines only on an interactive terminal, never with
    # --quiet or --json.
    progress.enable(
        error_console.is_terminal and not quiet and not json_out,
        console=error_console,
        announce=not quiet,
    )
    logger.debug("edgerecon %s: %s", __version__, " ".join(sys.argv if argv is None else argv))
    try:
        return int(args.func(args) or 0)
    except (EdgereconError, ValueError) as exc:
        # Bad input (files, calibration, option values): a message, not a traceback (-vv
        # shows the traceback for debugging).
        if verbose >= 2:
            raise
        logger.debug("error: %s", exc)
        # Never wrapped (paths stay whole in logs) and never read as rich markup.
        error_console.print(
            f"[bold red]error:[/] {escape(str(exc))}", highlight=False, soft_wrap=True
        )
        return 2
    except KeyboardInterrupt:
        error_console.print("[yellow]interrupted[/]")
        return 130


__all__ = ["build_parser", "console", "main"]
