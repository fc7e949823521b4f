"""Threads of the dense stage: per-view work on a few threads, and the idle threads' cores
lent to the depth maps still running (``RowBands``). The compiled kernels release the GIL,
and so do NumPy's and OpenCV's array operations, so plain threads run in parallel."""

from __future__ import annotations

import itertools
import queue
import threading
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

from edgerecon.progress import track
from edgerecon.threads import pool
from edgerecon.types import TaskCancelled

#: Bands narrower than this many rows are not worth a thread hand-off.
_MIN_BAND_ROWS = 32


class RowBands:
    """Lends the idle threads of the dense stage to the depth maps still running.

    Depth maps run one per thread; a thread that finds no map left to start calls
    :meth:`lend`, and the kernels of the maps still running (the sweep and the hypothesis
    scoring, which are row-separable: an output row depends only on the rows within the
    window radius) then split their rows with it, so the last maps of a task do not run on
    one core while the others idle. The bands are the same whether they run in parallel
    or not, so the result does not depend on timing. The bands run on the calling thread's
    pool (``edgerecon.threads``), made once."""

    def __init__(self, num_threads: int) -> None:
        self._max_extra = max(num_threads - 1, 0)
        self._idle = threading.Semaphore(0)
        self._pool = pool("dense-band", self._max_extra) if self._max_extra else None

    def lend(self) -> None:
        """The calling thread has no more work of its own: its core may take row bands."""
        self._idle.release()

    def run(self, kernel: Callable[[int, int], None], height: int) -> None:
        """``kernel(row0, row1)`` over the rows ``0 <= y < height`` in fixed bands (one per
        thread of the stage, so that the result never depends on timing), on the idle
        threads' cores when there are any and one after the other on this thread otherwise."""
        num = max(1, min(self._max_extra + 1, height // _MIN_BAND_ROWS))
        edges = [round(k * height / num) for k in range(num + 1)]
        bands = list(itertools.pairwise(edges))
        extra = 0
        while extra < num - 1 and self._idle.acquire(blocking=False):
            extra += 1
        try:
            futures = []
            if extra:
                assert self._pool is not None
                futures = [self._pool.submit(kernel, a, b) for a, b in bands[num - extra :]]
            for a, b in bands[: num - extra]:
                kernel(a, b)
            for f in futures:
                f.result()
        finally:
            for _ in range(extra):
                self._idle.release()


T = TypeVar("T")
R = TypeVar("R")


def run_jobs(
    fn: Callable[[T], R],
    jobs: Sequence[T],
    num_threads: int,
    bands: RowBands,
    label: str,
    *,
    cancel: threading.Event | None = None,
) -> list[R]:
    """``[fn(job) for job in jobs]`` on ``num_threads`` threads that take the jobs in order;
    a thread that finds none left lends its core to the others (``bands.lend``), and so do
    the threads that have no job from the start (one foreground ROI: its kernels run on
    every core). Progress follows the finished jobs; the first error is raised once every
    job has ended. Once ``cancel`` is set no job starts (the jobs left end as
    :class:`TaskCancelled` at once), so a cancelled caller gets its threads back after the
    jobs already running."""
    for _ in range(max(num_threads - max(len(jobs), 1), 0)):
        bands.lend()

    def guarded(job: T) -> R:
        if cancel is not None and cancel.is_set():
            raise TaskCancelled(f"{label}: cancelled")
        return fn(job)

    if num_threads <= 1 or len(jobs) <= 1:
        return list(track(map(guarded, jobs), label, total=len(jobs)))
    results: list[Any] = [None] * len(jobs)
    counter = itertools.count()
    finished: queue.Queue[BaseException | None] = queue.Queue()

    def worker() -> None:
        try:
            while (k := next(counter)) < len(jobs):
                try:
                    results[k] = guarded(jobs[k])
                    finished.put(None)
                except BaseException as exc:  # re-raised by the caller
                    finished.put(exc)
        finally:
            bands.lend()

    workers = pool("dense", num_threads)
    running = [workers.submit(worker) for _ in range(min(num_threads, len(jobs)))]
    errors = [e for e in track((finished.get() for _ in jobs), label, total=len(jobs)) if e]
    for f in running:
        f.result()
    if errors:
        raise errors[0]
    return results
