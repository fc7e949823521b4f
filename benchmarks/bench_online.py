"""Online-system benchmark: the paper's Table III (online optimisation under deadlines) and
Table VI (latency of the original vs the optimized pipeline, with stage breakdown).

    python benchmarks/bench_online.py                                    # utrecht4cam + demo
    python benchmarks/bench_online.py --datasets utrecht4cam --fractions 0.2 0.3 0.4 --tasks 40
    python benchmarks/bench_online.py --datasets demo --json online.json

Per dataset:

1. the original pipeline — golden configuration (r = 1, all cameras), whole scene, no split —
   on ``--baseline-tasks`` timestamps: mean seconds per stage and total (Table VI, left);
2. for each deadline = fraction x that golden time, ``edgerecon run`` (embedded engine,
   optimizer on, background updates in the back-end's idle time) over ``--tasks`` timestamps:
   average scale, cameras, average critical path (all tasks and after convergence), deadline
   misses after convergence, online F-score, offline F-score against the golden cloud's
   foreground (and against ground truth on synthetic scenes), backgrounds pushed, search steps
   (Table III), and the optimized critical path's mean stage breakdown (Table VI, right).

Offline F-score against the golden cloud: each task's foreground cloud is scored against the
golden whole-scene dense cloud of the same timestamp, restricted to the points the masks
label foreground (the paper's "offline evaluation"). Computed after the run, never on the
critical path.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np

from _report import SHARED, print_rows, report_header, write_report
from edgerecon.io.dataset import open_dataset
from edgerecon.io.ply import read_ply
from edgerecon.pipeline import label_by_masks, reconstruct, warm_up
from edgerecon.quality import evaluate_clouds
from edgerecon.runtime import FrameRange, RuntimeConfig, SessionOptions, run_online
from edgerecon.runtime.engine import learn_scene_model
from edgerecon.scene.foreground import RigForeground


def dataset_root(name: str, work: Path) -> Path | None:
    if name in ("demo", "arc7", "ring"):
        from edgerecon.synth import preset_config, write_dataset

        root = work / name
        if not (root / "dataset.json").exists():
            write_dataset(preset_config(name), root, overwrite=True)
        return root
    root = SHARED / name
    return root if root.exists() else None


def golden_baseline(root: Path, times: list[int]) -> dict[str, Any]:
    """The original pipeline on ``times``: mean stage seconds, and per time the golden dense
    cloud's foreground (masks from a background model warmed on the preceding frames)."""
    ds = open_dataset(root)
    warm_up()  # the compiled kernels load before the first timed task
    scene = learn_scene_model(ds)
    model = RigForeground.from_states(ds.rig, scene.states)
    stages: dict[str, list[float]] = {}
    totals = []
    golden_fg = {}
    with ds.open_frames() as src:
        for t in times:
            frames = src.read(t)
            fg = model.segment(frames)
            result = reconstruct(frames, ds.rig)
            totals.append(result.timings.total)
            for k, v in result.timings.seconds.items():
                stages.setdefault(k, []).append(v)
            assert result.dense is not None
            labels = label_by_masks(result.dense.cloud.points3D, ds.rig, fg.label_images(), 1.5)
            golden_fg[t] = result.dense.cloud.select(labels > 0)
    return {
        "times": times,
        "mean_total_s": float(np.mean(totals)),
        "stages_s": {k: round(float(np.mean(v)), 4) for k, v in stages.items()},
        "golden_fg": golden_fg,
    }


def run_deadline(
    root: Path,
    deadline: float,
    frames: FrameRange,
    out: Path,
    golden_fg: dict[int, Any],
    threshold: float,
    sparse_scope: str = "foreground",
) -> dict[str, Any]:
    ds = open_dataset(root)
    config = RuntimeConfig(deadline_s=deadline, sparse_scope=sparse_scope)
    options = SessionOptions(frames=frames, ground_truth_threshold=threshold, overwrite=True)
    summary, metrics = run_online(ds, config, options, out)
    vs_golden = []
    for m in metrics:
        if m.status != "ok" or m.time_index not in golden_fg:
            continue
        merged = read_ply(out / "tasks" / f"{m.time_index:06d}" / "merged.ply")
        fg = merged.select(merged.labels > 0)
        vs_golden.append(evaluate_clouds(fg, golden_fg[m.time_index], threshold)[0].fscore)
    s = summary.to_dict()
    return {
        "deadline_s": deadline,
        "avg_scale": s["avg_scale"],
        "avg_cameras": s["avg_cameras"],
        "cameras": s["cameras_used"],
        "avg_time_s": s["avg_time_s"],
        "avg_time_converged_s": s["avg_time_converged_s"],
        "converged_vs_deadline": None
        if s["avg_time_converged_s"] is None
        else round(s["avg_time_converged_s"] / deadline - 1, 3),
        "misses_converged": s["deadline_misses_converged"],
        "online_f": s["avg_online_fscore"],
        "offline_f_golden": float(np.mean(vs_golden)) if vs_golden else None,
        "offline_f_gt": s["avg_offline_fscore"],
        "backgrounds": s["backgrounds_pushed"],
        "search_steps": s["search_steps"],
        "degraded": s["degraded"],
        "stages_s": s["stage_means_s"],
        "wall_s": s["wall_s"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--datasets", nargs="+", default=["utrecht4cam", "demo"])
    ap.add_argument(
        "--fractions",
        nargs="+",
        type=float,
        default=[0.2, 0.3, 0.4],
        help="deadlines as shares of the golden per-task time",
    )
    ap.add_argument("--tasks", type=int, default=40, help="tasks per online run")
    ap.add_argument("--start", type=int, default=None, help="first timestamp (default: 40%% in)")
    ap.add_argument("--step", type=int, default=None, help="timestamp step (default: spread)")
    ap.add_argument("--baseline-tasks", type=int, default=3)
    ap.add_argument(
        "--threshold-rel",
        type=float,
        default=0.005,
        help="F-score threshold relative to the median camera distance",
    )
    ap.add_argument("--work", default="/tmp/edgerecon-bench", help="synthetic scenes and runs")
    ap.add_argument(
        "--sparse-scope",
        default="foreground",
        choices=("foreground", "scene"),
        help="SfM of the foreground only (default) or of the whole frames (the paper)",
    )
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    work = Path(args.work)
    report: dict[str, Any] = {**report_header(), "datasets": {}}
    for name in args.datasets:
        root = dataset_root(name, work)
        if root is None:
            print(f"skipping {name}: not found")
            continue
        ds = open_dataset(root)
        n = ds.num_frames
        start = args.start if args.start is not None else (0 if n <= args.tasks else n // 4)
        step = args.step or max(1, (n - start) // args.tasks)
        frames = FrameRange(start=start, stop=min(n, start + step * args.tasks), step=step)
        times = frames.indices(n)
        threshold = RuntimeConfig(
            deadline_s=1.0, eval_threshold_rel=args.threshold_rel
        ).eval_threshold_for(ds.rig)
        base_times = times[:: max(1, len(times) // args.baseline_tasks)][: args.baseline_tasks]
        t0 = time.perf_counter()
        base = golden_baseline(root, base_times)
        # Offline reference for every task: the golden foreground of the task's timestamp.
        golden_fg = dict(base["golden_fg"])
        missing = [t for t in times if t not in golden_fg]
        golden_fg.update(golden_baseline(root, missing)["golden_fg"] if missing else {})
        print(
            f"{name}: golden pipeline {base['mean_total_s']:.2f} s per task "
            f"({time.perf_counter() - t0:.0f} s for the baseline)"
        )
        runs = []
        for frac in args.fractions:
            deadline = round(frac * base["mean_total_s"], 2)
            out = work / "runs" / f"{name}-{frac:g}"
            row = run_deadline(root, deadline, frames, out, golden_fg, threshold, args.sparse_scope)
            row["fraction"] = frac
            runs.append(row)
            print(
                f"  deadline {deadline:.2f} s: avg {row['avg_time_s']:.2f} s, converged "
                f"{row['avg_time_converged_s']}, r {row['avg_scale']:.2f}"
            )
        cols = [
            "fraction",
            "deadline_s",
            "avg_scale",
            "avg_cameras",
            "avg_time_s",
            "avg_time_converged_s",
            "converged_vs_deadline",
            "misses_converged",
            "online_f",
            "offline_f_golden",
            "offline_f_gt",
            "backgrounds",
            "search_steps",
            "degraded",
        ]
        print_rows(
            f"Table III — {name} ({len(times)} tasks, threshold {threshold:.4g} {ds.rig.unit})",
            cols,
            runs,
        )
        stage_rows = [{"stage": k, "original": v} for k, v in base["stages_s"].items()]
        stage_rows.append({"stage": "total", "original": round(base["mean_total_s"], 3)})
        for r in runs:
            stage_rows.append(
                {
                    "stage": f"optimized @ {r['deadline_s']:.2f} s: critical path",
                    "optimized": r["avg_time_s"],
                    "reduction": round(1 - r["avg_time_s"] / base["mean_total_s"], 3),
                }
            )
            for k, v in sorted(r["stages_s"].items(), key=lambda kv: -kv[1])[:6]:
                stage_rows.append({"stage": f"    {k}", "optimized": v})
        print_rows(
            f"Table VI — {name}: original vs optimized per task (s)",
            ["stage", "original", "optimized", "reduction"],
            stage_rows,
        )
        report["datasets"][name] = {
            "frames": [frames.start, frames.stop, frames.step],
            "threshold": threshold,
            "golden": {k: v for k, v in base.items() if k != "golden_fg"},
            "runs": runs,
        }
    if args.json:
        write_report(args.json, report)
        print(f"report: {args.json}")


if __name__ == "__main__":
    main()
