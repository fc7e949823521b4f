"""The foreground's cost over the image scale r, and the model the controller skips scales by.

    python benchmarks/bench_scale_cost.py
    python benchmarks/bench_scale_cost.py --datasets ../shared/data/caliscope_charuco /tmp/hd4 \\
        --reps 5 --json scale_cost.json

One task's foreground per time index (``pipeline.reconstruct_task`` as the online front-end
runs it: hull scope, no background, every camera, the online system's ``task_configs``,
masks from the stream's scene model) at every r of ``--scales``, ``--reps`` passes in
alternating order; the seconds of its ``fg_*`` stages, median per (time, r). Then:

* the least-squares fit of those seconds to an intercept per time index plus the working
  pixels (two local-search passes, and separately the passes above r = 1) plus the pixels
  of the level the plane sweep runs at (``pipeline.foreground_pixels``): the sweep pixel's
  weight against a working pixel (``dense.depth.SWEEP_PIXEL_COST`` takes 8), one pass's
  weight against two, the fit's rms;
* the intervals the controller skips on the rig (``pipeline.dominated_scales``) and, for
  each, the measured seconds of the r inside against those at its upper end (a skipped r
  should cost more).

Times are of this machine and its load (printed): compare within one run.
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from _report import SHARED, print_rows, report_header, write_report
from edgerecon.io.dataset import open_dataset
from edgerecon.optimize import BisectionController
from edgerecon.pipeline import foreground_pixels, reconstruct_task, warm_up
from edgerecon.progress import track
from edgerecon.runtime.config import RuntimeConfig
from edgerecon.runtime.online import make_controller
from edgerecon.scene.stream import dataset_scene_at
from edgerecon.types import PointCloud

DEFAULT_SCALES = (0.3, 0.4, 0.45, 0.5, 0.55, 0.6, 0.7, 0.8, 0.9, 1.0, 1.1, 1.2, 1.5)


def measure(root: Path, times: list[int], scales: list[float], reps: int) -> list[dict[str, Any]]:
    """Median seconds of the foreground's stages per (time index, r)."""
    ds = open_dataset(root)
    rig = ds.rig
    rc = RuntimeConfig(deadline_s=1.0)
    ids = tuple(range(len(rig)))
    seconds: dict[tuple[int, float], list[float]] = defaultdict(list)
    points: dict[tuple[int, float], int] = {}
    for t in times:
        tracker = dataset_scene_at(ds, t, rc.foreground)
        with ds.open_frames() as source:
            frames = source.read(t)
        fg = tracker.segment(frames)
        for rep in track(range(reps), f"{ds.name} t={t}"):
            for r in scales if rep % 2 == 0 else scales[::-1]:
                cfg, split = rc.task_configs(r, rig, ids)
                rec = reconstruct_task(
                    frames,
                    rig,
                    fg,
                    cfg,
                    background=PointCloud.empty(),
                    split_config=split,
                    sparse_scope="hull",
                )
                stages = rec.timings.to_dict()
                seconds[t, r].append(sum(v for k, v in stages.items() if k.startswith("fg_")))
                points[t, r] = len(rec.foreground.cloud)
    rows = []
    for (t, r), v in sorted(seconds.items()):
        working, sweep, passes = foreground_pixels(
            r, rig, dense_config=rc.dense, split_config=rc.split
        )
        rows.append(
            {
                "t": t,
                "r": r,
                "seconds": float(np.median(v)),
                "points": points[t, r],
                "working_px": working,
                "sweep_px": sweep,
                "passes": passes,
            }
        )
    return rows


def fit(rows: list[dict[str, Any]]) -> dict[str, float]:
    """Seconds = intercept per time index + a working pixel's seconds (two passes, one pass)
    + a sweep pixel's: the weights relative to a working pixel at two passes."""
    times = sorted({r["t"] for r in rows})
    passes = sorted({r["passes"] for r in rows})
    X, y = [], []
    for r in rows:
        X.append(
            [1.0 if r["t"] == t else 0.0 for t in times]
            + [r["working_px"] * 1e-5 if r["passes"] == p else 0.0 for p in passes]
            + [r["sweep_px"] * 1e-5]
        )
        y.append(r["seconds"])
    A, b = np.asarray(X), np.asarray(y)
    coef, *_ = np.linalg.lstsq(A, b, rcond=None)
    rms = float(np.sqrt(np.mean((A @ coef - b) ** 2)))
    per_pass = dict(zip(passes, coef[len(times) : len(times) + len(passes)], strict=True))
    ref = per_pass.get(2, next(iter(per_pass.values())))
    out = {"sweep_pixel_weight": float(coef[-1] / ref) if ref > 0 else float("nan")}
    for p, c in per_pass.items():
        out[f"pass{p}_weight"] = float(c / ref) if ref > 0 else float("nan")
    out["rms_s"] = rms
    out["points"] = len(rows)
    return out


def check_intervals(root: Path, rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The controller's skipped intervals on this rig, with the measured seconds of the
    scales inside against those at (or just above) the upper end."""
    ds = open_dataset(root)
    ctrl = make_controller(ds, RuntimeConfig(deadline_s=1.0))
    assert isinstance(ctrl, BisectionController)
    skipped = ctrl.config.skip_scales
    out = []
    measured = sorted({r["r"] for r in rows})
    for a, b in skipped:
        inside = [r for r in measured if a < r < b]
        above = [r for r in measured if r >= b]
        if not inside or not above:
            out.append({"interval": f"{a:g}-{b:g}", "inside": "-", "at_end": "-"})
            continue
        end = above[0]

        def mean_s(scales: list[float]) -> float:
            return float(np.mean([r["seconds"] for r in rows if r["r"] in scales]))

        out.append(
            {
                "interval": f"{a:g}-{b:g}",
                "inside": ", ".join(f"{r:g}" for r in inside),
                "inside_s": mean_s(inside),
                "at_end": f"{end:g}",
                "at_end_s": mean_s([end]),
            }
        )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--datasets", nargs="+", type=Path, default=[SHARED / "caliscope_charuco"], metavar="DIR"
    )
    ap.add_argument("--times", nargs="+", type=int, help="time indices (default: 3 spread)")
    ap.add_argument("--scales", nargs="+", type=float, default=list(DEFAULT_SCALES))
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--json", metavar="FILE", help="also write the results as JSON")
    args = ap.parse_args()
    warm_up()
    report: dict[str, Any] = {"header": report_header(), "datasets": {}}
    print(f"load {report['header']['load_avg']:.1f}, {report['header']['cpus']} CPUs")
    for root in args.datasets:
        if not root.exists():
            print(f"{root}: not found, skipped")
            continue
        ds = open_dataset(root)
        n = ds.num_frames
        times = args.times or [n * k // 4 for k in (1, 2, 3)]
        ctrl = make_controller(ds, RuntimeConfig(deadline_s=1.0))
        assert isinstance(ctrl, BisectionController)
        finest = ctrl.config.r_fine or ctrl.config.r_max
        scales = [s for s in args.scales if s <= finest]
        t0 = time.perf_counter()
        rows = measure(root, times, scales, args.reps)
        model = fit(rows)
        intervals = check_intervals(root, rows)
        report["datasets"][ds.name] = {"rows": rows, "fit": model, "intervals": intervals}
        table = []
        for r in scales:
            row: dict[str, Any] = {"r": r}
            for t in times:
                row[f"t={t}"] = next(x["seconds"] for x in rows if x["t"] == t and x["r"] == r)
            table.append(row)
        print_rows(
            f"{ds.name}: the foreground's seconds per r ({time.perf_counter() - t0:.0f} s)",
            ["r", *(f"t={t}" for t in times)],
            table,
        )
        print_rows(
            f"{ds.name}: fit (weights against a working pixel with two local-search passes)",
            list(model),
            [model],
        )
        print_rows(
            f"{ds.name}: skipped intervals (pipeline.dominated_scales) against the measurements",
            ["interval", "inside", "inside_s", "at_end", "at_end_s"],
            intervals,
        )
    if args.json:
        write_report(args.json, report)


if __name__ == "__main__":
    main()
