"""A long live run: does memory or disk grow with the number of tasks?

    python benchmarks/bench_soak.py --dataset ../shared/data/caliscope_charuco --duration 900
    python benchmarks/bench_soak.py --duration 600 --keep-clouds 50 --json soak.json

A recorded dataset's cameras are served in a loop as live MJPEG streams on 127.0.0.1 at the
dataset's frame rate (``edgerecon.io.mjpeg.serve_dataset``; ``--fps`` overrides it), and
``edgerecon run`` reads them for ``--duration`` seconds in a process of its own (optimizer on,
embedded engine, background rebuilds on, ``--keep-clouds``). Every ``--sample`` seconds:
the tasks recorded so far, the resident memory of the run's main process (front-end and
back-end roles) and of its children (the background rebuild's process), and the bytes under
its output folder. Printed: the samples, then the growth of each per hour and per 1000
tasks (least squares over the samples after the first quarter, when the models, the
kernels and the first backgrounds are in place), and the run's summary. The server encodes
JPEG in this process: it shares the machine's cores with the run (say the load).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from _report import print_rows, report_header, write_report
from edgerecon.io.dataset import open_dataset
from edgerecon.io.mjpeg import serve_dataset


def _children(pid: int) -> list[int]:
    """Every descendant of ``pid`` (from /proc)."""
    parents: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat", encoding="ascii", errors="replace") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        parents.setdefault(int(fields[1]), []).append(int(entry))
    out: list[int] = []
    todo = list(parents.get(pid, []))
    while todo:
        p = todo.pop()
        out.append(p)
        todo.extend(parents.get(p, []))
    return out


def _rss_mb(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


def _folder_mb(path: Path) -> float:
    total = 0
    for root, _, files in os.walk(path):
        for name in files:
            try:
                total += os.stat(os.path.join(root, name)).st_size
            except OSError:
                pass
    return total / 2**20


def _lines(path: Path) -> int:
    try:
        with open(path, "rb") as f:
            return sum(1 for _ in f)
    except OSError:
        return 0


def _slope(x: list[float], y: list[float]) -> float:
    """Least-squares slope of y over x (nan with fewer than 3 samples)."""
    if len(x) < 3 or np.ptp(x) == 0:
        return float("nan")
    return float(np.polyfit(np.asarray(x), np.asarray(y), 1)[0])


#: The allocator's parts in ``_malloc_report`` (MB): name, value of one probe row.
_PARTS: tuple[tuple[str, Any], ...] = (
    ("rss", lambda r: r["rss_kb"] / 1024),
    ("heap_rss", lambda r: r["smaps_kb"]["heap"] / 1024),
    ("anon_rss", lambda r: r["smaps_kb"]["anon"] / 1024),
    ("file_rss", lambda r: r["smaps_kb"]["file"] / 1024),
    ("arenas_system", lambda r: sum(a["system"] for a in r["arenas"]) / 2**20),
    ("arenas_in_use", lambda r: sum(a["system"] - a["free"] for a in r["arenas"]) / 2**20),
    ("arenas_free", lambda r: sum(a["free"] for a in r["arenas"]) / 2**20),
    ("mmapped_blocks", lambda r: r["mmap"] / 2**20),
    # Anonymous memory that is neither an arena after the main one (glibc maps those) nor a
    # block mapped on its own: Python's object arenas, thread stacks, libraries' own maps.
    (
        "anon_not_malloc",
        lambda r: (
            r["smaps_kb"]["anon"] / 1024
            - sum(a["system"] for a in r["arenas"][1:]) / 2**20
            - r["mmap"] / 2**20
        ),
    ),
)


def _malloc_report(
    work: Path, pid: int, started: float, samples: list[dict[str, Any]], duration: float
) -> dict[str, Any]:
    """The probe's rows of the run's main process: medians per five minutes and the growth
    of each part per 1000 tasks after the first quarter (tasks interpolated from the
    samples by time)."""
    files = sorted(work.glob("malloc.*.jsonl"))
    chosen = work / f"malloc.{pid}.jsonl"
    if not chosen.exists():  # under --wrap: the process with the most rows that runs `run`
        runs = [f for f in files if '"run"' in f.read_text(encoding="utf-8")]
        if not runs:
            print("malloc stats: no probe rows (is glibc the C library?)")
            return {}
        chosen = max(runs, key=lambda f: len(f.read_text(encoding="utf-8").splitlines()))
    rows = [json.loads(line) for line in chosen.read_text(encoding="utf-8").splitlines()]
    if not rows or not samples:
        return {}
    at = np.array([r["t"] - started for r in rows])
    tasks = np.interp(at, [s["at_s"] for s in samples], [float(s["tasks"]) for s in samples])
    values = {name: np.array([f(r) for r in rows]) for name, f in _PARTS}
    table = []
    for lo in range(0, int(at.max()) + 1, 300):
        sel = (at >= lo) & (at < lo + 300)
        if sel.any():
            table.append(
                {"minutes": f"{lo // 60}-{lo // 60 + 5}"}
                | {name: round(float(np.median(v[sel])), 1) for name, v in values.items()}
            )
    print_rows(
        f"the run's allocator ({chosen.name}), medians of five minutes, MB", list(table[0]), table
    )
    settled = at >= 0.25 * duration
    growth = [
        {
            "part": name,
            "per_1000_tasks": round(1000 * _slope(list(tasks[settled]), list(v[settled])), 1),
        }
        for name, v in values.items()
    ]
    print_rows("growth after the first quarter", ["part", "per_1000_tasks"], growth)
    return {"file": str(chosen), "table": table, "growth": growth}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", default="../shared/data/caliscope_charuco")
    ap.add_argument("--cameras", type=int, nargs="+", default=None, help="served cameras")
    ap.add_argument("--fps", type=float, default=None, help="stream rate (default: dataset's)")
    ap.add_argument("--deadline", type=float, default=0.6, help="deadline per task (s)")
    ap.add_argument("--duration", type=float, default=900.0, help="seconds of live run")
    ap.add_argument("--keep-clouds", type=int, default=50)
    ap.add_argument("--sample", type=float, default=15.0, help="seconds between samples")
    ap.add_argument("--work", default="/tmp/edgerecon-soak", help="stream dataset and run")
    ap.add_argument(
        "--wrap",
        default="",
        help="a command the run is started under, e.g. 'heaptrack -o /tmp/soak' "
        "(benchmarks/heap_growth.py reads its recording); main_mb is then the wrapper's, "
        "children_mb includes the run",
    )
    ap.add_argument(
        "--malloc-stats",
        action="store_true",
        help="sample glibc's allocator inside the run's process every --sample seconds "
        "(benchmarks/_malloc_probe): its arenas' system and free bytes, the blocks mapped on "
        "their own and the resident memory's parts, printed per five minutes with their growth",
    )
    ap.add_argument("--json", default=None)
    args = ap.parse_args()

    work = Path(args.work)
    live = work / "live"
    out = work / "run"
    fps = args.fps or open_dataset(args.dataset).fps or 10.0
    server = serve_dataset(
        args.dataset,
        live,
        cameras=args.cameras,
        fps=fps,
        stream_options={"stall_s": 2.0, "max_wait_s": 2.0},
    )
    cmd = [
        *shlex.split(args.wrap),
        sys.executable,
        "-m",
        "edgerecon",
        "-q",
        "run",
        "--dataset",
        str(live),
        "--out",
        str(out),
        "--overwrite",
        "--deadline",
        f"{args.deadline:g}",
        "--duration",
        f"{args.duration:g}",
        "--keep-clouds",
        str(args.keep_clouds),
        "--json",
    ]
    samples: list[dict[str, Any]] = []
    wall0 = time.monotonic()
    started = time.time()
    try:
        # The run's JSON (every task's record) to a file: a pipe not read until the end
        # would fill and block the run's last write.
        report = open(work / "run.json", "w+", encoding="utf-8")
        env = None
        if args.malloc_stats:
            probe = str(Path(__file__).resolve().parent / "_malloc_probe")
            path = os.environ.get("PYTHONPATH")
            env = {
                **os.environ,
                "PYTHONPATH": probe + (os.pathsep + path if path else ""),
                "EDGERECON_MALLOC_PROBE": str(work / "malloc"),
                "EDGERECON_MALLOC_PROBE_S": f"{args.sample:g}",
            }
            for old in work.glob("malloc.*"):
                old.unlink()
        proc = subprocess.Popen(cmd, stdout=report, text=True, env=env)
        while proc.poll() is None:
            time.sleep(args.sample)
            if proc.poll() is not None:
                break
            kids = _children(proc.pid)
            sample = {
                "at_s": round(time.monotonic() - wall0, 1),
                "tasks": _lines(out / "metrics.jsonl"),
                "main_mb": round(_rss_mb(proc.pid), 1),
                "children_mb": round(sum(_rss_mb(k) for k in kids), 1),
                "children": len(kids),
                "out_mb": round(_folder_mb(out), 1),
                "load": round(os.getloadavg()[0], 2),
            }
            samples.append(sample)
            print(json.dumps(sample), flush=True)
        proc.wait()
        report.seek(0)
        stdout = report.read()
        report.close()
    finally:
        server.stop()
    result: dict[str, Any] = {"exit": proc.returncode}
    try:
        data = json.loads(stdout)
        summary = data["summary"]
    except (ValueError, KeyError):
        summary = {}
    print_rows("samples", list(samples[0]) if samples else ["at_s"], samples)
    settled = [s for s in samples if s["at_s"] >= 0.25 * args.duration]
    if settled:
        at = [s["at_s"] / 3600.0 for s in settled]
        tasks = [float(s["tasks"]) for s in settled]
        growth = {}
        for key in ("main_mb", "out_mb"):
            values = [float(s[key]) for s in settled]
            growth[key] = {
                "first": values[0],
                "last": values[-1],
                "max": max(values),
                "per_hour": round(_slope(at, values), 1),
                "per_1000_tasks": round(1000 * _slope(tasks, values), 1),
            }
        result["growth"] = growth
        rows = [{"what": k, **v} for k, v in growth.items()]
        print_rows("growth after the first quarter", list(rows[0]), rows)
    keys = (
        "tasks",
        "failed",
        "degraded",
        "avg_time_s",
        "avg_time_converged_s",
        "clouds_written",
        "clouds_kept",
        "clouds_skipped",
        "wall_s",
    )
    result["summary"] = {k: summary.get(k) for k in keys}
    if args.malloc_stats:
        result["malloc"] = _malloc_report(work, proc.pid, started, samples, args.duration)
    result["stream"] = summary.get("stream", {})
    print_rows("run", list(keys), [result["summary"]])
    if args.json:
        write_report(
            args.json, {**report_header(), "args": vars(args), **result, "samples": samples}
        )


if __name__ == "__main__":
    main()
