"""The viewer of a run in its own process (``edgerecon run --view``).

The front-end's critical path must not pay for the viewer: it runs as a child process
(``edgerecon view RUN_DIR --parent-pid PID``) at a lower CPU priority (``nice``), so it never
holds the front-end's interpreter lock and the OS scheduler gives the front-end's threads
precedence on a busy device; it only reads the files the session writes anyway. The child
exits when the run's process is gone.
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import threading
from pathlib import Path
from typing import IO

from edgerecon.types import EdgereconError

logger = logging.getLogger(__name__)

#: CPU priority decrease of the viewer process (Linux nice; the back-end's rebuilds use 10).
VIEWER_NICE = 10


class ViewerProcess:
    """A running ``edgerecon view`` child; ``url`` is where a browser opens it."""

    def __init__(self, proc: subprocess.Popen[str], url: str, port: int) -> None:
        self.proc = proc
        self.url = url
        self.port = port

    @property
    def pid(self) -> int:
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self, timeout: float = 5.0) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()

    def wait(self) -> None:
        self.proc.wait()

    def __enter__(self) -> ViewerProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def start_viewer_process(
    run_dir: str | os.PathLike[str],
    *,
    host: str = "127.0.0.1",
    port: int = 8080,
    points: int = 150_000,
    nice: int = VIEWER_NICE,
    startup_timeout_s: float = 60.0,
) -> ViewerProcess:
    """Start ``edgerecon view`` on ``run_dir`` in a child process at lower priority and
    wait until it serves (raises ``EdgereconError`` when it cannot start)."""
    from edgerecon.viewer.server import require_viser

    require_viser()
    cmd = [
        sys.executable,
        "-m",
        "edgerecon",
        "view",
        str(Path(run_dir)),
        "--host",
        host,
        "--port",
        str(port),
        "--points",
        str(points),
        "--nice",
        str(nice),
        "--parent-pid",
        str(os.getpid()),
        "--json",
    ]
    proc = subprocess.Popen(
        cmd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        stdin=subprocess.DEVNULL,
        text=True,
        start_new_session=True,  # Ctrl-C in the terminal reaches the run, which stops us
    )
    line = _read_line(proc.stdout, startup_timeout_s)
    if not line:
        proc.kill()
        _, err = proc.communicate(timeout=5)
        raise EdgereconError(f"the viewer did not start: {err.strip()[-500:] or 'no output'}")
    info = json.loads(line)
    # Keep draining stderr so the child never blocks on a full pipe (its warnings go to ours).
    threading.Thread(target=_forward, args=(proc.stderr,), daemon=True).start()
    return ViewerProcess(proc, str(info["url"]), int(info["port"]))


def _read_line(stream: IO[str] | None, timeout_s: float) -> str:
    if stream is None:
        return ""
    out: list[str] = []
    reader = threading.Thread(target=lambda: out.append(stream.readline()), daemon=True)
    reader.start()
    reader.join(timeout_s)
    return out[0].strip() if out else ""


def _forward(stream: IO[str] | None) -> None:
    if stream is None:
        return
    for line in stream:
        sys.stderr.write(line)
