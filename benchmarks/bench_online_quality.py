"""Does the online quality estimate carry signal? (issue 11, item 6)

For a few timestamps of a dataset and the configurations the controller visits (image scales
x camera subsets pi(N')), runs the task's foreground pipeline exactly as the front-end does
(SfM on the foreground crops, split, foreground MVS) and compares every candidate online
estimate with the *offline* foreground F-score of the task's dense foreground:

* synthetic datasets (with ground truth): against the ground-truth foreground surfaces seen by
  >= 2 cameras, at 1 % and 2 % of the median camera distance;
* real datasets: against the golden configuration's dense foreground of the same timestamp.

Online estimates compared (all against the back-end's golden reference of the same task, the
golden configuration's foreground sparse points, at the online threshold d):

* ``sparse_F``  — the paper's: F-score of the task's foreground sparse points;
* ``coverage``  — share of the golden foreground sparse points within d of the task's dense
  foreground (what of the golden surfaces the task recovered);
* ``dense_F``   — F-score of the task's dense foreground against the golden sparse points,
  precision taken at 3 d (a sparse reference is too thin to judge dense precision at d);
* ``sil_recall`` / ``sil_F`` — no golden reference at all: the task's dense foreground
  projected into every camera's foreground mask (all cameras, also those the task left out):
  share of mask pixels within a pixel of a point (recall; only the pixels with texture,
  ``quality.online.textured``: the front-end's estimate), share of points in the masks
  (precision); ``sil_F_all`` the same with every mask pixel in the recall;
* ``density``   — dense foreground points per foreground mask pixel, relative to the golden
  task's (capped at 1).

Prints the samples and, per estimate, Pearson / Spearman correlation with the offline score
over all samples, and the mean and smallest Pearson within one timestamp across its
configurations (the same content: what the controller compares). On synthetic data with
actors seated and still from the first frame (in no mask, so no estimate from the masks sees
them) the offline F is also given without them ("moving").

    python benchmarks/bench_online_quality.py --dataset DIR --times 60 90 120
    python benchmarks/bench_online_quality.py --dataset DIR --times 60 90 120 \
        --configs-from RUN        # the configurations an online run's controller visited

``--configs-from``: instead of the grid of ``--scales`` x subsets, the configurations
(r, camera set) that the tasks of a run folder ran (``edgerecon run`` or ``bench_online.py``'s
runs), each judged at every ``--times`` timestamp: the correlation "across the configurations
the controller visits" (issue 11) with the content held fixed, where a run's own Pearson
correlates tasks of different timestamps (on a run that settles on one configuration, the
content's spread, not the configurations').
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path
from typing import Any

import numpy as np

from _report import print_rows, report_header, write_report
from edgerecon.config import MIN_CAMERAS
from edgerecon.geometry.camera import Rig
from edgerecon.io.dataset import open_dataset
from edgerecon.optimize.selection import camera_mapping
from edgerecon.pipeline import (
    ForegroundReconstruction,
    fine_scale_limit,
    reconstruct_task,
    warm_up,
)
from edgerecon.quality.metrics import evaluate_clouds
from edgerecon.quality.online import online_offline_correlation, silhouette_quality
from edgerecon.runtime.config import RuntimeConfig, median_camera_distance
from edgerecon.scene.foreground import ForegroundResult
from edgerecon.scene.stream import dataset_scene_at
from edgerecon.sparse import SparseReconstruction
from edgerecon.types import FrameSet, PointCloud
from edgerecon.viewer.rundir import RunFolder

ESTIMATES = ("sparse_F", "coverage", "dense_F", "sil_recall", "sil_F", "sil_F_all", "density")


def estimates(
    fg_sparse: np.ndarray,
    fg_dense: np.ndarray,
    golden_sparse: np.ndarray,
    d: float,
    fg: ForegroundResult,
    golden_density: float,
) -> dict[str, float]:
    """The candidate online estimates of one task (see the module docstring)."""
    from scipy.spatial import cKDTree

    out: dict[str, float] = {}
    # The front-end's estimate: recall over the masks' textured pixels (``sil_F``); without
    # the frames, over every mask pixel (``sil_F_all``, the estimate before the textured recall).
    images = [None if sg is None else sg.image for sg in fg.segmentations] or None
    sil = silhouette_quality(fg_dense, fg.cameras, fg.masks, images=images)
    out["sil_recall"] = sil.recall if sil.recall is not None else np.nan
    out["sil_F"] = sil.fscore if sil.fscore is not None else np.nan
    every = silhouette_quality(fg_dense, fg.cameras, fg.masks)
    out["sil_F_all"] = every.fscore if every.fscore is not None else np.nan
    area = sum(int(np.count_nonzero(m)) for m in fg.masks if m is not None)
    out["density"] = min(1.0, len(fg_dense) / area / golden_density) if area else 0.0
    if len(golden_sparse) == 0:
        return {**out, "sparse_F": np.nan, "coverage": np.nan, "dense_F": np.nan}
    out["sparse_F"] = (
        evaluate_clouds(fg_sparse, golden_sparse, d)[0].fscore if len(fg_sparse) else 0.0
    )
    if len(fg_dense) == 0:
        out["coverage"] = out["dense_F"] = 0.0
        return out
    dist_ref, _ = cKDTree(fg_dense).query(golden_sparse, k=1)
    coverage = float(np.mean(dist_ref <= d))
    dist_cand, _ = cKDTree(golden_sparse).query(fg_dense, k=1, distance_upper_bound=3 * d)
    precision = float(np.mean(dist_cand <= 3 * d))
    out["coverage"] = coverage
    out["dense_F"] = (
        2 * precision * coverage / (precision + coverage) if precision + coverage else 0.0
    )
    return out


def foreground_task(
    frames: FrameSet,
    rig: Rig,
    fg: ForegroundResult,
    rc: RuntimeConfig,
    scale: float,
    ids: tuple[int, ...],
) -> tuple[SparseReconstruction, ForegroundReconstruction]:
    """The front-end's task for one configuration (``pipeline.reconstruct_task`` with the
    online system's ``task_configs``: r > 1 finer than golden), with the SfM of the
    foreground crops that the paper's sparse estimate needs (the hull bounds the depth
    search either way: the same foreground cloud as the online system's "hull" scope)."""
    cfg, split = rc.task_configs(scale, rig, ids)
    rec = reconstruct_task(
        frames,
        rig,
        fg,
        cfg,
        background=PointCloud.empty(),
        split_config=split,
        sparse_scope="foreground",
    )
    return rec.sparse, rec.foreground


def visited_configs(run_dir: Path, step: float = 0.05) -> list[tuple[float, tuple[int, ...]]]:
    """The distinct configurations (r to the nearest ``step``, camera ids) of a run's
    finished tasks, in the order the controller first ran them (the workload scaling moves r
    a little task by task: r within a step of each other is one configuration here)."""
    folder = RunFolder(run_dir)
    folder.poll()
    seen: dict[tuple[float, tuple[int, ...]], None] = {}
    for m in folder.tasks:
        if m.status == "ok" and m.scale > 0 and m.camera_ids:
            r = round(round(m.scale / step) * step, 4) or step
            seen.setdefault((r, tuple(sorted(m.camera_ids))), None)
    if not seen:
        raise SystemExit(f"{run_dir}: no finished task to take configurations from")
    return list(seen)


def run(args: argparse.Namespace) -> dict[str, Any]:
    ds = open_dataset(args.dataset)
    rig = ds.rig
    rc = RuntimeConfig(deadline_s=1.0)
    d_online = rc.eval_threshold_for(rig)
    dist = median_camera_distance(rig)
    offline_d = [0.01 * dist, 0.02 * dist]
    gt = None
    if ds.ground_truth is not None:
        from edgerecon.synth import GroundTruth

        gt = GroundTruth.open(ds.root)
    warm_up()
    rows: list[dict[str, Any]] = []
    for t in args.times:
        tracker = dataset_scene_at(ds, t, rc.foreground)
        with ds.open_frames() as src:
            frames = src.read(t)
        fg = tracker.segment(frames)

        all_ids = tuple(range(len(rig)))
        golden_sparse, golden = foreground_task(frames, rig, fg, rc, 1.0, all_ids)
        area = sum(int(np.count_nonzero(m)) for m in fg.masks if m is not None)
        golden_density = len(golden.cloud) / max(area, 1)
        ref_sparse = golden.fg_sparse.points3D
        if gt is not None:
            reference: PointCloud | np.ndarray = gt.reference_cloud(t, "foreground", min_views=2)
            ref_name = "truth"
        else:
            reference = golden.cloud
            ref_name = "golden dense"
        ref_pts = reference.points3D if isinstance(reference, PointCloud) else reference
        # Without the actors seated and still from the first frame (in no mask: no estimate
        # made from the masks sees them, and the offline F against all the truth drops by
        # their share whatever the configuration).
        moving_pts = None
        if gt is not None and gt.seated_from_start and isinstance(reference, PointCloud):
            if reference.labels is not None:
                moving_pts = reference.points3D[~np.isin(reference.labels, gt.seated_from_start)]
        if args.configs_from is not None:
            configs = visited_configs(args.configs_from, args.config_step)
        else:
            mapping = camera_mapping(
                golden_sparse.visibility_matrix(len(rig)),
                camera_centers=rig.centers,
                viewing_directions=np.array([c.viewing_direction for c in rig]),
                sizes=range(len(rig), MIN_CAMERAS - 1, -1),
            )
            subsets = [tuple(mapping(n)) for n in sorted(mapping.selections, reverse=True)]
            if args.max_subsets:
                subsets = subsets[: args.max_subsets]
            limit = fine_scale_limit(rig, rc.dense, rc.split)
            scales = [r for r in args.scales if 0 < r <= limit]
            configs = list(itertools.product(scales, subsets))
        for scale, ids in configs:
            if scale == 1.0 and ids == all_ids:
                rec = golden
            else:
                _, rec = foreground_task(frames, rig, fg, rc, scale, ids)
            est = estimates(
                rec.fg_sparse.points3D,
                rec.cloud.points3D,
                ref_sparse,
                d_online,
                fg,
                golden_density,
            )
            off = [
                evaluate_clouds(rec.cloud.points3D, ref_pts, dd)[0].fscore
                if len(rec.cloud) and len(ref_pts)
                else 0.0
                for dd in offline_d
            ]
            moving = (
                [
                    evaluate_clouds(rec.cloud.points3D, moving_pts, dd)[0].fscore
                    if len(rec.cloud) and len(moving_pts)
                    else 0.0
                    for dd in offline_d
                ]
                if moving_pts is not None
                else None
            )
            row = {
                "time": t,
                "r": scale,
                "cameras": ",".join(map(str, ids)),
                "fg_sparse": len(rec.fg_sparse),
                "golden_sparse": len(ref_sparse),
                "fg_dense": len(rec.cloud),
                **{k: round(v, 4) for k, v in est.items()},
                "offline_F1%": round(off[0], 4),
                "offline_F2%": round(off[1], 4),
            }
            if moving is not None:
                row["moving_F1%"] = round(moving[0], 4)
                row["moving_F2%"] = round(moving[1], 4)
            rows.append(row)
            print_rows(f"t={t}", list(row), [row])
    corr = []
    for name in ESTIMATES:
        keys = ["offline_F1%", "offline_F2%"]
        if rows and "moving_F1%" in rows[0]:
            keys += ["moving_F1%", "moving_F2%"]
        for key in keys:
            c = online_offline_correlation([r[name] for r in rows], [r[key] for r in rows])
            # Within each timestamp, across its configurations (what the controller
            # compares: the content is the same, only the configuration differs).
            within = [
                online_offline_correlation(
                    [r[name] for r in rows if r["time"] == t],
                    [r[key] for r in rows if r["time"] == t],
                ).pearson
                for t in args.times
            ]
            within = [p for p in within if np.isfinite(p)]
            corr.append(
                {
                    "estimate": name,
                    "offline": f"{key} vs {ref_name}",
                    "n": c.num_samples,
                    "pearson": round(c.pearson, 3),
                    "spearman": round(c.spearman, 3),
                    "pearson_within_time_mean": round(float(np.mean(within)), 3)
                    if within
                    else None,
                    "pearson_within_time_min": round(float(np.min(within)), 3) if within else None,
                }
            )
    print_rows(
        f"{ds.name}: online estimate vs offline foreground F (d online = {d_online:.4g} {rig.unit})",
        list(corr[0]),
        corr,
    )
    return {"dataset": str(ds.root), "d_online": d_online, "rows": rows, "correlation": corr}


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--dataset", required=True, help="dataset folder")
    ap.add_argument("--times", nargs="+", type=int, required=True, help="timestamps")
    ap.add_argument(
        "--scales",
        nargs="+",
        type=float,
        default=[2.0, 1.5, 1.0, 0.8, 0.6, 0.45, 0.3],
        help="image scales r (above 1: finer than golden, where the rig has finer; the "
        "scales above its limit are left out)",
    )
    ap.add_argument("--max-subsets", type=int, default=0, help="largest N' subsets only (0 = all)")
    ap.add_argument(
        "--configs-from",
        type=Path,
        default=None,
        metavar="RUN",
        help="the configurations a run folder's tasks ran, instead of --scales x subsets",
    )
    ap.add_argument(
        "--config-step",
        type=float,
        default=0.05,
        help="with --configs-from: r within this of each other is one configuration",
    )
    ap.add_argument("--json", type=Path, default=None, help="write a JSON report")
    args = ap.parse_args()
    out = run(args)
    if args.json:
        write_report(args.json, {**report_header(), **out})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
