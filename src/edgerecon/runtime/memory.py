"""The C heap of a long run: few malloc arenas, image-sized blocks mapped on their own, the
heap trimmed, so that memory does not creep up for hours.

glibc's malloc gives each thread that allocates an arena of its own, up to 8 per core (16 on
a 2-core device). A task's stages run in several threads (the watchdog's worker, OpenCV's
and numba's pools, the back-end's, the stream readers'), each allocating and freeing image-
and cloud-sized blocks; the arenas fragment and the resident memory steps up and stays. On
caliscope_charuco served as a live stream (``benchmarks/bench_soak.py``, 4 x 1280x720,
~1.9 tasks per second) the run's main process grew from 1.55 GB to 2.63 GB over 900 s
(about 1 GB per 1000 tasks, in steps); with two arenas set when the command starts it held
1.08-1.26 GB from the fifth minute to the thirtieth (3,364 tasks). Over 110 minutes it
still rose, 1.04 GB in the first five minutes to 1.38 GB at 30 and 1.54 GB at the end
(+23 MB per 1000 tasks).

What still grew was glibc's mapping threshold: a block from 128 KiB on is mapped on its own
and given back when freed, but each free of such a block raises the threshold to its size
(up to 32 MiB), so after the first frames every image, depth map and cloud column came from
the arenas, whose holes between blocks still in use add up. A fixed threshold
(``mallopt(M_MMAP_THRESHOLD)``, 1 MiB) keeps them mapped: the same 45-minute stream held the
main process at 0.56-0.66 GB (medians per five minutes; 1.04-1.44 GB before), +16 MB per
1000 tasks, the rebuild process at 0.37-0.41 GB (0.50). The price is the page faults of
fresh mappings, the kernel's zeroed pages: tasks at r = 1 on caliscope_charuco took 0.562 s
instead of 0.528 s on average (+6 %; four alternated runs of 60 tasks each), a golden task
1.74 s instead of 1.61 s (+8 %). So only a long run maps them (:func:`long_run`: a live
stream, ``--duration``, more than :data:`LONG_RUN_TASKS` tasks), where hours of creeping
memory cost more than 6 % of the time; ``MALLOC_MMAP_THRESHOLD_`` set by the user wins
either way (1048576 for any run, 33554432 to turn it off).

:func:`tune_malloc` sets the limits for this process (``mallopt``, for what is still to be
allocated: call it before the work starts) and, through ``MALLOC_ARENA_MAX`` and
``MALLOC_MMAP_THRESHOLD_``, for the processes it starts (the background rebuild's, a private
Ray instance's workers). Other C libraries (musl, macOS) are left as they are.
:func:`start_heap_trimmer` gives the heap's free pages back every 30 s in a run's processes
(the session's, the rebuild's, Ray's actors, the viewer's). :func:`resident_mb` is what each
task records (``TaskMetrics.rss_mb``). See docs/BENCHMARKS.md.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, cast

logger = logging.getLogger(__name__)

#: glibc's ``mallopt`` parameters (malloc.h): the arena count, the size from which a block
#: is mapped on its own.
_M_ARENA_MAX = -8
_M_MMAP_THRESHOLD = -3
#: Arenas a run uses (one per core of the 2-core devices it targets).
ARENAS = 2
#: In a long run, blocks from this size on (an image, a depth map, a cloud's columns) are
#: mapped on their own and given back when freed.
MMAP_THRESHOLD = 1 << 20
#: A run of more tasks than this maps them (:func:`long_run`); ~20 minutes at 2 tasks / s.
LONG_RUN_TASKS = 2000


def long_run(*, live: bool, duration_s: float | None, num_tasks: int) -> bool:
    """Whether a run goes on long enough for its memory to creep up: a live stream, a run
    bounded by ``--duration``, or more than ``LONG_RUN_TASKS`` tasks to do."""
    return live or duration_s is not None or num_tasks > LONG_RUN_TASKS


@dataclass(frozen=True)
class MallocTuning:
    """What :func:`tune_malloc` set in this process (None: not set)."""

    arenas: int | None
    mmap_threshold: int | None


_done: dict[int, int] = {}


def _glibc(name: str, argtypes: list[Any]) -> Any | None:
    """glibc's function ``name`` (returning an int) with ``argtypes``, None elsewhere."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        fn = getattr(ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6"), name)
    except (OSError, AttributeError):  # not glibc
        return None
    fn.argtypes = argtypes
    fn.restype = ctypes.c_int
    return fn


def _mallopt() -> Callable[[int, int], int] | None:
    """glibc's ``mallopt``, None elsewhere."""
    return cast("Callable[[int, int], int] | None", _glibc("mallopt", [ctypes.c_int] * 2))


def _set(env: str, param: int, default: int) -> int | None:
    """``mallopt(param, value)`` with the user's ``env`` value, else ``default``, which the
    processes started from here inherit through ``env``; the value set, or None."""
    text = os.environ.setdefault(env, str(int(default)))
    try:
        value = int(text)
    except ValueError:
        logger.warning("%s=%r is not a number: malloc left as it is there", env, text)
        return None
    if _done.get(param) == value:
        return value
    mallopt = _mallopt()
    if mallopt is None:
        return None
    if not mallopt(param, value):
        logger.debug("mallopt(%d, %d) refused", param, value)
        return None
    _done[param] = value
    return value


def tune_malloc(arenas: int = ARENAS, mmap_threshold: int | None = None) -> MallocTuning:
    """Limit glibc's malloc to ``arenas`` arenas in this process and the ones it starts
    (``MALLOC_ARENA_MAX``); with ``mmap_threshold`` (a long run's: :data:`MMAP_THRESHOLD`),
    or where the user set ``MALLOC_MMAP_THRESHOLD_``, also map blocks from that many bytes
    on their own. A value the user put in the environment wins. Call it before the work
    starts. Elsewhere than glibc nothing is done but the environment variables."""
    threshold = None
    if mmap_threshold is not None or "MALLOC_MMAP_THRESHOLD_" in os.environ:
        default = MMAP_THRESHOLD if mmap_threshold is None else mmap_threshold
        threshold = _set("MALLOC_MMAP_THRESHOLD_", _M_MMAP_THRESHOLD, default)
    return MallocTuning(
        arenas=_set("MALLOC_ARENA_MAX", _M_ARENA_MAX, arenas), mmap_threshold=threshold
    )


def _malloc_trim() -> Callable[[int], int] | None:
    """glibc's ``malloc_trim``, None elsewhere."""
    return cast("Callable[[int], int] | None", _glibc("malloc_trim", [ctypes.c_size_t]))


def resident_mb() -> float | None:
    """This process's resident memory now, MB (Linux's ``/proc/self/statm``; None
    elsewhere)."""
    try:
        with open("/proc/self/statm", encoding="ascii") as f:
            pages = int(f.read().split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return round(pages * os.sysconf("SC_PAGE_SIZE") / 2**20, 1)


def peak_resident_mb() -> float | None:
    """This process's largest resident memory so far, MB: Linux's ``VmHWM`` (the high-water
    mark of this program's memory; ``getrusage``'s ``ru_maxrss`` also counts the parent's
    memory copied by the fork before ``exec``: a run started by a 1.3 GB benchmark reported
    1.3 GB while it never held 0.64 GB), ``getrusage`` elsewhere; None where neither says."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return round(int(line.split()[1]) / 1024.0, 1)
    except (OSError, ValueError, IndexError):
        pass
    try:
        import resource
    except ImportError:  # not POSIX
        return None
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return round(peak / (2**20 if sys.platform == "darwin" else 2**10), 1)  # bytes / KiB


#: Seconds between two ``malloc_trim`` calls of a run's processes.
TRIM_INTERVAL_S = 30.0
_trimmer: threading.Thread | None = None
_trim_lock = threading.Lock()
_trim_stop = threading.Event()


def start_heap_trimmer(interval_s: float = TRIM_INTERVAL_S) -> bool:
    """Give the C heap's free pages back to the system every ``interval_s`` in this process
    (``malloc_trim(0)``: free pages inside the arenas too, not only at their tops), from a
    daemon thread, once per process. Two arenas keep a long run's fragmentation low, not at
    zero: freed holes between blocks still in use add up over an hour. A trim holds each
    arena's lock for a few milliseconds. Returns whether a trimmer runs (glibc only)."""
    global _trimmer
    trim = _malloc_trim()
    if trim is None:
        return False
    with _trim_lock:
        if _trimmer is not None and _trimmer.is_alive():
            return True

        _trim_stop.clear()

        def loop() -> None:
            while not _trim_stop.wait(interval_s):
                t0 = time.perf_counter()
                trim(0)
                logger.debug("malloc_trim: %.1f ms", 1000 * (time.perf_counter() - t0))

        _trimmer = threading.Thread(target=loop, name="heap-trim", daemon=True)
        _trimmer.start()
    return True


def stop_heap_trimmer(timeout: float = 5.0) -> None:
    """Stop this process's trimmer (tests; a run's processes keep theirs)."""
    global _trimmer
    with _trim_lock:
        thread, _trimmer = _trimmer, None
        _trim_stop.set()
    if thread is not None:
        thread.join(timeout)


__all__ = [
    "ARENAS",
    "LONG_RUN_TASKS",
    "MMAP_THRESHOLD",
    "TRIM_INTERVAL_S",
    "MallocTuning",
    "long_run",
    "peak_resident_mb",
    "resident_mb",
    "start_heap_trimmer",
    "stop_heap_trimmer",
    "tune_malloc",
]
