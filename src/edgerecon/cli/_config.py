"""``--config FILE.toml`` for the subcommands: loading, command-line precedence, and the
effective configuration written next to the outputs (see ``edgerecon.configfile``)."""

from __future__ import annotations

import argparse
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from edgerecon import __version__
from edgerecon.configfile import load_config_file, write_config

#: File name of the effective configuration in an output folder.
CONFIG_NAME = "config.toml"


@dataclass(frozen=True)
class DeadlineShare:
    """``--deadline 40%``: the deadline as a share of the original pipeline's time, measured
    when the run starts (``RuntimeConfig.deadline_share``)."""

    fraction: float

    def __str__(self) -> str:
        return f"{100 * self.fraction:g}%"


def parse_deadline(text: str) -> float | DeadlineShare:
    """``--deadline``: seconds (``0.6``) or a share of the original pipeline (``40%``)."""
    from edgerecon.runtime.config import MAX_DEADLINE_SHARE

    word = text.strip()
    share = word.endswith("%")
    try:
        value = float(word[:-1] if share else word)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: seconds (0.6) or a share of the original pipeline's time (40%)"
        ) from None
    if share:
        fraction = value / 100
        if not 0 < fraction <= MAX_DEADLINE_SHARE:
            raise argparse.ArgumentTypeError(
                f"{text!r}: a share in (0%, {100 * MAX_DEADLINE_SHARE:g}%]"
            )
        return DeadlineShare(fraction)
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"{text!r}: a deadline must be > 0 seconds")
    return value


def add_config_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--config",
        metavar="FILE.toml",
        help="settings of every stage (tables [reconstruction], [runtime], [controller]; "
        f"an output folder's {CONFIG_NAME} loads again); options given here win",
    )


def load_config(args: argparse.Namespace) -> dict[str, Any]:
    path = getattr(args, "config", None)
    return load_config_file(path) if path else {}


def given(args: argparse.Namespace, *dests: str) -> bool:
    """Whether any of the options ``dests`` was typed on the command line (not defaulted)."""
    explicit = getattr(args, "_explicit", None)
    if explicit is None:
        return True  # called without main(): treat every value as given
    return any(d in explicit for d in dests)


def explicit_dests(parser: argparse.ArgumentParser, words: list[str]) -> set[str]:
    """Destinations of the options that appear in ``words`` (for ``given``)."""
    out = set()
    for action in parser._actions:
        for opt in action.option_strings:
            for w in words:
                if (
                    w == opt
                    or (opt.startswith("--") and w.startswith(opt + "="))
                    or (
                        not opt.startswith("--")
                        and len(opt) == 2
                        and w.startswith(opt)
                        and w != opt
                        and not w.startswith("--")
                    )
                ):
                    out.add(action.dest)
        if isinstance(action, argparse._SubParsersAction):
            for w in words:
                if w in action.choices:
                    out |= explicit_dests(action.choices[w], words)
    return out


def write_effective(
    out_dir: str | os.PathLike[str], command: str, sections: dict[str, Any]
) -> Path:
    """``OUT/config.toml``: the configuration a command ran with, loadable by ``--config``."""
    header = (
        f"Effective configuration of `edgerecon {command}` (edgerecon {__version__}).\n"
        f"Load it again with --config {Path(out_dir) / CONFIG_NAME}"
    )
    return write_config(Path(out_dir) / CONFIG_NAME, sections, header=header)


def online_configs(args: argparse.Namespace, cfg: dict[str, Any]) -> tuple[Any, Any]:
    """``RuntimeConfig`` and ``ControllerConfig`` of ``run`` / ``demo``: the file's
    [runtime] / [controller] with the options typed on the command line on top; [run]
    fills ``--frames`` / ``--policy`` / ``--engine`` when they were not typed."""
    from edgerecon.configfile import build, section
    from edgerecon.optimize.controller import ControllerConfig
    from edgerecon.runtime.config import RuntimeConfig

    for key in ("frames", "policy", "engine", "sparse_scope"):
        if key in section(cfg, "run") and not given(args, key) and hasattr(args, key):
            setattr(args, key, section(cfg, "run")[key])
    rt = section(cfg, "runtime")
    over: dict[str, Any] = {}
    if isinstance(args.deadline, DeadlineShare):
        over["deadline_share"] = args.deadline.fraction
        over["deadline_s"] = math.nan
    elif args.deadline is not None:
        over["deadline_s"] = args.deadline
        rt = {k: v for k, v in rt.items() if k != "deadline_share"}  # seconds typed win
    elif "deadline_s" not in rt and rt.get("deadline_share") is None:
        raise ValueError(
            "--deadline is required (seconds per task, or a share of the original pipeline's "
            "time such as 40%), or deadline_s / deadline_share in the [runtime] table of --config"
        )
    if getattr(args, "no_background_updates", False):
        over["background_updates"] = False
    # Options that mirror a RuntimeConfig field: typed ones win, else the file, else the
    # option's default.
    for dest in ("sparse_scope", "background_scale", "online_quality"):
        if hasattr(args, dest) and (given(args, dest) or dest not in rt):
            over[dest] = getattr(args, dest)
    runtime = build(RuntimeConfig, rt, where="runtime", overrides=over)
    # The runtime's adjust_target unless the [controller] table sets its own; a deadline
    # given as a share is the runtime's once measured (``run_online``: 1 s until then).
    deadline = 1.0 if runtime.deadline_share is not None else runtime.deadline_s
    ctrl_over: dict[str, Any] = {"deadline_s": deadline}
    if "adjust_target" not in section(cfg, "controller"):
        ctrl_over["adjust_target"] = runtime.adjust_target
    if getattr(args, "late_share", None) is not None:
        ctrl_over["late_share"] = args.late_share
    controller = build(
        ControllerConfig,
        section(cfg, "controller"),
        where="controller",
        overrides=ctrl_over,
        exclude={"deadline_s"},
    )
    return runtime, controller


def run_options_table(args: argparse.Namespace) -> dict[str, Any]:
    """The [run] table of an online run's effective configuration."""
    return {
        "frames": args.frames,
        "policy": args.policy,
        "engine": args.engine,
        "fixed": args.fixed,
        "cameras": args.cameras,
    }
