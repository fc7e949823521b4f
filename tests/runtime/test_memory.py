"""malloc tuned for a long run: few arenas, image-sized blocks mapped on their own, the
heap trimmed (``runtime.memory``)."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time

import pytest

from edgerecon.runtime import memory
from edgerecon.runtime.frontend import FrontEnd
from tests.runtime.conftest import run_frames, runtime_config

_ENV = ("MALLOC_ARENA_MAX", "MALLOC_MMAP_THRESHOLD_")


def test_malloc_is_tuned_here_and_for_the_processes_started_from_here(monkeypatch):
    for name in _ENV:
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setattr(memory, "_done", {})
    got = memory.tune_malloc()  # any command: the arenas only
    assert os.environ["MALLOC_ARENA_MAX"] == str(memory.ARENAS)
    assert "MALLOC_MMAP_THRESHOLD_" not in os.environ and got.mmap_threshold is None
    if sys.platform.startswith("linux") and got.arenas is None:
        pytest.skip("not glibc: mallopt unavailable")
    assert got.arenas == memory.ARENAS
    # A long run (this test process's own malloc left as it is: the mapping's effect is
    # the next test's, in a process of its own).
    calls: list[tuple[int, int]] = []
    monkeypatch.setattr(memory, "_mallopt", lambda: lambda p, v: calls.append((p, v)) or 1)
    got = memory.tune_malloc(mmap_threshold=memory.MMAP_THRESHOLD)
    assert calls == [(memory._M_MMAP_THRESHOLD, memory.MMAP_THRESHOLD)]
    assert got == memory.MallocTuning(arenas=memory.ARENAS, mmap_threshold=memory.MMAP_THRESHOLD)
    assert memory.tune_malloc().mmap_threshold == memory.MMAP_THRESHOLD  # kept from then on
    # A process started from here inherits it (the rebuild's, Ray's workers).
    code = "import os; print(os.environ.get('MALLOC_ARENA_MAX'), os.environ.get('MALLOC_MMAP_THRESHOLD_'))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == [str(memory.ARENAS), str(memory.MMAP_THRESHOLD)]


def test_long_runs_are_live_bounded_by_time_or_many_tasks():
    assert memory.long_run(live=True, duration_s=None, num_tasks=0)
    assert memory.long_run(live=False, duration_s=60.0, num_tasks=10)
    assert memory.long_run(live=False, duration_s=None, num_tasks=memory.LONG_RUN_TASKS + 1)
    assert not memory.long_run(live=False, duration_s=None, num_tasks=111)


_FREED_AND_AGAIN = """
import ctypes, sys
from edgerecon.runtime import memory
libc = ctypes.CDLL("libc.so.6")
class Info(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks",
                 "uordblks", "fordblks", "keepcost")]
libc.mallinfo2.restype = Info
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
if sys.argv[1] == "tuned":
    memory.tune_malloc(mmap_threshold=memory.MMAP_THRESHOLD)
libc.free(libc.malloc(2 << 20))  # an image-sized block, freed
before = libc.mallinfo2().hblkhd  # (the bytes mapped so far: the libraries' own blocks)
block = libc.malloc(2 << 20)  # and the next one
print(libc.mallinfo2().hblkhd - before >= 2 << 20)
"""


@pytest.mark.parametrize("how", ["tuned", "default"])
def test_an_image_sized_block_is_mapped_on_its_own_after_one_was_freed(how, monkeypatch):
    """glibc's default raises its mapping threshold to the size of a freed mapped block:
    the next image-sized blocks come from the heap, whose holes a long run keeps (its
    resident memory crept up 0.15 GB an hour); tuned for a long run, every such block is
    mapped and given back when freed."""
    if not sys.platform.startswith("linux") or memory._mallopt() is None:
        pytest.skip("glibc only")
    for name in _ENV:
        monkeypatch.delenv(name, raising=False)
    out = subprocess.run(
        [sys.executable, "-c", _FREED_AND_AGAIN, how], capture_output=True, text=True
    )
    if "mallinfo2" in out.stderr:
        pytest.skip("glibc older than 2.33 (no mallinfo2)")
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == ("True" if how == "tuned" else "False")


def test_the_users_value_wins_and_a_bad_one_is_said(monkeypatch, caplog):
    monkeypatch.setattr(memory, "_done", {})
    monkeypatch.setenv("MALLOC_ARENA_MAX", "4")
    monkeypatch.setenv("MALLOC_MMAP_THRESHOLD_", "4194304")
    got = memory.tune_malloc()
    assert got.arenas in (4, None) and got.mmap_threshold in (4 << 20, None)
    monkeypatch.setenv("MALLOC_ARENA_MAX", "many")
    assert memory.tune_malloc().arenas is None
    assert "not a number" in caplog.text
    monkeypatch.setattr(memory, "_done", {})
    monkeypatch.setenv("MALLOC_ARENA_MAX", str(memory.ARENAS))
    monkeypatch.setenv("MALLOC_MMAP_THRESHOLD_", str(memory.MMAP_THRESHOLD))
    memory.tune_malloc()


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


def test_the_peak_is_this_programs_high_water_mark():
    if not sys.platform.startswith("linux"):
        pytest.skip("Linux's /proc")
    code = (
        "import numpy as np\n"
        "from edgerecon.runtime.memory import peak_resident_mb, resident_mb\n"
        "before = peak_resident_mb()\n"
        "a = np.ones(40_000_000); del a\n"  # 320 MB touched, then given back
        "print(before, resident_mb(), peak_resident_mb())\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    before, now, peak = (float(x) for x in out.stdout.split())
    assert peak >= before + 250 and peak >= now + 250


def test_a_runs_threads_are_made_once_not_per_task(tiny, tmp_path, monkeypatch):
    # Native libraries keep a little data per thread that ever called them (OpenCV 5.1:
    # 0.2-0.7 KB each) after it ends: a thread per task and pools per stage call (about
    # ten threads a task) made a long run's memory grow with its tasks.
    ours = ("task", "edgerecon-", "scene-updates", "backend-rebuild")
    started: list[str] = []
    real_start = threading.Thread.start

    def start(self):
        if self.name.startswith(ours):
            started.append(self.name)
        return real_start(self)

    after_task: list[int] = []
    real_run_task = FrontEnd.run_task

    def run_task(self, *args, **kwargs):
        out = real_run_task(self, *args, **kwargs)
        after_task.append(len(started))
        return out

    monkeypatch.setattr(threading.Thread, "start", start)
    monkeypatch.setattr(FrontEnd, "run_task", run_task)
    config = runtime_config()
    assert config.background_updates and config.still is not None, "everything on"
    _, metrics = run_frames(tiny, tmp_path, 0, 8, config, fixed=(0.8, None))
    assert [m.status for m in metrics] == ["ok"] * 8
    assert len(after_task) == 8
    assert sum(name.startswith("task") for name in started) == 1
    # After the first two tasks, hardly any (a pool first used later); it was 10 a task.
    assert after_task[-1] - after_task[1] <= 4, started
