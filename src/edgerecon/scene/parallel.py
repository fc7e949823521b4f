"""Per-camera work of the scene stage on a few threads (OpenCV's and NumPy's array
operations release the interpreter lock, so plain threads run in parallel)."""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

_T = TypeVar("_T")
_R = TypeVar("_R")

_POOLS: dict[int, ThreadPoolExecutor] = {}
_POOLS_LOCK = threading.Lock()
# A forked child has none of the parent's threads: it starts its own pools.
os.register_at_fork(after_in_child=_POOLS.clear)


def per_camera(fn: Callable[[_T], _R], items: Sequence[_T], num_threads: int) -> list[_R]:
    """``[fn(x) for x in items]`` on up to ``num_threads`` threads (a pool shared by every
    caller, so ``fn`` must not call this again), in order; the first error is raised."""
    if num_threads <= 1 or len(items) <= 1:
        return [fn(x) for x in items]
    with _POOLS_LOCK:
        pool = _POOLS.get(num_threads)
        if pool is None:
            pool = ThreadPoolExecutor(num_threads, thread_name_prefix="edgerecon-scene")
            _POOLS[num_threads] = pool
    return list(pool.map(fn, items))
