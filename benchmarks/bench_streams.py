"""The online system on live camera streams: three loopback MJPEG streams, one stalls.

    python benchmarks/bench_streams.py                        # 60 s, demo scene, cameras 0 1 2
    python benchmarks/bench_streams.py --duration 30 --stall 10 20 --json streams.json

The demo scene's frames (its cameras ``--cameras``) are served in a loop at ``--fps`` as
MJPEG streams on 127.0.0.1 (``edgerecon.io.mjpeg.serve_dataset``: one stream per camera, one
clock for all), with a ``dataset.json`` of ``frames.kind = "stream"`` pointing at them (and the
scene's recorded background clip). ``run_online`` reads them for ``--duration`` seconds
(optimizer on, embedded engine). The last camera stops sending from ``--stall A B`` seconds
after the first task (its connection stays open) and resumes after. Printed: one row per
task (cameras in the task, sync spread, critical path), when the stalled camera left the tasks
and when it came back, and the stream counts (sets, waits, cameras left out, frames dropped).
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from _report import print_rows, report_header, write_report
from edgerecon.io.dataset import open_dataset
from edgerecon.io.mjpeg import serve_dataset
from edgerecon.runtime import FrameRange, RuntimeConfig, SessionOptions, run_online


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=60.0, help="seconds of live run")
    ap.add_argument("--cameras", type=int, nargs="+", default=[0, 1, 2], help="served cameras")
    ap.add_argument("--fps", type=float, default=10.0, help="stream frame rate")
    ap.add_argument(
        "--stall",
        type=float,
        nargs=2,
        default=(20.0, 35.0),
        metavar=("FROM", "TO"),
        help="seconds after the first task during which the last camera sends nothing",
    )
    ap.add_argument("--tolerance", type=float, default=0.05, help="sync tolerance (s)")
    ap.add_argument("--deadline", type=float, default=2.0, help="deadline (s)")
    ap.add_argument("--work", default="/tmp/edgerecon-bench", help="scene and runs")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s: %(message)s")
    from edgerecon.synth import preset_config, write_dataset

    root = Path(args.work) / "demo"
    if not (root / "dataset.json").exists():
        write_dataset(preset_config("demo"), root, overwrite=True)
    live_dir = Path(args.work) / "demo-live"
    server = serve_dataset(
        root,
        live_dir,
        cameras=args.cameras,
        fps=args.fps,
        stream_options={"sync_tolerance_s": args.tolerance, "stall_s": 1.0, "max_wait_s": 1.0},
    )
    stalled = len(args.cameras) - 1
    first_task: list[float] = []

    def on_task(m: Any) -> None:
        if not first_task:
            first_task.append(time.time() - m.critical_path_s)
            server.add_stall(stalled, args.stall[0], args.stall[1])
        cams = ",".join(str(i) for i in m.camera_ids) if m.status == "ok" else "-"
        spread = "-" if m.sync_spread_s is None else f"{m.sync_spread_s * 1000:.1f} ms"
        print(
            f"task {m.task:3d} at {time.time() - first_task[0]:5.1f} s: {m.status:6s} "
            f"cameras {cams:7s} spread {spread:9s} T {m.critical_path_s:.2f} s "
            f"{m.error[:60]}",
            flush=True,
        )

    try:
        ds = open_dataset(live_dir)
        config = RuntimeConfig(deadline_s=args.deadline)
        options = SessionOptions(
            policy="newest", duration_s=args.duration, frames=FrameRange(start=0), overwrite=True
        )
        out = Path(args.work) / "demo-live-run"
        wall0 = time.perf_counter()
        summary, metrics = run_online(ds, config, options, out, on_task=on_task)
        wall = time.perf_counter() - wall0
    finally:
        server.stop()
    t0 = first_task[0]
    rows = []
    for m in metrics:
        rows.append(
            {
                "task": m.task,
                "at_s": round(m.wall_time - t0, 1),
                "status": m.status,
                "cameras": m.camera_ids,
                "spread_ms": None if m.sync_spread_s is None else m.sync_spread_s * 1000,
                "critical_path_s": m.critical_path_s,
            }
        )
    without = [r for r in rows if r["status"] != "ok" or stalled not in r["cameras"]]
    after = [r for r in rows if without and r["task"] > without[-1]["task"]]
    spreads = np.array([r["spread_ms"] for r in rows if r["spread_ms"] is not None])
    result = {
        "tasks": len(rows),
        "ok": sum(r["status"] == "ok" for r in rows),
        "wall_s": wall,
        "spread_ms_mean": float(spreads.mean()) if len(spreads) else None,
        "spread_ms_p95": float(np.percentile(spreads, 95)) if len(spreads) else None,
        "spread_ms_max": float(spreads.max()) if len(spreads) else None,
        "stalled_camera": ds.rig.names[stalled],
        "left_out_first_at_s": without[0]["at_s"] if without else None,
        "left_out_last_at_s": without[-1]["at_s"] if without else None,
        "tasks_without_it": len(without),
        "back_at_s": after[0]["at_s"] if after else None,
        "stream": summary.stream,
    }
    print_rows("tasks", ["task", "at_s", "status", "cameras", "spread_ms", "critical_path_s"], rows)
    print_rows("live run", [k for k in result if k != "stream"], [result])
    print_rows("stream counts", list(summary.stream), [summary.stream])
    if args.json:
        write_report(args.json, {**report_header(), "args": vars(args), **result, "rows": rows})


if __name__ == "__main__":
    main()
