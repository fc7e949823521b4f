"""Worker threads that last (``edgerecon.threads``)."""

from __future__ import annotations

import gc
import threading
import time

from edgerecon.threads import pool, thread_map


def _ident(_: object) -> int:
    time.sleep(0.01)  # long enough for both of a pool's threads to take work
    return threading.get_ident()


def _in_thread(fn):
    box = {}
    th = threading.Thread(target=lambda: box.setdefault("v", fn()))
    th.start()
    th.join(30.0)
    return box["v"]


def test_a_callers_pool_is_made_once_and_kept():
    first = set(thread_map(_ident, range(6), 2))
    again = set(thread_map(_ident, range(6), 2))
    assert len(first) == 2 and again == first, "the same two threads, not new ones"
    assert threading.get_ident() not in first
    assert pool("map", 2) is pool("map", 2)
    assert pool("map", 3) is not pool("map", 2) and pool("other", 2) is not pool("map", 2)
    assert thread_map(lambda x: x * x, [3], 2) == [9]  # one item: on the caller's thread
    assert thread_map(_ident, range(3), 1) == [threading.get_ident()] * 3


def test_callers_do_not_share_workers_and_their_pools_end_with_them():
    mine = set(thread_map(_ident, range(4), 2))
    theirs = _in_thread(lambda: set(thread_map(_ident, range(4), 2)))
    assert not mine & theirs, "another caller's work never queues behind this one's"
    gc.collect()
    end = time.monotonic() + 10.0
    while time.monotonic() < end and any(t.ident in theirs for t in threading.enumerate()):
        time.sleep(0.05)
    assert not [t for t in threading.enumerate() if t.ident in theirs]
    assert all(any(t.ident == i for t in threading.enumerate()) for i in mine)


def test_nested_maps_get_pools_of_their_own():
    def outer(k: int) -> list[int]:
        return thread_map(lambda j: k * 10 + j, range(3), 2)

    assert thread_map(outer, range(4), 2) == [[k * 10 + j for j in range(3)] for k in range(4)]


def test_errors_are_raised_in_the_caller():
    def boom(x: int) -> int:
        if x == 2:
            raise ValueError("two")
        return x

    try:
        thread_map(boom, range(4), 2)
    except ValueError as exc:
        assert str(exc) == "two"
    else:
        raise AssertionError("not raised")
    assert thread_map(boom, [0, 1], 2) == [0, 1]  # the pool still works
