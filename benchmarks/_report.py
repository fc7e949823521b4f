"""Shared helpers of the benchmark commands: report headers (commit, versions, machine load),
tables and JSON reports."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TypeVar

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"

T = TypeVar("T")


def report_header() -> dict[str, Any]:
    """Where and when a measurement was taken: commit, library versions, CPU count, load."""
    import cv2
    import numpy
    import scipy

    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            cwd=Path(__file__).parent,
            check=False,
        ).stdout.strip()
    except OSError:
        commit = ""
    return {
        "commit": commit,
        "date": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "python": platform.python_version(),
        "numpy": numpy.__version__,
        "scipy": scipy.__version__,
        "opencv": cv2.__version__,
        "cpus": os.cpu_count(),
        "load_avg": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
    }


def print_rows(title: str, columns: Sequence[str], rows: Sequence[dict[str, Any]]) -> None:
    """A plain-text table of ``rows`` (dicts) restricted to ``columns``."""

    def fmt(v: Any) -> str:
        if v is None:
            return "-"
        if isinstance(v, float):
            return f"{v:.3f}" if abs(v) < 1000 else f"{v:,.0f}"
        return str(v)

    table = [[fmt(r.get(c)) for c in columns] for r in rows]
    widths = [
        max(len(c), *(len(row[i]) for row in table)) if table else len(c)
        for i, c in enumerate(columns)
    ]
    print(f"\n{title}")
    print("  ".join(c.rjust(w) for c, w in zip(columns, widths, strict=True)))
    for row in table:
        print("  ".join(v.rjust(w) for v, w in zip(row, widths, strict=True)))


def write_report(path: str | Path, data: dict[str, Any]) -> None:
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(data, indent=2, default=str) + "\n")


def with_settings(config: T, items: Sequence[str], where: str) -> T:
    """``config`` (a configuration dataclass) with ``FIELD=VALUE`` settings (``--set``) on top,
    read as the ``[where]`` table of a ``--config`` file would be (``configfile.build``: TOML
    values, the same checks and messages; dotted fields reach nested tables)."""
    import tomllib

    from edgerecon.configfile import ConfigError, build

    table: dict[str, Any] = {}
    for item in items:
        path, sep, text = item.partition("=")
        if not sep:
            raise SystemExit(f"--set wants FIELD=VALUE, got {item!r}")
        *parents, name = path.strip().split(".")
        try:
            value = tomllib.loads(f"v = {text.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = text.strip()  # a bare word: a string setting
        node = table
        for part in parents:
            node = node.setdefault(part, {})
        node[name] = value
    try:
        return build(type(config), table, base=config, where=where)
    except ConfigError as exc:
        raise SystemExit(f"--set: {exc}") from None
