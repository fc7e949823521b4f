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
  share of mask pixels within a pixel of a point (recall), share of points in the masks
  (precision);
* ``density``   — dense foreground points per foreground mask pixel, relative to the golden
  task's (capped at 1).

Prints the samples and, per estimate, Pearson / Spearman correlation with the offline score.

    python benchmarks/bench_online_quality.py --dataset DIR --times 60 90 120
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path
from typing import Any

import numpy as np

from _report import print_rows, report_header, write_report
from edgerecon.config import MIN_CAMERAS, ReconstructionConfig
from edgerecon.geometry.camera import Rig
from edgerecon.io.dataset import open_dataset
from edgerecon.optimize.selection import camera_mapping
from edgerecon.pipeline import (
    ForegroundReconstruction,
    foreground_views,
    prepare_task_views,
    reconstruct_foreground,
    warm_up,
)
from edgerecon.quality.metrics import evaluate_clouds
from edgerecon.quality.online import online_offline_correlation, silhouette_quality
from edgerecon.runtime.config import RuntimeConfig, median_camera_distance
from edgerecon.scene.foreground import ForegroundResult
from edgerecon.scene.stream import dataset_scene_at
from edgerecon.sparse import SparseReconstruction, reconstruct_sparse
from edgerecon.types import FrameSet, PointCloud

ESTIMATES = ("sparse_F", "coverage", "dense_F", "sil_recall", "sil_F", "density")


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
    sil = silhouette_quality(fg_dense, fg.cameras, fg.masks)
    out["sil_recall"] = sil.recall if sil.recall is not None else np.nan
    out["sil_F"] = sil.fscore if sil.fscore is not None else np.nan
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
    """The front-end's critical path for one configuration: SfM of the foreground crops,
    split, foreground MVS."""
    cfg = ReconstructionConfig(scale=scale, camera_ids=ids, sparse_config=rc.sparse)
    views = prepare_task_views(frames, rig, cfg)
    sparse = reconstruct_sparse(
        foreground_views(views, rig, fg.masks, rc.split.fg_mask_dilation_px), rc.sparse
    )
    return sparse, reconstruct_foreground(views, rig, sparse, fg, rc.dense, rc.split)


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
        mapping = camera_mapping(
            golden_sparse.visibility_matrix(len(rig)),
            camera_centers=rig.centers,
            viewing_directions=np.array([c.viewing_direction for c in rig]),
            sizes=range(len(rig), MIN_CAMERAS - 1, -1),
        )
        subsets = [tuple(mapping(n)) for n in sorted(mapping.selections, reverse=True)]
        if args.max_subsets:
            subsets = subsets[: args.max_subsets]
        for scale, ids in itertools.product(args.scales, subsets):
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
            rows.append(row)
            print_rows(f"t={t}", list(row), [row])
    corr = []
    for name in ESTIMATES:
        for key in ("offline_F1%", "offline_F2%"):
            c = online_offline_correlation([r[name] for r in rows], [r[key] for r in rows])
            corr.append(
                {
                    "estimate": name,
                    "offline": f"{key} vs {ref_name}",
                    "n": c.num_samples,
                    "pearson": round(c.pearson, 3),
                    "spearman": round(c.spearman, 3),
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
    ap.add_argument("--scales", nargs="+", type=float, default=[1.0, 0.8, 0.6, 0.45, 0.3])
    ap.add_argument("--max-subsets", type=int, default=0, help="largest N' subsets only (0 = all)")
    ap.add_argument("--json", type=Path, default=None, help="write a JSON report")
    args = ap.parse_args()
    out = run(args)
    if args.json:
        write_report(args.json, {**report_header(), **out})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
