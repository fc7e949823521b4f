"""Worker threads that last: the per-camera and per-view work of every stage runs on pools
owned by the thread that hands the work out, made once and kept.

A thread made per call (a pool per stage call, a thread per task) costs little time, but
native libraries keep a little per-thread data that outlives the thread: OpenCV 5.1 keeps
0.2-0.7 KB per thread that ever called it (``benchmarks/bench_threads.py``), and a task made
about ten threads, so a long run's memory grew with the tasks for that alone. Here each
caller thread (a task's thread, the back-end's loops) owns one pool per ``site``, so the
threads are made once per caller: a caller never waits behind another caller's work (the
front-end's critical path does not queue behind the back-end's rebuild), and a pool's thread
that hands out work of its own gets pools of its own (nested calls cannot deadlock). A
caller's pools end with it: its thread-local storage is dropped when it ends, the pools are
collected and their idle threads exit.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")

_local = threading.local()


def _forget_pools() -> None:
    # A forked child has none of the parent's threads: the forking thread starts new pools.
    global _local
    _local = threading.local()


os.register_at_fork(after_in_child=_forget_pools)


def pool(site: str, num_threads: int) -> ThreadPoolExecutor:
    """The calling thread's pool of ``num_threads`` threads for ``site`` (made on the first
    call, the same one after). Work submitted to it from one call site at a time never waits
    for another caller's."""
    pools: dict[tuple[str, int], ThreadPoolExecutor] | None = getattr(_local, "pools", None)
    if pools is None:
        pools = _local.pools = {}
    key = (site, num_threads)
    found = pools.get(key)
    if found is None:
        found = pools[key] = ThreadPoolExecutor(num_threads, thread_name_prefix=f"edgerecon-{site}")
    return found


def thread_map(fn: Callable[[T], R], items: Iterable[T], num_threads: int) -> list[R]:
    """``[fn(x) for x in items]``, on the calling thread's pool of ``num_threads`` threads
    when that is more than one (in order; the first error is raised)."""
    items = list(items)
    if num_threads <= 1 or len(items) <= 1:
        return [fn(x) for x in items]
    return list(pool("map", num_threads).map(fn, items))


__all__ = ["pool", "thread_map"]
