"""Stopping the threads of work the runtime gave up on (a stage that hung).

The watchdog abandons a task still running after its limit: the task's ``cancel`` event
stops it at its next stage boundary or before its next depth map. A stage that never gets
there (a loop that does not end) would keep its thread, and on a 2-core device a thread
that spins takes a core from every later task. :func:`stop_thread` raises
:class:`ThreadAbandoned` inside such a thread (CPython's ``PyThreadState_SetAsyncExc``): the
exception is raised at the thread's next Python instruction, so a stage looping in Python
code ends at once and one blocked inside a native call (a compiled kernel, OpenCV, a lock
wait without timeout) ends when that call returns. ``finally`` blocks and ``with`` exits run
on the way out, so the locks it holds are released. :class:`AbandonedThreads` keeps the
threads given up on and says which still run (``RunSummary.abandoned_threads``).
"""

from __future__ import annotations

import ctypes
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar, cast

T = TypeVar("T")

logger = logging.getLogger(__name__)

#: Seconds an abandoned thread has to end on its own before it is stopped.
GRACE_S = 2.0


class ThreadAbandoned(BaseException):
    """Raised inside a thread whose work the runtime abandoned. A ``BaseException``: the
    stages' ``except Exception`` handlers (a camera left out, a degraded result) do not
    swallow it and go on working."""


def stop_thread(thread: threading.Thread) -> bool:
    """Raise :class:`ThreadAbandoned` in ``thread`` at its next Python instruction. False
    when it has already ended (or was never started)."""
    ident = thread.ident
    if ident is None or not thread.is_alive():
        return False
    set_async_exc = ctypes.pythonapi.PyThreadState_SetAsyncExc
    done = set_async_exc(ctypes.c_ulong(ident), ctypes.py_object(ThreadAbandoned))
    if done > 1:  # more than one thread state matched: undo (CPython's documented protocol)
        set_async_exc(ctypes.c_ulong(ident), None)
        return False
    return bool(done == 1)


class AbandonedThreads:
    """The threads of abandoned work: each is stopped when given up on, and the ones still
    running (blocked inside a native call) are counted."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._threads: list[tuple[threading.Thread, str]] = []

    def abandon(self, thread: threading.Thread, what: str, grace_s: float = GRACE_S) -> None:
        """Give up on ``thread`` (doing ``what``): unless it ends within ``grace_s`` (its
        work was cancelled: it stops at its next check), stop it, and keep it to count.
        Raising in a thread that is releasing a lock could leave the lock held: the grace
        lets a thread on its way out finish, so the threads stopped are the ones stuck."""
        thread.join(grace_s)
        stopped = stop_thread(thread)
        logger.warning(
            "%s: %s",
            what,
            "stopping its thread (an exception raised at its next Python instruction)"
            if stopped
            else "its thread ended on its own",
        )
        with self._lock:
            self._threads = [(t, w) for t, w in self._threads if t.is_alive()]
            if stopped:
                self._threads.append((thread, what))

    def running(self) -> list[str]:
        """What the abandoned threads still running were doing."""
        with self._lock:
            self._threads = [(t, w) for t, w in self._threads if t.is_alive()]
            return [w for _, w in self._threads]


@dataclass(frozen=True)
class Bounded(Generic[T]):
    """What :func:`call_bounded` saw: ``value`` when ``fn`` returned, ``error`` when it
    raised, neither while its ``thread`` still runs (``timed_out``)."""

    thread: threading.Thread
    value: T | None = None
    error: BaseException | None = None

    @property
    def timed_out(self) -> bool:
        return self.thread.is_alive()


def call_bounded(fn: Callable[[], T], limit_s: float, name: str) -> Bounded[T]:
    """``fn()`` in a daemon thread of its own (it inherits the caller's niceness), waited
    for ``limit_s`` seconds. Still running then: the caller decides (``_restore_scene``,
    :meth:`AbandonedThreads.abandon`); what it returns or raises later is dropped."""
    box: dict[str, object] = {}

    def run() -> None:
        try:
            box["value"] = fn()
        except BaseException as exc:  # ThreadAbandoned included: nobody reads it then
            box["error"] = exc

    thread = threading.Thread(target=run, name=name, daemon=True)
    thread.start()
    thread.join(limit_s)
    if thread.is_alive():
        return Bounded(thread)
    error = box.get("error")
    return Bounded(
        thread,
        value=cast("T | None", box.get("value")),
        error=error if isinstance(error, BaseException) else None,
    )


__all__ = ["AbandonedThreads", "Bounded", "ThreadAbandoned", "call_bounded", "stop_thread"]
