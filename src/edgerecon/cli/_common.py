"""Shared helpers of the CLI subcommands: consoles, JSON output, tables, common options."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from rich.console import Console
from rich.table import Table

if TYPE_CHECKING:
    from edgerecon.io.dataset import Dataset

console = Console(highlight=False)
error_console = Console(stderr=True, highlight=False)


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating):
        return float(obj)
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if hasattr(obj, "to_dict"):
        return obj.to_dict()
    return str(obj)


def to_json(data: Any, indent: int | None = 2) -> str:
    return json.dumps(data, indent=indent, default=_json_default)


def emit_json(data: Any) -> None:
    """Print machine-readable results to stdout (and nothing else goes to stdout)."""
    sys.stdout.write(to_json(data) + "\n")
    sys.stdout.flush()


def add_json_flag(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--json",
        action="store_true",
        help="print machine-readable results (JSON) to stdout instead of tables",
    )


def print_table(
    title: str, columns: Sequence[str], rows: Iterable[Sequence[Any]], stderr: bool = False
) -> None:
    table = Table(title=title)
    for col in columns:
        table.add_column(col, justify="right" if col not in ("stage", "camera", "name") else "left")
    for row in rows:
        table.add_row(*[_fmt(v) for v in row])
    out = error_console if stderr else console
    if not out.is_terminal:
        # Piped or redirected: the table at its natural width, never cut ("1080x1…").
        natural = out.measure(table, options=out.options.update(max_width=1000)).maximum
        if natural > out.width:
            out = Console(file=out.file, width=natural, highlight=False)
    out.print(table)


def _fmt(v: Any) -> str:
    if isinstance(v, float | np.floating):
        x = float(v)
        return f"{x:.4g}" if abs(x) < 1e4 else f"{x:,.0f}"
    return str(v)


def dataset_to_check(path: str, *, write: bool, what: str) -> Dataset:
    """The dataset a check command reads (``sync``, ``calib``): recorded frames, and with
    ``--write`` a ``dataset.json`` to write ``what`` into (``DataError`` otherwise)."""
    from edgerecon.io.dataset import DESCRIPTOR, open_dataset
    from edgerecon.types import DataError

    ds = open_dataset(path)
    if ds.is_live:
        raise DataError("a live dataset cannot be checked (its frames are not kept)")
    if write and ds.layout != "descriptor":
        raise DataError(
            f"{ds.root} has no {DESCRIPTOR} to {what} (a layout detected from its files): make "
            "one with edgerecon import"
        )
    return ds
