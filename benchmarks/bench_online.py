"""Online-system benchmark: the paper's Table III (online optimisation under deadlines) and
Table VI (latency of the original vs the optimized pipeline, with stage breakdown), and the
done-when numbers of the online system on real rigs (issue 11).

    python benchmarks/bench_online.py                                    # utrecht4cam + demo
    python benchmarks/bench_online.py --datasets caliscope_charuco --fractions 0.3 0.4 0.6
    python benchmarks/bench_online.py --datasets /data/hd4 --tasks 40 --json online.json
    python benchmarks/bench_online.py --datasets /data/hd4 --split fg_noise_adaptive_ncc=false  # A/B
    python benchmarks/bench_online.py --datasets /data/hd4 --set foreground.person_model=off  # A/B
    python benchmarks/bench_online.py --datasets caliscope_charuco --fractions 0.4 --engines embedded ray

Per dataset (a name under ../shared/data, a synthetic preset name, or a dataset folder):

1. the original pipeline — golden configuration (r = 1, all cameras), whole scene, no split —
   on ``--baseline-tasks`` timestamps: mean seconds per stage and total (Table VI, left; the
   product's own stage timings, as ``reconstruct`` writes them to timings.json);
2. the golden configuration of the foreground pipeline (``pipeline.reconstruct_task`` at
   r = 1 with all cameras) on every task's timestamp: the reference foreground of real data
   and the golden foreground point count;
3. for each deadline = fraction x the original pipeline's time and each of ``--engines``,
   ``edgerecon run`` (the embedded engine by default; ``ray``: a private Ray instance, the
   two roles as actors, against the same golden time), optimizer on, background updates in the back-end's idle time) over ``--tasks``
   timestamps: average scale, cameras, average critical path (all tasks and after
   convergence), deadline misses after convergence, degraded tasks, tasks slower than the
   golden task, the online/original ratio, online F, the offline foreground F (against the
   golden foreground of the same timestamp on real data, and against ground truth at 0.5 %,
   1 % and 2 % of the median camera distance on synthetic scenes; "moving_f": the same
   without the actors seated and still from the first frame, which no motion cue separates
   from the room), foreground points per task
   against the golden foreground's, the Pearson correlation of the online estimate with the
   offline F across the tasks (the configurations the controller visited; "pearson_moving":
   with the moving actors' F at 1 %, what the masks can hold), backgrounds
   pushed and search steps (Table III), and the optimized critical path's mean stage
   breakdown (Table VI, right).

Offline scores are computed after the run, never on the critical path. The machine's load
average is printed with each run: compare ratios taken within one run.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from _report import SHARED, print_rows, report_header, with_settings, write_report
from edgerecon.io.dataset import open_dataset
from edgerecon.pipeline import (
    SPARSE_SCOPES,
    SplitPipelineConfig,
    reconstruct,
    reconstruct_task,
    warm_up,
)
from edgerecon.quality import evaluate_clouds
from edgerecon.quality.metrics import evaluate_against
from edgerecon.quality.online import online_offline_correlation
from edgerecon.runtime import FrameRange, RuntimeConfig, SessionOptions, run_online
from edgerecon.runtime.config import median_camera_distance
from edgerecon.scene import ForegroundConfig
from edgerecon.scene.stream import bootstrap_scene
from edgerecon.types import PointCloud
from edgerecon.viewer.rundir import RunFolder


def dataset_root(name: str, work: Path) -> Path | None:
    from edgerecon.synth import PRESETS, preset_config, write_dataset

    if (Path(name) / "dataset.json").exists() or Path(name).is_dir():
        return Path(name)
    if name in PRESETS:
        root = work / name
        if not (root / "dataset.json").exists():
            write_dataset(preset_config(name), root, overwrite=True)
        return root
    root = SHARED / name
    return root if root.exists() else None


def golden_baseline(root: Path, times: list[int]) -> dict[str, Any]:
    """The original pipeline (whole scene, golden configuration) on ``times``: mean stage
    seconds and total."""
    ds = open_dataset(root)
    warm_up()  # the compiled kernels load before the first timed task
    stages: dict[str, list[float]] = {}
    totals = []
    with ds.open_frames() as src:
        for t in times:
            result = reconstruct(src.read(t), ds.rig)
            totals.append(result.timings.total)
            for k, v in result.timings.seconds.items():
                stages.setdefault(k, []).append(v)
    return {
        "times": times,
        "mean_total_s": float(np.mean(totals)),
        "stages_s": {k: round(float(np.mean(v)), 4) for k, v in stages.items()},
    }


def golden_foregrounds(
    root: Path,
    times: list[int],
    split: SplitPipelineConfig | None = None,
    foreground: ForegroundConfig | None = None,
) -> tuple[dict[int, PointCloud], float]:
    """The golden configuration's foreground (the foreground pipeline at r = 1 with all
    cameras, masks as the online system computes them) of every timestamp, and the mean
    seconds of that golden task (scene stage + the task's stage timings: the online
    system's own golden task)."""
    ds = open_dataset(root)
    out = {}
    seconds = []
    clip = ds.open_background()
    with ds.open_frames() as source:
        # One pass over the stream: the models at each time index, as the online system's.
        tracker = bootstrap_scene(ds.rig, source, ds.fps, foreground, clip=clip)
        for t in sorted(times):
            tracker.catch_up(source, t)
            frames = source.read(t)
            fg = tracker.segment(frames)
            rec = reconstruct_task(
                frames, ds.rig, fg, background=PointCloud.empty(), split_config=split
            )
            out[t] = rec.foreground.cloud
            seconds.append(fg.timings.total + rec.timings.total)
    if clip is not None:
        clip.close()
    return out, float(np.mean(seconds)) if seconds else math.nan


def run_deadline(
    root: Path,
    deadline: float,
    frames: FrameRange,
    out: Path,
    golden_fg: dict[int, PointCloud],
    original_s: float,
    sparse_scope: str = "hull",
    split: SplitPipelineConfig | None = None,
    engine: str = "embedded",
    still: bool = True,
    settings: Sequence[str] = (),
) -> dict[str, Any]:
    ds = open_dataset(root)
    dist = median_camera_distance(ds.rig)
    config = RuntimeConfig(
        deadline_s=deadline, sparse_scope=sparse_scope, split=split or SplitPipelineConfig()
    )
    config = with_settings(config, settings, "runtime")
    if not still:
        config = dataclasses.replace(config, still=None)
    options = SessionOptions(frames=frames, overwrite=True)
    load = os.getloadavg()[0]
    summary, metrics = run_online(ds, config, options, out, engine=engine)
    gt = None
    if ds.ground_truth is not None:
        from edgerecon.synth import GroundTruth

        gt = GroundTruth.open(ds.root)
    ok = [m for m in metrics if m.status == "ok"]
    vs_golden, vs_truth, online, points_share = [], [], [], []
    # The truth without the actors seated and still from the first frame (no motion cue
    # ever separates them from the room: they are reconstructed as background).
    vs_moving: list[list[float]] = []
    seated = gt.seated_from_start if gt is not None else []
    for m in ok:
        merged = RunFolder(out).cloud(m.time_index)
        assert merged is not None and merged.labels is not None
        fg = merged.select(merged.labels > 0)
        ref = golden_fg.get(m.time_index)
        if ref is not None and len(ref):
            f = evaluate_clouds(fg, ref, 0.01 * dist)[0].fscore if len(fg) else 0.0
            vs_golden.append(f)
            points_share.append(len(fg) / len(ref))
            if m.online_fscore is not None:
                online.append((m.online_fscore, f))
        if gt is not None:
            truth = gt.reference_cloud(m.time_index, "foreground", min_views=2)
            if len(truth):
                refs = [truth]
                if seated and truth.labels is not None:
                    moving = truth.select(~np.isin(truth.labels, seated))
                    if len(moving):
                        refs.append(moving)
                # One scoring of the task's foreground against both references, all thresholds.
                ths = [k * dist for k in (0.005, 0.01, 0.02)]
                if len(fg):
                    fs = [[sc.fscore for sc in row] for row in evaluate_against(fg, refs, ths)]
                else:
                    fs = [[0.0] * len(ths) for _ in refs]
                vs_truth.append(fs[0])
                if len(fs) > 1:
                    vs_moving.append(fs[1])
    if gt is not None and vs_truth:
        # Online estimate against the offline F vs truth at 1 % where there is truth.
        online = [
            (m.online_fscore, f[1])
            for m, f in zip(ok, vs_truth, strict=False)
            if m.online_fscore is not None
        ]
    corr = online_offline_correlation([a for a, _ in online], [b for _, b in online])
    # The same against the moving actors' F: what the masks can hold (an actor seated and
    # still from the first frame is in no mask, so no estimate made from them sees it).
    pearson_moving = None
    if vs_moving and len(vs_moving) == len(ok):
        pairs = [
            (m.online_fscore, f[1])
            for m, f in zip(ok, vs_moving, strict=True)
            if m.online_fscore is not None
        ]
        pearson_moving = online_offline_correlation(
            [a for a, _ in pairs], [b for _, b in pairs]
        ).pearson
    s = summary.to_dict()
    conv = s["avg_time_converged_s"]
    truth_mean = np.mean(vs_truth, axis=0) if vs_truth else [None, None, None]
    moving_mean = np.mean(vs_moving, axis=0) if vs_moving else [None, None, None]
    reused = [m for m in ok if m.still_share is not None]
    return {
        "engine": engine,
        "still": "on" if still else "off",
        "still_tasks": len(reused),
        "still_share": round(float(np.mean([m.still_share for m in reused])), 3)
        if reused
        else None,
        "deadline_s": deadline,
        "load": round(load, 1),
        "tasks": s["tasks"],
        "failed": s["failed"],
        "degraded": s["degraded"],
        "avg_scale": s["avg_scale"],
        "avg_cameras": s["avg_cameras"],
        "cameras": s["cameras_used"],
        "avg_time_s": s["avg_time_s"],
        "avg_time_converged_s": conv,
        "converged_vs_deadline": None if conv is None else round(conv / deadline - 1, 3),
        "misses_converged": s["deadline_misses_converged"],
        "slower_than_golden": sum(m.critical_path_s > original_s for m in ok),
        "online_over_original": round(
            float(np.mean([m.critical_path_s for m in ok])) / original_s, 3
        )
        if ok
        else None,
        "online_f": s["avg_online_fscore"],
        "offline_f_golden_1%": float(np.mean(vs_golden)) if vs_golden else None,
        "truth_f_0.5%": truth_mean[0],
        "truth_f_1%": truth_mean[1],
        "truth_f_2%": truth_mean[2],
        "moving_f_0.5%": moving_mean[0],
        "moving_f_1%": moving_mean[1],
        "moving_f_2%": moving_mean[2],
        "fg_points_vs_golden": float(np.median(points_share)) if points_share else None,
        "pearson_online_offline": corr.pearson,
        "pearson_moving": pearson_moving,
        "backgrounds": s["backgrounds_pushed"],
        "search_steps": s["search_steps"],
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
        "--relative-to",
        choices=("original", "golden-task"),
        default="original",
        help="deadlines as shares of the original pipeline's time (whole scene, r = 1, all "
        "cameras; the paper's) or of the online system's own golden task (default: original)",
    )
    ap.add_argument("--work", default="/tmp/edgerecon-bench", help="synthetic scenes and runs")
    ap.add_argument(
        "--sparse-scope",
        default="hull",
        choices=SPARSE_SCOPES,
        help="SfM of the foreground on golden-configuration tasks only (hull, default), on "
        "every task (foreground) or of the whole frames (scene, the paper)",
    )
    ap.add_argument(
        "--split",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="a SplitPipelineConfig setting for the online runs and the golden foreground "
        "(read as the [runtime.split] table of a --config file)",
    )
    ap.add_argument(
        "--engines",
        nargs="+",
        default=["embedded"],
        choices=("embedded", "ray"),
        help="engines of the online runs, each at every deadline (ray: a private local instance)",
    )
    ap.add_argument(
        "--still",
        nargs="+",
        default=["on"],
        choices=("on", "off"),
        help="still foreground (RuntimeConfig.still; off: every task densifies its whole "
        "foreground), each at every deadline",
    )
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="a RuntimeConfig setting for the online runs, dotted for nested ones (read as "
        "the [runtime] table of a --config file: foreground.person_model=off); its "
        "foreground settings also make the golden foreground's masks",
    )
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    split = with_settings(SplitPipelineConfig(), args.split, "runtime.split")
    fg_config = with_settings(RuntimeConfig(deadline_s=1.0), args.set, "runtime").foreground
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
        base_times = times[:: max(1, len(times) // args.baseline_tasks)][: args.baseline_tasks]
        t0 = time.perf_counter()
        base = golden_baseline(root, base_times)
        print(
            f"{name}: golden pipeline {base['mean_total_s']:.2f} s per task "
            f"({time.perf_counter() - t0:.0f} s for the baseline, load {os.getloadavg()[0]:.1f})"
        )
        golden_fg, golden_task_s = golden_foregrounds(root, times, split, fg_config)
        print(f"  the online system's golden task (r = 1, all cameras): {golden_task_s:.2f} s")
        reference_s = base["mean_total_s"] if args.relative_to == "original" else golden_task_s
        runs = []
        label = Path(name).name
        for frac in args.fractions:
            deadline = round(frac * reference_s, 2)
            for engine in args.engines:
                for still in args.still:
                    out = work / "runs" / f"{label}-{args.relative_to}-{frac:g}-{engine}-{still}"
                    row = run_deadline(
                        root,
                        deadline,
                        frames,
                        out,
                        golden_fg,
                        base["mean_total_s"],
                        args.sparse_scope,
                        split,
                        engine,
                        still == "on",
                        args.set,
                    )
                    row["fraction"] = frac
                    runs.append(row)
                    print(
                        f"  deadline {deadline:.2f} s ({engine}, still {still}): avg "
                        f"{row['avg_time_s']:.2f} s, converged {row['avg_time_converged_s']}, "
                        f"r {row['avg_scale']:.2f}"
                    )
        cols = [
            "fraction",
            *(["engine"] if len(args.engines) > 1 else []),
            "still",
            "still_tasks",
            "still_share",
            "deadline_s",
            "load",
            "avg_scale",
            "avg_cameras",
            "avg_time_s",
            "avg_time_converged_s",
            "converged_vs_deadline",
            "misses_converged",
            "degraded",
            "failed",
            "slower_than_golden",
            "online_over_original",
            "online_f",
            "offline_f_golden_1%",
            "truth_f_0.5%",
            "truth_f_1%",
            "truth_f_2%",
            "moving_f_0.5%",
            "moving_f_1%",
            "moving_f_2%",
            "fg_points_vs_golden",
            "pearson_online_offline",
            "pearson_moving",
            "backgrounds",
            "search_steps",
        ]
        print_rows(f"Table III — {label} ({len(times)} tasks)", cols, runs)
        stage_rows = [{"stage": k, "original": v} for k, v in base["stages_s"].items()]
        stage_rows.append({"stage": "total", "original": round(base["mean_total_s"], 3)})
        for r in runs:
            stage_rows.append(
                {
                    "stage": f"optimized @ {r['deadline_s']:.2f} s ({r['engine']}): critical path",
                    "optimized": r["avg_time_s"],
                    "reduction": round(1 - r["avg_time_s"] / base["mean_total_s"], 3),
                }
            )
            for k, v in sorted(r["stages_s"].items(), key=lambda kv: -kv[1])[:6]:
                stage_rows.append({"stage": f"    {k}", "optimized": v})
        print_rows(
            f"Table VI — {label}: original vs optimized per task (s)",
            ["stage", "original", "optimized", "reduction"],
            stage_rows,
        )
        report["datasets"][label] = {
            "frames": [frames.start, frames.stop, frames.step],
            "relative_to": args.relative_to,
            "golden_task_s": golden_task_s,
            "golden": base,
            "runs": runs,
        }
    if args.json:
        write_report(args.json, report)
        print(f"report: {args.json}")


if __name__ == "__main__":
    main()
