"""``edgerecon run`` on a terminal: captured under a pseudo-terminal and replayed on a
terminal emulator (pyte), the task rows, the log lines and the status line never interleave."""

from __future__ import annotations

import os
import pty
import re
import select
import subprocess
import sys
import time

import pytest

pyte = pytest.importorskip("pyte")

ROW = re.compile(r"^\s+\d+\s+\d+\s+[a-z]+\s+\d\.\d\d\s+\d\s+\d+\.\d\d\s+(yes|NO)\s")


def _run_in_pty(args, cols=110, rows=40, timeout=300.0):
    master, slave = pty.openpty()
    os.set_blocking(master, False)
    import fcntl
    import struct
    import termios

    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", rows, cols, 0, 0))
    env = {**os.environ, "COLUMNS": str(cols), "LINES": str(rows), "TERM": "xterm-256color"}
    env.pop("NO_COLOR", None)
    proc = subprocess.Popen(
        [sys.executable, "-m", "edgerecon", *args],
        stdin=slave,
        stdout=slave,
        stderr=slave,
        env=env,
        close_fds=True,
    )
    os.close(slave)
    out = bytearray()
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        ready, _, _ = select.select([master], [], [], 0.2)
        if ready:
            try:
                chunk = os.read(master, 65536)
            except OSError:
                break
            if not chunk:
                break
            out += chunk
        elif proc.poll() is not None:
            break
    proc.wait(timeout=10)
    os.close(master)
    return proc.returncode, bytes(out)


def test_run_output_on_a_terminal_never_interleaves(tiny_dataset, tmp_path):
    code, raw = _run_in_pty(
        [
            "run",
            "--dataset",
            str(tiny_dataset),
            "--deadline",
            "1.5",
            "--frames",
            "0:6",
            "--out",
            str(tmp_path / "run"),
            "--inject-fault",
            "2:stall:3",  # the back-end stalls: warnings are logged during the run
        ]
    )
    assert code == 0, raw[-2000:].decode(errors="replace")
    screen = pyte.HistoryScreen(110, 40, history=2000)
    pyte.ByteStream(screen).feed(raw.replace(b"\n", b"\r\n"))
    history = ["".join(ch.data for ch in line.values()) for line in screen.history.top]
    lines = [ln.rstrip() for ln in [*history, *screen.display]]
    rows = [ln for ln in lines if ROW.match(ln)]
    assert len(rows) == 6, "\n".join(lines)
    assert [int(r.split()[0]) for r in rows] == list(range(6))
    header = [ln for ln in lines if ln.strip().startswith("task   time   phase")]
    assert len(header) == 1
    # The status line (task i/N, ETA) was shown while running and is gone at the end; it
    # never shares a line with a row or a log record.
    assert b"task 1/6" in raw and re.search(rb"ETA \d+:\d\d", raw)
    assert not any("elapsed" in ln for ln in lines)
    logs = [ln for ln in lines if re.match(r"^\d\d:\d\d:\d\d (WARNING|ERROR) ", ln)]
    assert logs, "\n".join(lines)  # the drill's warnings are on lines of their own
    for ln in rows + logs:
        assert "elapsed" not in ln and "━" not in ln
    # A task of the run exports as it is (dataset and time from the run folder).
    from edgerecon.cli import main
    from edgerecon.io.colmap import read_colmap_model

    task = tmp_path / "run" / "tasks" / "000003"
    assert main(["export", str(task), "--out", str(tmp_path / "ws"), "--no-images"]) == 0
    assert len(read_colmap_model(tmp_path / "ws" / "sparse").points3D) > 100
    assert (tmp_path / "run" / "config.toml").read_text().count("[runtime") >= 1
