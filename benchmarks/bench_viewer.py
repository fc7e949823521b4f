"""The live viewer's cost on the critical path: the same online run with and without it.

    python benchmarks/bench_viewer.py                          # demo scene, 2 pairs of runs
    python benchmarks/bench_viewer.py --pairs 3 --tasks 40 --json viewer.json

Each pair runs the demo scene's online system twice with one fixed configuration (so both
runs do the same work; ``--adaptive`` lets the optimizer choose, as ``demo`` does; no
background rebuilds unless ``--background``; masks waited for, so no task runs degraded): once
plain and once as ``run --view`` runs it (``edgerecon view`` in a child process at nice 10,
following the run folder) with a client connected that receives and decodes every message
(``python -m edgerecon.viewer.wire``, standing in for a browser on another device; run at
nice 19 so that it takes as little as possible from the device it does not belong on). The
order alternates between pairs. Reported per run: mean and median critical path, CPU
seconds of the run's process, of the viewer process and of the client, clouds received.
The viewer's cost is the ratio of mean critical paths, with vs without, over all pairs.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
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


def one_run(
    root: Path, scene: Any, out: Path, args: argparse.Namespace, view: bool
) -> dict[str, Any]:
    ds = open_dataset(root)
    # Generous waits: on a busy machine a late mask would make a task degraded and change
    # its work; both runs must do the same work.
    config = RuntimeConfig(
        deadline_s=args.deadline,
        masks_timeout_s=60.0,
        golden_timeout_s=60.0,
        background_updates=args.background,
    )
    options = SessionOptions(frames=FrameRange(start=0, stop=args.tasks))
    fixed = None if args.adaptive else (args.scale, None)
    viewer = client = None
    viewer_cpu0 = 0.0
    if view:
        viewer = start_viewer_process(out, port=0)
        viewer_cpu0 = cpu_seconds(viewer.pid)  # its start-up (imports) is before the run
        client = subprocess.Popen(
            ["nice", "-n", "19", sys.executable, "-m", "edgerecon.viewer.wire", str(viewer.port)],
            stdout=subprocess.PIPE,
            text=True,
        )
    cpu0 = resource.getrusage(resource.RUSAGE_SELF)
    wall0 = time.perf_counter()
    try:
        _, metrics = run_online(ds, config, options, out, fixed=fixed, scene=scene)
        time.sleep(2 * 0.25)  # the viewer's last look at the folder
    finally:
        wall = time.perf_counter() - wall0
        cpu1 = resource.getrusage(resource.RUSAGE_SELF)
        viewer_cpu = client_cpu = None
        received: dict[str, Any] = {}
        if viewer is not None:
            viewer_cpu = cpu_seconds(viewer.pid) - viewer_cpu0
            viewer.stop()
        if client is not None:
            client_cpu = cpu_seconds(client.pid)
            client.terminate()
            received = json.loads(client.communicate(timeout=30)[0].strip() or "{}")
    ok = [m for m in metrics if m.status == "ok"]
    paths = np.array([m.critical_path_s for m in ok])
    return {
        "view": view,
        "tasks": len(ok),
        "mean_critical_path_s": float(paths.mean()),
        "median_critical_path_s": float(np.median(paths)),
        "mean_scale": float(np.mean([m.scale for m in ok])),
        "wall_s": wall,
        "run_cpu_s": (cpu1.ru_utime + cpu1.ru_stime) - (cpu0.ru_utime + cpu0.ru_stime),
        "viewer_cpu_s": viewer_cpu,
        "client_cpu_s": client_cpu,
        "clouds_received": received.get("clouds"),
        "mb_received": None if not received else received["bytes"] / 1e6,
        "load_avg": os.getloadavg()[0],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs", type=int, default=2, help="pairs of runs (with / without)")
    ap.add_argument("--tasks", type=int, default=40, help="tasks per run")
    ap.add_argument("--scale", type=float, default=0.8, help="fixed image scale (all cameras)")
    ap.add_argument("--adaptive", action="store_true", help="let the optimizer choose")
    ap.add_argument("--deadline", type=float, default=2.0, help="deadline (s)")
    ap.add_argument(
        "--background",
        action="store_true",
        help="background rebuilds on (off by default: they compete with the viewer for the "
        "low-priority CPU and make runs differ more)",
    )
    ap.add_argument("--work", default="/tmp/edgerecon-bench", help="scene and runs")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    from edgerecon.synth import preset_config, write_dataset

    root = Path(args.work) / "demo"
    if not (root / "dataset.json").exists():
        write_dataset(preset_config("demo"), root, overwrite=True)
    scene = learn_scene_model(open_dataset(root))
    rows = []
    for pair in range(args.pairs):
        order = (False, True) if pair % 2 == 0 else (True, False)
        for view in order:
            out = Path(args.work) / f"viewer-run-{pair}-{'view' if view else 'plain'}"
            row = one_run(root, scene, out, args, view)
            row["pair"] = pair
            rows.append(row)
            print_rows("run", list(row), [row])
    with_v = [r["mean_critical_path_s"] for r in rows if r["view"]]
    without = [r["mean_critical_path_s"] for r in rows if not r["view"]]
    ratio = float(np.mean(with_v) / np.mean(without))
    pairs = [
        next(r for r in rows if r["pair"] == p and r["view"])["mean_critical_path_s"]
        / next(r for r in rows if r["pair"] == p and not r["view"])["mean_critical_path_s"]
        for p in range(args.pairs)
    ]
    viewer_cpu = [r["viewer_cpu_s"] for r in rows if r["view"]]
    run_cpu = [r["run_cpu_s"] for r in rows if r["view"]]
    columns = ["pair", "view", "tasks", "mean_critical_path_s", "median_critical_path_s"]
    columns += ["run_cpu_s", "viewer_cpu_s", "client_cpu_s", "clouds_received", "mb_received"]
    print_rows("viewer cost on the critical path", columns + ["wall_s", "load_avg"], rows)
    print(
        f"\nmean critical path with / without the viewer: {ratio:.3f} "
        f"(per pair: {', '.join(f'{p:.3f}' for p in pairs)}); viewer CPU "
        f"{np.sum(viewer_cpu):.1f} s for {np.sum(run_cpu):.1f} s of the runs' CPU "
        f"({np.sum(viewer_cpu) / np.sum(run_cpu):.1%})"
    )
    if args.json:
        write_report(
            args.json,
            {**report_header(), "args": vars(args), "runs": rows, "ratio": ratio, "pairs": pairs},
        )


if __name__ == "__main__":
    main()
