"""The live viewer's cost on the critical path: the same tasks with and without it.

    python benchmarks/bench_viewer.py                          # demo scene, 40 tasks x 2 runs
    python benchmarks/bench_viewer.py --tasks 40 --block 2 --json viewer.json

The project's machines are shared: the load changes the critical path by tens of per cent
from one minute to the next, far more than the few per cent to measure, so separate runs
with and without the viewer cannot be compared. Here the viewer runs alongside the online
system exactly as ``run --view`` starts it (``edgerecon view`` in a child process at nice 10,
following the run folder) with a client connected that receives and decodes every message
(``python -m edgerecon.viewer.wire``, standing in for a browser on another device, at nice
19), and it is switched on and off in blocks of ``--block`` tasks (SIGCONT / SIGSTOP after
each task: the viewer's work for task t falls during task t + 1). Two runs over the same
timestamps swap the blocks, so every timestamp is measured once with and once without the
viewer, a few minutes apart. One fixed configuration (``--scale``, all cameras), no
background rebuilds (``--background`` turns them on) and golden references waited for, so the
work of a task does not depend on the load.

Printed: mean critical path of the tasks with and without the viewer and their ratio, the
median of the per-timestamp ratios, and the viewer's CPU seconds per task (from the run's
start: its imports come before).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from _report import print_rows, report_header, write_report
from edgerecon.io.dataset import open_dataset
from edgerecon.runtime import FrameRange, RuntimeConfig, SessionOptions, run_online
from edgerecon.runtime.engine import learn_scene_model
from edgerecon.viewer.process import start_viewer_process


def cpu_seconds(pid: int) -> float:
    """utime + stime of a live process (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def on_block(task: int, block: int, parity: int) -> bool:
    """Whether the viewer runs during task ``task``."""
    return (task // block + parity) % 2 == 0


def one_run(
    root: Path, scene: Any, out: Path, args: argparse.Namespace, parity: int
) -> list[dict[str, Any]]:
    ds = open_dataset(root)
    # A late golden reference makes a task degraded: wait for it, so that the work of a task
    # does not depend on the load.
    config = RuntimeConfig(
        deadline_s=args.deadline,
        golden_timeout_s=60.0,
        background_updates=args.background,
    )
    options = SessionOptions(frames=FrameRange(start=0, stop=args.tasks), overwrite=True)
    viewer = start_viewer_process(out, port=0)
    client = subprocess.Popen(
        ["nice", "-n", "19", sys.executable, "-m", "edgerecon.viewer.wire", str(viewer.port)],
        stdout=subprocess.PIPE,
        text=True,
    )
    time.sleep(2.0)  # the client connects
    cpu = {"last": cpu_seconds(viewer.pid), "on": 0.0, "off": 0.0}
    state = {"running": True}

    def switch(run: bool) -> None:
        if run != state["running"]:
            os.kill(viewer.pid, signal.SIGCONT if run else signal.SIGSTOP)
            state["running"] = run

    def on_task(m: Any) -> None:
        now = cpu_seconds(viewer.pid)
        cpu["on" if on_block(m.task, args.block, parity) else "off"] += now - cpu["last"]
        cpu["last"] = now
        switch(on_block(m.task + 1, args.block, parity))

    switch(on_block(0, args.block, parity))
    try:
        _, metrics = run_online(
            ds, config, options, out, fixed=(args.scale, None), scene=scene, on_task=on_task
        )
    finally:
        switch(True)
        viewer.stop()
        client.terminate()
        received = json.loads(client.communicate(timeout=30)[0].strip() or "{}")
    n_on = sum(on_block(m.task, args.block, parity) for m in metrics)
    print(
        f"run {parity}: viewer CPU {cpu['on']:.2f} s in {n_on} tasks with it, {cpu['off']:.2f} s "
        f"in the others; client received {received.get('clouds')} clouds, "
        f"{received.get('bytes', 0) / 1e6:.1f} MB",
        flush=True,
    )
    return [
        {
            "run": parity,
            "task": m.task,
            "time_index": m.time_index,
            "viewer": on_block(m.task, args.block, parity),
            "critical_path_s": m.critical_path_s,
            "viewer_cpu_per_task_s": cpu["on"] / max(n_on, 1),
        }
        for m in metrics
        if m.status == "ok" and not m.degraded
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tasks", type=int, default=40, help="timestamps per run")
    ap.add_argument("--block", type=int, default=2, help="tasks per on / off block")
    ap.add_argument("--skip", type=int, default=2, help="first tasks of a run left out")
    ap.add_argument("--scale", type=float, default=0.8, help="fixed image scale (all cameras)")
    ap.add_argument("--deadline", type=float, default=2.0, help="deadline (s)")
    ap.add_argument("--background", action="store_true", help="background rebuilds on")
    ap.add_argument("--work", default="/tmp/edgerecon-bench", help="scene and runs")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    from edgerecon.synth import preset_config, write_dataset

    root = Path(args.work) / "demo"
    if not (root / "dataset.json").exists():
        write_dataset(preset_config("demo"), root, overwrite=True)
    scene = learn_scene_model(open_dataset(root))
    rows: list[dict[str, Any]] = []
    for parity in (0, 1):
        out = Path(args.work) / f"viewer-run-{parity}"
        rows += [r for r in one_run(root, scene, out, args, parity) if r["task"] >= args.skip]
    on = np.array([r["critical_path_s"] for r in rows if r["viewer"]])
    off = np.array([r["critical_path_s"] for r in rows if not r["viewer"]])
    paired = []
    for t in sorted({r["time_index"] for r in rows}):
        a = [r["critical_path_s"] for r in rows if r["time_index"] == t and r["viewer"]]
        b = [r["critical_path_s"] for r in rows if r["time_index"] == t and not r["viewer"]]
        if a and b:
            paired.append(a[0] / b[0])
    cpu_per_task = float(np.mean([r["viewer_cpu_per_task_s"] for r in rows]))
    result = {
        "tasks_with": len(on),
        "tasks_without": len(off),
        "mean_with_s": float(on.mean()),
        "mean_without_s": float(off.mean()),
        "ratio_of_means": float(on.mean() / off.mean()),
        "median_paired_ratio": float(np.median(paired)),
        "paired_timestamps": len(paired),
        "viewer_cpu_per_task_s": cpu_per_task,
        "viewer_cpu_share": cpu_per_task / float(off.mean()),
        "load_avg": os.getloadavg()[0],
    }
    print_rows("viewer cost on the critical path", list(result), [result])
    if args.json:
        write_report(args.json, {**report_header(), "args": vars(args), **result, "rows": rows})


if __name__ == "__main__":
    main()
