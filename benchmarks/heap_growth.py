"""Which call stacks hold more heap as a run goes on: a heaptrack recording read at
checkpoints.

    python benchmarks/bench_soak.py --duration 660 --wrap "heaptrack -o /tmp/soak"
    python benchmarks/heap_growth.py /tmp/soak.zst --every 50 --start 150

heaptrack (1.4: ``apt install heaptrack``) records every allocation and free with its call
stack. This reads the recording once (``zstd -dc`` / ``gzip -dc``), keeps the number of
blocks each allocation record holds, and every ``--every`` seconds from ``--start`` on sums
the bytes held per call stack. A stack whose bytes grew at every checkpoint (by more than
``--min-kb`` in all) is one that keeps what it allocates as tasks go by; one that swings is
the task in flight. Printed: the heap held at each checkpoint, and the growing stacks with
their innermost named frames (the interpreter's own frames left out). heaptrack's
``heaptrack_print --print-leaks`` gives what was never freed at the exit instead.

Reads heaptrack's interpreted format (lines ``s`` string, ``i`` instruction pointer, ``t``
trace, ``a`` allocation record, ``+`` / ``-`` an allocation / free of a record, ``c``
milliseconds since the start).
"""

from __future__ import annotations

import argparse
import itertools
import json
import subprocess
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any

from _report import print_rows, write_report

#: Frames of the interpreter and of the allocator that say nothing about the caller.
_NOISE = (
    "_PyEval",
    "_PyObject_Vectorcall",
    "_PyFunction_Vectorcall",
    "_PyObject_Call",
    "PyObject_Call",
    "method_vectorcall",
    "cfunction_",
    "slot_tp_call",
    "_PyObject_MakeTpCall",
    "_PyObject_FastCall",
    "do_call_core",
    "thread_run",
    "pythread_wrapper",
    "start_thread",
    "clone3",
    "malloc",
    "operator new",
    "default_malloc",
    "PyDataMem_UserNEW",
)


def _decompress(path: Path) -> subprocess.Popen[bytes]:
    tool = "gzip" if path.suffix == ".gz" else "zstd"
    return subprocess.Popen([tool, "-dc", str(path)], stdout=subprocess.PIPE)


def read_checkpoints(
    path: Path, every_s: float, start_s: float, end_s: float = float("inf")
) -> tuple[list[float], dict[int, list[int]], dict[str, Any]]:
    """The checkpoints' times (s), bytes held per trace at each, and what resolves traces."""
    records: list[tuple[int, int]] = []  # allocation record -> (size, trace)
    held: Counter[bytes] = Counter()  # "+ idx" / "- idx" lines so far
    pending: list[bytes] = []
    strings: list[str] = [""]
    ips: list[list[str]] = [[]]
    traces: list[tuple[int, int]] = [(0, 0)]
    times: list[float] = []
    per_trace: dict[int, list[int]] = defaultdict(list)
    next_ms = start_s * 1000.0

    def checkpoint(t_ms: float) -> None:
        held.update(pending)
        pending.clear()
        net: Counter[int] = Counter()
        for key, n in held.items():
            idx = int(key[2:], 16)
            net[idx] += n if key[:1] == b"+" else -n
        now: Counter[int] = Counter()
        for idx, n in net.items():
            if n:
                size, trace = records[idx]
                now[trace] += size * n
        k = len(times)
        for trace, b in now.items():
            series = per_trace[trace]
            series.extend([0] * (k - len(series)))
            series.append(b)
        times.append(t_ms / 1000.0)

    proc = _decompress(path)
    assert proc.stdout is not None
    for raw in proc.stdout:
        line = raw.rstrip(b"\n")
        head = line[:1]
        if head in (b"+", b"-"):
            pending.append(line)
        elif head == b"a":
            _, size, trace = line.split()
            records.append((int(size, 16), int(trace, 16)))
        elif head == b"c":
            t_ms = int(line.split()[1], 16)
            if next_ms <= t_ms <= end_s * 1000.0 + every_s * 500.0:
                checkpoint(t_ms)
                next_ms += every_s * 1000.0
        elif head == b"s":
            strings.append(line[2:].split(b" ", 1)[-1].decode("utf-8", "replace"))  # s LEN TEXT
        elif head == b"i":
            ips.append(line.decode().split()[1:])
        elif head == b"t":
            _, ip, parent = line.split()
            traces.append((int(ip, 16), int(parent, 16)))
    proc.wait()
    for series in per_trace.values():
        series.extend([0] * (len(times) - len(series)))
    return times, dict(per_trace), {"strings": strings, "ips": ips, "traces": traces}


def frames_of(trace: int, table: dict[str, Any], limit: int = 4) -> list[str]:
    """The innermost ``limit`` named frames of ``trace`` (module names where unnamed)."""
    strings, ips, traces = table["strings"], table["ips"], table["traces"]
    out: list[str] = []
    while trace and len(out) < limit:
        ip, trace = traces[trace]
        fields = ips[ip]
        module = strings[int(fields[1], 16)].rsplit("/", 1)[-1] if len(fields) > 1 else "?"
        names = [strings[int(f, 16)] for f in fields[2::3]] or [f"?? {module}"]
        for name in names:
            if not name.startswith(_NOISE) and (not out or out[-1] != name):
                out.append(name[:80])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("recording", type=Path, help="heaptrack's .zst (or .gz) file")
    ap.add_argument("--every", type=float, default=50.0, help="seconds between checkpoints")
    ap.add_argument("--start", type=float, default=150.0, help="first checkpoint (s)")
    ap.add_argument("--end", type=float, default=float("inf"), help="last checkpoint (s)")
    ap.add_argument("--min-kb", type=float, default=16.0, help="least growth listed")
    ap.add_argument("--top", type=int, default=20)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    times, per_trace, table = read_checkpoints(args.recording, args.every, args.start, args.end)
    if len(times) < 2:
        raise SystemExit("fewer than two checkpoints: a longer recording or a smaller --every")
    totals = [sum(s[k] for s in per_trace.values()) for k in range(len(times))]
    print_rows(
        "heap held at each checkpoint",
        ["at_s", "held_mb"],
        [{"at_s": t, "held_mb": b / 2**20} for t, b in zip(times, totals, strict=True)],
    )
    growing = []
    for trace, series in per_trace.items():
        rise = series[-1] - series[0]
        steady = all(b >= a for a, b in itertools.pairwise(series))
        if steady and series[0] > 0 and rise > args.min_kb * 1024:
            growing.append((rise, trace, series))
    growing.sort(reverse=True)
    rows = [
        {
            "grew_kb": rise / 1024,
            "first_kb": series[0] / 1024,
            "last_kb": series[-1] / 1024,
            "frames": " <- ".join(frames_of(trace, table)),
        }
        for rise, trace, series in growing[: args.top]
    ]
    total = sum(r[0] for r in growing) / 2**20
    print_rows(
        f"stacks holding more at every checkpoint ({len(growing)}, {total:.2f} MB "
        f"from {times[0]:.0f} to {times[-1]:.0f} s)",
        ["grew_kb", "first_kb", "last_kb", "frames"],
        rows,
    )
    if args.json:
        write_report(
            args.json,
            {"times_s": times, "held_bytes": totals, "growing_mb": total, "growing": rows},
        )
    else:
        print(json.dumps({"growing_mb": round(total, 3), "stacks": len(growing)}))


if __name__ == "__main__":
    main()
