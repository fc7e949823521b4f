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
import queue
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
    """What :meth:`Runner.call` saw: ``value`` when ``fn`` returned, ``error`` when it
    raised, neither while it still runs on ``thread`` (``timed_out``)."""

    thread: threading.Thread
    finished: threading.Event
    value: T | None = None
    error: BaseException | None = None

    @property
    def timed_out(self) -> bool:
        return not self.finished.is_set()

    def wait(self, timeout: float | None = None) -> bool:
        """Wait for the call to end (True when it did)."""
        return self.finished.wait(timeout)


_Job = tuple[Callable[[], object], dict[str, object], threading.Event, str]


def _serve(jobs: queue.SimpleQueue[_Job | None]) -> None:
    me = threading.current_thread()
    idle = me.name
    try:
        while (job := jobs.get()) is not None:
            fn, box, finished, name = job
            me.name = name  # what it runs, while it runs
            try:
                box["value"] = fn()
            except BaseException as exc:  # ThreadAbandoned included: nobody reads it then
                box["error"] = exc
            finally:
                me.name = idle
                finished.set()
            del job, fn, box
    except ThreadAbandoned:  # stopped between two calls: it was given up on anyway
        pass


class Runner:
    """Calls, one at a time, on a daemon thread that lasts from one call to the next (it
    inherits the niceness of the thread that made it). A thread made per call would cost a
    little memory per call for good (``edgerecon.threads``); a call still running when its
    limit is reached gives the thread up: the thread ends after that call (the caller
    decides what to do with it: ``_restore_scene``, :meth:`AbandonedThreads.abandon`) and
    the next call starts a new one. Not for concurrent callers."""

    def __init__(self, name: str) -> None:
        self.name = name
        self._thread: threading.Thread | None = None
        self._jobs: queue.SimpleQueue[_Job | None] = queue.SimpleQueue()

    def call(self, fn: Callable[[], T], limit_s: float, name: str | None = None) -> Bounded[T]:
        """``fn()`` on the runner's thread (named ``name`` while it runs), waited for
        ``limit_s`` seconds. Still running then: what it returns or raises later is
        dropped."""
        thread = self._thread
        if thread is None or not thread.is_alive():
            self._jobs = queue.SimpleQueue()
            thread = self._thread = threading.Thread(
                target=_serve, args=(self._jobs,), name=self.name, daemon=True
            )
            thread.start()
        box: dict[str, object] = {}
        finished = threading.Event()
        self._jobs.put((fn, box, finished, name or self.name))
        if not finished.wait(limit_s):
            self._jobs.put(None)  # the thread ends after this call; the next starts another
            self._thread = None
            return Bounded(thread, finished)
        error = box.get("error")
        return Bounded(
            thread,
            finished,
            value=cast("T | None", box.get("value")),
            error=error if isinstance(error, BaseException) else None,
        )

    def close(self) -> None:
        """Let the thread end once it is idle."""
        if self._thread is not None:
            self._jobs.put(None)
            self._thread = None

    def __del__(self) -> None:
        self.close()


__all__ = ["AbandonedThreads", "Bounded", "Runner", "ThreadAbandoned", "stop_thread"]
