"""malloc's arenas limited for a long run (``runtime.memory``)."""

from __future__ import annotations

import os
import subprocess
import sys

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
