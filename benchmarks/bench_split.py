"""Foreground/background split benchmark: foreground-only MVS against the golden whole-scene
MVS, on utrecht4cam and on the synthetic 7-camera 1920x1080 arc (issue 4's done-when).

    python benchmarks/bench_split.py                       # utrecht4cam t=200 + arc7 t=20
    python benchmarks/bench_split.py --datasets arc7 --synthetic-dir /tmp/arc7 --json split.json

Per dataset and timestamp: the background model learns from the background clip and sees the
five frames before the task; then, on the same views and sparse cloud,

* golden: ``reconstruct_dense`` over the whole images (the original pipeline's MVS);
* foreground: ``reconstruct_foreground`` (split, MVS restricted to the dilated foreground and
  the visual hull's depth interval, labelling).

Both after one untimed warm-up run (the compiled kernels load once per process).

Reported: foreground share of the image area, seconds of each MVS (wall and process CPU), the
ratio (target <= 25 %), dense point counts, and on synthetic scenes the foreground F-score
against the ground truth (surfaces seen by >= 2 cameras) of the foreground pipeline and of the
golden cloud's foreground points (target: within 0.03).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from _report import SHARED, print_rows, report_header, write_report
from edgerecon.config import ReconstructionConfig
from edgerecon.dense import DenseConfig, reconstruct_dense
from edgerecon.io.dataset import open_dataset
from edgerecon.pipeline import label_by_masks, prepare_task_views, reconstruct_foreground
from edgerecon.quality import evaluate_clouds
from edgerecon.runtime.engine import foreground_at
from edgerecon.sparse import reconstruct_sparse


def synthetic_arc7(folder: Path, num_frames: int = 24) -> Path:
    """The arc7 stream in ``folder``, written (again) unless it holds ``num_frames`` frames."""
    from edgerecon.synth import preset_config, write_dataset

    if not (folder / "dataset.json").exists() or open_dataset(folder).num_frames < num_frames:
        write_dataset(
            preset_config("arc7", num_frames=num_frames, background_frames=8),
            folder,
            overwrite=True,
        )
    return folder


def measure(root: Path, t: int, threshold: float | None) -> dict[str, Any]:
    ds = open_dataset(root)
    rig = ds.rig
    frames, fg = foreground_at(ds, t)
    views = prepare_task_views(frames, rig, ReconstructionConfig())
    sparse = reconstruct_sparse(views)
    config = DenseConfig()

    def timed(fn: Any) -> tuple[Any, float, float]:
        w0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        return out, time.perf_counter() - w0, time.process_time() - c0

    # Warm-up: the compiled kernels load once per process (a second or two, which would
    # otherwise land on whichever variant runs first).
    reconstruct_foreground(views, rig, sparse, fg, config)
    golden, g_wall, g_cpu = timed(lambda: reconstruct_dense(views, config, sparse, up=rig.up))
    fgr, f_wall, f_cpu = timed(lambda: reconstruct_foreground(views, rig, sparse, fg, config))
    area = float(np.mean([m.mean() for m in fg.masks if m is not None]))
    row: dict[str, Any] = {
        "dataset": ds.name,
        "time": t,
        "cameras": len(rig),
        "size": f"{rig[0].width}x{rig[0].height}",
        "fg_area": round(area, 4),
        "golden_dense_s": round(g_wall, 3),
        "golden_dense_cpu_s": round(g_cpu, 3),
        "fg_dense_s": round(f_wall, 3),
        "fg_dense_cpu_s": round(f_cpu, 3),
        "ratio_wall": round(f_wall / g_wall, 3),
        "ratio_cpu": round(f_cpu / g_cpu, 3),
        "golden_points": len(golden.cloud),
        "fg_points": len(fgr.cloud),
    }
    if threshold is not None and ds.ground_truth is not None:
        from edgerecon.synth import GroundTruth

        gt = GroundTruth.open(root)
        ref = gt.reference_cloud(t, "foreground", min_views=2)
        labels = label_by_masks(golden.cloud.points3D, rig, fg.label_images(), 1.5)
        golden_fg = golden.cloud.select(labels > 0)
        s_fg = evaluate_clouds(fgr.cloud, ref, threshold)[0]
        s_gold = evaluate_clouds(golden_fg, ref, threshold)[0]
        row.update(
            threshold=threshold,
            fg_fscore=round(s_fg.fscore, 4),
            fg_precision=round(s_fg.precision, 4),
            fg_recall=round(s_fg.recall, 4),
            golden_fg_fscore=round(s_gold.fscore, 4),
            fscore_gap=round(s_gold.fscore - s_fg.fscore, 4),
        )
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--datasets", nargs="+", default=["utrecht4cam", "arc7"])
    ap.add_argument("--synthetic-dir", default="/tmp/edgerecon-bench/arc7-stream")
    ap.add_argument("--time-utrecht", type=int, default=200)
    ap.add_argument("--time-arc7", type=int, default=20)
    ap.add_argument("--threshold", type=float, default=0.02, help="F-score threshold (m)")
    ap.add_argument("--json", default=None, help="write the report here")
    args = ap.parse_args()
    rows = []
    for name in args.datasets:
        if name == "arc7":
            root = synthetic_arc7(Path(args.synthetic_dir), max(24, args.time_arc7 + 1))
            rows.append(measure(root, args.time_arc7, args.threshold))
        else:
            root = SHARED / name
            if not root.exists():
                print(f"skipping {name}: {root} not found")
                continue
            rows.append(measure(root, args.time_utrecht, None))
    cols = [
        "dataset",
        "time",
        "size",
        "fg_area",
        "golden_dense_s",
        "fg_dense_s",
        "ratio_wall",
        "ratio_cpu",
        "golden_points",
        "fg_points",
        "fg_fscore",
        "golden_fg_fscore",
        "fscore_gap",
    ]
    print_rows("foreground-only MVS vs golden whole-scene MVS", cols, rows)
    if args.json:
        write_report(args.json, {**report_header(), "rows": rows})
        print(f"report: {args.json}")
    print(json.dumps({"rows": len(rows)}))


if __name__ == "__main__":
    main()
