"""The live display of ``run`` and ``demo``: one row per finished task and one status line
(task i/N, elapsed, ETA, what is running now), the terminal's only live display.

* stdout a terminal: a rich ``Live`` on stdout with the status line at the bottom; task rows
  are printed above it; writes to stdout and stderr (log lines, warnings, other libraries'
  prints) are redirected through it, and loops on other threads (the back-end's) never draw
  (``edgerecon.progress``), so nothing interleaves.
* stdout piped (``run ... | tee log``, whose output lands on the same terminal): rows only,
  as whole lines; no spinner or progress bar redraws a line meanwhile. ``--json``: nothing
  until the end.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

from rich.console import Console
from rich.live import Live
from rich.text import Text

from edgerecon import progress
from edgerecon.cli._common import console, error_console


def _clock(seconds: float) -> str:
    s = round(seconds)
    return (
        f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"
    )


class _Status:
    """The status line, rendered at each refresh (the elapsed time ticks)."""

    def __init__(self, display: TaskDisplay) -> None:
        self.display = display

    def __rich__(self) -> Text:
        return Text(
            self.display.status_text(), style="bold cyan", no_wrap=True, overflow="ellipsis"
        )


class TaskDisplay:
    """Callable ``on_task(metrics)`` and context manager; see the module docstring."""

    def __init__(
        self,
        *,
        columns: Sequence[str],
        widths: Sequence[int],
        row: Callable[[Any], Sequence[Any]],
        total: int | None,
        rows: bool = True,
        live: bool | None = None,
        out: Console | None = None,
        err: Console | None = None,
    ) -> None:
        self.columns, self.widths, self.row = list(columns), list(widths), row
        self.total = total
        self.rows = rows
        self.out = out or console
        self.err = err or error_console
        if live is None:
            live = rows and self.out.is_terminal
        self.live_on = live
        self.done = 0
        self.started = time.perf_counter()
        self.first_done: float | None = None
        self.last_done: float | None = None
        self.activity = "starting: opening the dataset, learning the background, loading kernels"
        self._header = False
        self._live: Live | None = None
        self._lock = threading.Lock()
        self._owner: Any = None

    # ---------------------------------------------------------------- status line
    def status_text(self) -> str:
        now = time.perf_counter()
        total = f"/{self.total}" if self.total else ""
        parts = [f"task {self.done + 1 if self.done < (self.total or 10**9) else self.done}{total}"]
        parts.append(f"elapsed {_clock(now - self.started)}")
        if self.done >= 1 and self.first_done is not None and self.last_done is not None:
            per = (
                (self.last_done - self.first_done) / max(1, self.done - 1)
                if self.done > 1
                else (self.last_done - self.started)
            )
            parts.append(f"{per:.1f} s/task")
            if self.total:
                parts.append(f"ETA {_clock(max(0, self.total - self.done) * per)}")
        if self.activity:
            parts.append(self.activity)
        return "  ".join(parts)

    def set_activity(self, text: str) -> None:
        self.activity = text or ("running" if self.done else self.activity)

    # ---------------------------------------------------------------- lifecycle
    def __enter__(self) -> TaskDisplay:
        if not self.live_on:
            # Still the only display: no phase spinner or progress bar may start meanwhile.
            self._owner = progress.own_display(None, None)
            self._owner.__enter__()
        else:
            target = self.out
            self._live = Live(
                _Status(self),
                console=target,
                refresh_per_second=4,
                transient=True,
                redirect_stdout=True,
                redirect_stderr=True,
            )
            self._live.start()
            self._owner = progress.own_display(self.set_activity, target)
            self._owner.__enter__()
        return self

    def __exit__(self, *exc: Any) -> None:
        if self._owner is not None:
            self._owner.__exit__(*exc)
            self._owner = None
        if self._live is not None:
            self._live.stop()
            self._live = None

    # ---------------------------------------------------------------- rows
    def _line(self, values: Sequence[Any]) -> str:
        return " ".join(str(v).rjust(w) for v, w in zip(values, self.widths, strict=True))

    def __call__(self, metrics: Any) -> None:
        with self._lock:
            now = time.perf_counter()
            self.done += 1
            if self.first_done is None:
                self.first_done = now
            self.last_done = now
            self.activity = "running"
            if not self.rows:
                return
            # One line per task even on an 80-column pipe (no wrapping).
            if not self._header:
                self.out.print(f"[bold]{self._line(self.columns)}[/]", soft_wrap=True)
                self._header = True
            self.out.print(self._line(self.row(metrics)), soft_wrap=True, highlight=False)
            if not self.out.is_terminal:
                sys.stdout.flush()


__all__ = ["TaskDisplay"]
