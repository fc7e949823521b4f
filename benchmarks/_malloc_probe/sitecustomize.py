"""Samples glibc's allocator in every Python process started with this folder on PYTHONPATH.

``bench_soak.py --malloc-stats`` puts it there for the run it starts. With
``EDGERECON_MALLOC_PROBE`` set to a path prefix, a daemon thread writes one JSON line every
``EDGERECON_MALLOC_PROBE_S`` seconds (default 60) to ``PREFIX.PID.jsonl``: the resident memory
(VmRSS) and its parts from ``/proc/self/smaps`` (the main arena ``[heap]``, anonymous
mappings, file mappings), and from ``malloc_info`` each arena's system bytes and free bytes
(fast bins and the other bins) and the blocks mapped on their own. Nothing is sampled without
the variable or where glibc is not the C library.
"""

from __future__ import annotations

import ctypes
import json
import os
import re
import sys
import tempfile
import threading
import time

_PREFIX = os.environ.get("EDGERECON_MALLOC_PROBE")


def _malloc_info() -> dict[str, object]:
    libc = ctypes.CDLL("libc.so.6")
    libc.fopen.restype = ctypes.c_void_p
    libc.fopen.argtypes = [ctypes.c_char_p, ctypes.c_char_p]
    libc.fclose.argtypes = [ctypes.c_void_p]
    libc.malloc_info.argtypes = [ctypes.c_int, ctypes.c_void_p]
    fd, path = tempfile.mkstemp(suffix=".xml")
    os.close(fd)
    try:
        fp = libc.fopen(path.encode(), b"w")
        if not fp:
            return {}
        libc.malloc_info(0, fp)
        libc.fclose(fp)
        with open(path, encoding="utf-8") as f:
            txt = f.read()
    finally:
        os.unlink(path)

    def total(body: str, kind: str) -> tuple[int, int]:
        m = re.search(rf'<total type="{kind}" count="(\d+)" size="(\d+)"', body)
        return (int(m.group(1)), int(m.group(2))) if m else (0, 0)

    def system(body: str) -> int:
        m = re.search(r'<system type="current" size="(\d+)"', body)
        return int(m.group(1)) if m else 0

    arenas = []
    for m in re.finditer(r'<heap nr="\d+">(.*?)</heap>', txt, re.S):
        body = m.group(1)
        arenas.append(
            {"system": system(body), "free": total(body, "fast")[1] + total(body, "rest")[1]}
        )
    tail = txt[txt.rfind("</heap>") :]
    n_mmap, mmap_bytes = total(tail, "mmap")
    return {"arenas": arenas, "mmap_n": n_mmap, "mmap": mmap_bytes}


def _smaps() -> dict[str, int]:
    parts = {"heap": 0, "anon": 0, "file": 0, "other": 0}
    name = ""
    with open("/proc/self/smaps", encoding="ascii", errors="replace") as f:
        for line in f:
            m = re.match(r"^[0-9a-f]+-[0-9a-f]+ \S+ \S+ \S+ \S+\s*(.*)$", line)
            if m:
                name = m.group(1).strip()
            elif line.startswith("Rss:"):
                kb = int(line.split()[1])
                if name == "[heap]":
                    parts["heap"] += kb
                elif name == "":
                    parts["anon"] += kb
                elif name.startswith("/"):
                    parts["file"] += kb
                else:
                    parts["other"] += kb
    return parts


def _loop(prefix: str, period: float) -> None:
    out = f"{prefix}.{os.getpid()}.jsonl"
    while True:
        time.sleep(period)
        try:
            with open("/proc/self/status", encoding="ascii") as f:
                rss = re.search(r"VmRSS:\s+(\d+)", f.read())
            row = {
                "t": round(time.time(), 1),
                "rss_kb": int(rss.group(1)) if rss else 0,
                "smaps_kb": _smaps(),
                **_malloc_info(),
                "py_blocks": sys.getallocatedblocks(),
                "threads": len(os.listdir("/proc/self/task")),
                "argv": sys.argv[:4],
            }
            with open(out, "a", encoding="utf-8") as f:
                f.write(json.dumps(row) + "\n")
        except Exception as exc:  # a probe never breaks the process it watches
            with open(f"{prefix}.{os.getpid()}.err", "a", encoding="utf-8") as f:
                f.write(repr(exc) + "\n")
            return


if _PREFIX and sys.platform.startswith("linux"):
    threading.Thread(
        target=_loop,
        args=(_PREFIX, float(os.environ.get("EDGERECON_MALLOC_PROBE_S", "60"))),
        daemon=True,
        name="malloc-probe",
    ).start()
