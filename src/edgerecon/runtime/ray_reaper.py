"""Fate-sharing for a private Ray instance: when the process that started it dies (kill -9
included), its Ray processes go too.

Ray's agents (``ray::DashboardAgent``, ``ray::RuntimeEnvAgent``) notice that their raylet died,
then try to report it to the GCS, which died with it, and wait out a hard-coded 60 s timeout:
after a kill -9 of the driver they lingered ~80 s. The reaper is a small process the Ray
engine starts next to a private instance: it keeps the list of the driver's descendants
(every 0.5 s) and, once the driver is gone, kills those still alive (the same processes:
their start times are checked, so a recycled pid is never hit). Linux only (/proc); elsewhere
it is not started.

    python .../edgerecon/runtime/ray_reaper.py DRIVER_PID

(run as a file, so that it imports nothing but the standard library and starts in ~50 ms).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

_PROC = Path("/proc")


def _stat(pid: int) -> tuple[int, int] | None:
    """(parent pid, start time) of ``pid``, or None when it is gone."""
    try:
        text = (_PROC / str(pid) / "stat").read_text()
    except OSError:
        return None
    fields = text[text.rindex(")") + 2 :].split()
    return int(fields[1]), int(fields[19])


def descendants(root: int) -> dict[int, int]:
    """pid -> start time of every living descendant of ``root``."""
    children: dict[int, list[int]] = {}
    starts: dict[int, int] = {}
    for entry in _PROC.iterdir():
        if entry.name.isdigit():
            st = _stat(int(entry.name))
            if st is not None:
                children.setdefault(st[0], []).append(int(entry.name))
                starts[int(entry.name)] = st[1]
    found: dict[int, int] = {}
    todo = list(children.get(root, []))
    while todo:
        pid = todo.pop()
        if pid not in found and pid in starts:
            found[pid] = starts[pid]
            todo.extend(children.get(pid, []))
    return found


def reap(driver: int, interval_s: float = 0.5) -> int:
    """Watch ``driver``; once it is gone, kill its recorded descendants. Returns how many."""
    me = os.getpid()
    known: dict[int, int] = {}
    ready = False
    while _stat(driver) is not None and os.getppid() == driver:
        known.update(descendants(driver))
        known = {p: s for p, s in known.items() if p != me and (_stat(p) or (0, -1))[1] == s}
        if not ready:  # the first scan is done: the driver may go on
            print("ready", flush=True)
            ready = True
        time.sleep(interval_s)
    killed = 0
    for pid, start in known.items():
        st = _stat(pid)
        if st is not None and st[1] == start:
            try:
                os.kill(pid, signal.SIGKILL)
                killed += 1
            except OSError:
                pass
    return killed


def start_reaper() -> subprocess.Popen[bytes] | None:
    """Start the reaper for this process (None where /proc is missing)."""
    if not (_PROC / "self" / "stat").exists():
        return None
    proc = subprocess.Popen(
        [sys.executable, "-S", str(Path(__file__).resolve()), str(os.getpid())],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        start_new_session=True,  # a Ctrl-C meant for the driver does not stop it
    )
    assert proc.stdout is not None
    proc.stdout.readline()  # "ready": it has seen the processes to reap
    return proc


if __name__ == "__main__":
    reap(int(sys.argv[1]))
