"""Progress reporting for long operations: loops (``track``) and phases (``phase``).

Library code wraps long loops in :func:`track` and long steps in :func:`phase`; both are
silent (``phase`` only logs and records its time) unless the CLI (or a user) turns the
display on with :func:`enable`. Keeping the switch here, rather than passing a callback
through every stage, keeps the pure stage signatures free of UI concerns.

The terminal has **one live display at a time**, owned by the main thread: a transient
progress bar of ``track``, a spinner of ``phase``, or a display that a command installs with
:func:`own_display` (``run``'s task rows and status line). While one is active, nested loops
and phases do not start their own (they update the owner's status line instead), and loops
on other threads (the back-end's) never draw: nothing else writes into the display. Log
records and finished phases are printed through the same console, above the display.

``collect()`` gathers the finished phases of a command (name, seconds) so that it can print
them with the wall time: what a user waited for is accounted for.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any, TypeVar

T = TypeVar("T")

logger = logging.getLogger(__name__)

_enabled = False
_console: Any = None  # rich Console the displays draw on (stderr), set by enable()
_announce = True
_owner: Any = None  # the active live display, or None
_status_hook: Callable[[str], None] | None = None  # an owner's status line, if it has one
_live_console: Any = None  # the console an owner's display draws on (print through it)
_collectors: list[PhaseLog] = []
_lock = threading.RLock()


@dataclass(frozen=True)
class Phase:
    """One finished phase."""

    name: str
    seconds: float
    depth: int
    """0 for a top-level phase, 1 inside another, ..."""


@dataclass
class PhaseLog:
    """The phases finished while ``collect()`` was active (main thread only)."""

    phases: list[Phase] = field(default_factory=list)
    started: float = field(default_factory=time.perf_counter)

    @property
    def top_level(self) -> list[Phase]:
        return [p for p in self.phases if p.depth == 0]

    @property
    def total(self) -> float:
        return float(sum(p.seconds for p in self.top_level))

    def to_dict(self) -> dict[str, float]:
        out: dict[str, float] = {}
        for p in self.top_level:
            out[p.name] = round(out.get(p.name, 0.0) + p.seconds, 6)
        return out


def enable(on: bool = True, console: Any = None, announce: bool = True) -> None:
    """Show progress bars and phase spinners on ``console`` (a rich Console, default
    stderr); ``announce``: print a line for each phase that took over a second."""
    global _enabled, _console, _announce
    _enabled = on
    _announce = announce
    if console is not None:
        _console = console


def enabled() -> bool:
    return _enabled


def _get_console() -> Any:
    global _console
    if _console is None:
        from rich.console import Console

        _console = Console(stderr=True, highlight=False)
    return _console


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


@contextlib.contextmanager
def own_display(status: Callable[[str], None] | None = None, console: Any = None) -> Iterator[None]:
    """Mark the caller's live display as the terminal's only one for the duration;
    ``status`` receives the text of phases and loops that run meanwhile; ``console`` is the
    console it draws on, through which log lines must be printed (``live_console``)."""
    global _owner, _status_hook, _live_console
    with _lock:
        previous = (_owner, _status_hook, _live_console)
        _owner, _status_hook, _live_console = object(), status, console
    try:
        yield
    finally:
        with _lock:
            _owner, _status_hook, _live_console = previous


def live_console() -> Any:
    """The console of the active live display (print there to appear above it), or None."""
    return _live_console


@contextlib.contextmanager
def collect() -> Iterator[PhaseLog]:
    """Gather the phases finished on the main thread inside the block."""
    log = PhaseLog()
    _collectors.append(log)
    try:
        yield log
    finally:
        _collectors.remove(log)


_depth = 0  # nesting of phases on the main thread


@contextlib.contextmanager
def phase(name: str, *, announce_after_s: float = 1.0) -> Iterator[None]:
    """Time a step. Logged when it ends; recorded by ``collect()``; with the display on, a
    spinner runs meanwhile and a line ``HH:MM:SS name  S.S s`` is printed when it took
    longer than ``announce_after_s``."""
    global _depth
    main = _main_thread()
    t0 = time.perf_counter()
    logger.debug("%s ...", name)
    spinner = None
    hook = None
    if _enabled and main:
        with _lock:
            if _owner is None and _depth == 0:
                from rich.status import Status

                spinner = Status(f"{name} ...", console=_get_console(), spinner="dots")
            elif _status_hook is not None:
                hook = _status_hook
    if hook is not None:
        hook(f"{name} ...")
    depth = _depth if main else -1
    if main:
        _depth += 1
    try:
        if spinner is not None:
            status = spinner
            with _claim(lambda text: status.update(f"{name} ... {text}"), status.console), spinner:
                yield
        else:
            yield
    finally:
        if main:
            _depth -= 1
        seconds = time.perf_counter() - t0
        logger.info("%s: %.2f s", name, seconds)
        if main:
            for log in _collectors:
                log.phases.append(Phase(name=name, seconds=seconds, depth=depth))
        if hook is not None:
            hook("")
        if _enabled and _announce and main and depth == 0 and seconds >= announce_after_s:
            # Through the live display's console when one is active (above it).
            (_live_console or _get_console()).print(
                f"[dim]{time.strftime('%H:%M:%S')}[/] {name} [dim]{seconds:.1f} s[/]",
                highlight=False,
                soft_wrap=True,
            )


@contextlib.contextmanager
def _claim(status: Callable[[str], None] | None = None, console: Any = None) -> Iterator[None]:
    global _owner, _status_hook, _live_console
    with _lock:
        _owner, _status_hook, _live_console = object(), status, console
    try:
        yield
    finally:
        with _lock:
            _owner, _status_hook, _live_console = None, None, None


def track(items: Iterable[T], description: str, total: int | None = None) -> Iterator[T]:
    """Iterate over ``items``, showing a transient progress bar when enabled (main thread,
    no other live display; inside an owner's display its status line counts instead)."""
    if total is None:
        try:
            total = len(items)  # type: ignore[arg-type]
        except TypeError:
            total = None
    if not _enabled or not _main_thread():
        yield from items
        return
    with _lock:
        free = _owner is None
        hook = None if free else _status_hook
    if not free:
        if hook is None:
            yield from items
            return
        for i, item in enumerate(items, start=1):
            yield item
            hook(f"{description} {i}/{total}" if total else f"{description} {i}")
        hook("")
        return
    from rich.progress import Progress

    with _claim(None, _get_console()), Progress(transient=True, console=_get_console()) as bar:
        task = bar.add_task(description, total=total)
        for item in items:
            yield item
            bar.advance(task)
