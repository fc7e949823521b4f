"""malloc's arenas limited for a long run (``runtime.memory``)."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time

import pytest

from edgerecon.runtime import memory


def test_the_arena_limit_is_set_here_and_for_the_processes_started_from_here(monkeypatch):
    monkeypatch.delenv("MALLOC_ARENA_MAX", raising=False)
    monkeypatch.setattr(memory, "_done", None)
    got = memory.limit_malloc_arenas()
    assert os.environ["MALLOC_ARENA_MAX"] == str(memory.ARENAS)
    if sys.platform.startswith("linux") and got is None:
        pytest.skip("not glibc: mallopt unavailable")
    assert got == memory.ARENAS
    # A process started from here inherits it (the rebuild's, Ray's workers).
    out = subprocess.run(
        [sys.executable, "-c", "import os; print(os.environ.get('MALLOC_ARENA_MAX'))"],
        capture_output=True,
        text=True,
        check=True,
    )
    assert out.stdout.strip() == str(memory.ARENAS)


def test_the_users_value_wins_and_a_bad_one_is_said(monkeypatch, caplog):
    monkeypatch.setattr(memory, "_done", None)
    monkeypatch.setenv("MALLOC_ARENA_MAX", "4")
    got = memory.limit_malloc_arenas()
    assert got in (4, None)
    monkeypatch.setenv("MALLOC_ARENA_MAX", "many")
    assert memory.limit_malloc_arenas() is None
    assert "not a number" in caplog.text
    monkeypatch.setattr(memory, "_done", None)
    monkeypatch.setenv("MALLOC_ARENA_MAX", str(memory.ARENAS))
    memory.limit_malloc_arenas()


def test_the_heap_trimmer_runs_once_per_process_until_stopped(monkeypatch):
    from tests.runtime.conftest import wait_until

    calls: list[int] = []
    monkeypatch.setattr(memory, "_malloc_trim", lambda: lambda pad: calls.append(pad) or 1)
    memory.stop_heap_trimmer()
    try:
        assert memory.start_heap_trimmer(0.02)
        assert memory.start_heap_trimmer(0.02)  # already running: not a second thread
        assert [t.name for t in threading.enumerate()].count("heap-trim") == 1
        assert wait_until(lambda: len(calls) >= 3, 5.0)
        assert set(calls) == {0}
    finally:
        memory.stop_heap_trimmer()
    n = len(calls)
    time.sleep(0.1)
    assert len(calls) == n  # stopped
    monkeypatch.setattr(memory, "_malloc_trim", lambda: None)
    assert not memory.start_heap_trimmer()  # not glibc: nothing runs


def test_malloc_trim_is_found_on_glibc():
    if not sys.platform.startswith("linux"):
        pytest.skip("glibc only")
    trim = memory._malloc_trim()
    if trim is None:
        pytest.skip("not glibc")
    assert trim(0) in (0, 1)
