"""The reaper of a private Ray instance: after a kill -9 of the driver its descendants go
(Ray's agents lingered ~80 s)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from edgerecon.runtime.ray_reaper import _stat, descendants

pytestmark = pytest.mark.skipif(not os.path.exists("/proc/self/stat"), reason="Linux /proc")

# A driver with a grandchild that ignores its parents' deaths (as Ray's agents do for a
# minute), and the reaper.
DRIVER = """
import subprocess, sys, time
from edgerecon.runtime.ray_reaper import start_reaper
child = subprocess.Popen([sys.executable, "-c",
    "import subprocess, sys, time; "
    "g = subprocess.Popen(['sleep', '300'], start_new_session=True); "
    "print(g.pid, flush=True); time.sleep(300)"], stdout=subprocess.PIPE, text=True)
grandchild = int(child.stdout.readline())
reaper = start_reaper()
time.sleep(1.0)  # the reaper rescans: processes started after it are seen too
print(child.pid, grandchild, reaper.pid, flush=True)
time.sleep(300)
"""


def test_a_killed_drivers_descendants_are_reaped():
    driver = subprocess.Popen([sys.executable, "-c", DRIVER], stdout=subprocess.PIPE, text=True)
    try:
        child, grandchild, reaper = (int(x) for x in driver.stdout.readline().split())
        assert {child, grandchild} <= set(descendants(driver.pid))
        os.kill(driver.pid, signal.SIGKILL)
        driver.wait()
        end = time.monotonic() + 10
        while time.monotonic() < end and any(_alive(p) for p in (child, grandchild, reaper)):
            time.sleep(0.1)
        assert not _alive(child) and not _alive(grandchild), "descendants reaped"
        assert not _alive(reaper), "the reaper exits after its work"
    finally:
        if driver.poll() is None:
            driver.kill()


def _alive(pid):
    st = _stat(pid)
    if st is None:
        return False
    state = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[0]
    return state != "Z"
