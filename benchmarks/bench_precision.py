"""Dense precision filters (issue 13): precision / recall / F-score and CPU seconds of the
golden dense stage with each filter of ``dense.filters`` on, A/B in one process against the
defaults, on synthetic scenes with ground truth.

    python benchmarks/bench_precision.py                        # arc7 t=20, demo t=20, object
    python benchmarks/bench_precision.py --scenes demo --variants base edge
    python benchmarks/bench_precision.py --data /tmp/h13        # where the scenes are written
    python benchmarks/bench_precision.py --scenes arc7 --variants default --breakdown

The scenes are written once under ``--data`` (``edgerecon synth`` presets, 21 frames; object
3). The sparse stage runs once per scene (its CPU seconds are added to every row); each
variant then runs the dense stage and is scored against every visible ground-truth point
(``evaluate --gt --part all``, min views 1) at 1 / 2 / 5 cm (object: 0.1 % of the median
camera distance, 2 and 5 mm, both clouds cropped to the object and the table within
``OBJECT_RADIUS_M`` of it: the table's far reaches are not what small-object capture is
measured on). CPU seconds: the least of ``--repeat`` runs. "mean/med" is the mean / median accuracy (predicted point to
truth) over all points; "CPU s" is process CPU time of sparse + dense (all threads).

``--breakdown`` adds, per variant, the precision at the first threshold by the fused points'
``num_views`` and that of the depth maps' own points before fusion (every 10th kept pixel of
every view): fusion keeps one point per voxel, so it weighs a surface by its area, not by
how many views measured it, and the few-view regions weigh more in the fused cloud.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from _report import report_header
from edgerecon.config import ReconstructionConfig
from edgerecon.dense import DenseConfig, DenseReconstruction, reconstruct_dense
from edgerecon.dense.fusion import camera_points
from edgerecon.io.dataset import open_dataset
from edgerecon.pipeline import prepare_task_views
from edgerecon.quality.metrics import evaluate_against
from edgerecon.runtime.config import median_camera_distance
from edgerecon.sparse import reconstruct_sparse
from edgerecon.synth import GroundTruth, preset_config, write_dataset

SCENES = {"arc7": ("arc7", 20, 21), "demo": ("demo", 20, 21), "object": ("object", 0, 3)}

VARIANTS: dict[str, dict[str, object]] = {
    "before": {"max_conflict_share": 1.0, "depth_edge_rel": 0.0},
    "default": {},
    "share0.5": {"consistent_view_share": 0.5},
    "conflict0.3": {"max_conflict_share": 0.3},
    "weakncc0.6": {"min_weak_ncc": 0.6},
    "edge0.02": {"depth_edge_rel": 0.02},
    "grazing80": {"max_grazing_deg": 80.0},
    "outlier8": {"outlier_k": 8, "outlier_std": 2.0},
    "mcv2": {"min_consistent_views": 2},
    "px2": {"consistency_px": 2.0},
    "px2topk2": {"consistency_px": 2.0, "ncc_top_k": 2},
    "noise": {"noise_adaptive_ncc": True},
    "vertical": {"sweep_families": ("fronto", "ground", "vertical")},
    "strict": {
        "consistent_view_share": 0.5,
        "max_conflict_share": 0.3,
        "depth_edge_rel": 0.02,
        "min_weak_ncc": 0.7,
    },
}
"""Each variant: DenseConfig overrides on top of the defaults ("before" = the defaults
before issue 13: no free-space test, no depth-edge test)."""

#: The object preset is scored in a cylinder around its target (radius, metres), from 5 mm
#: below the table top (6 cm under the target) up: the object and the support around it.
OBJECT_RADIUS_M = 0.12


def scene(data: Path, name: str) -> tuple[Path, int]:
    preset, t, frames = SCENES[name]
    path = data / name
    if not (path / "gt" / "scene.json").exists():
        write_dataset(preset_config(preset, num_frames=frames), path, overwrite=True)
    return path, t


def breakdown(
    dense: DenseReconstruction,
    cloud_points: np.ndarray,
    num_views: np.ndarray,
    ref: np.ndarray,
    threshold: float,
    region: Callable[[np.ndarray], np.ndarray] | None = None,
) -> str:
    """Precision at ``threshold`` by the fused points' number of views, and of the depth
    maps' points before fusion (see the module docstring)."""
    tree = cKDTree(ref)
    d, _ = tree.query(cloud_points, distance_upper_bound=2 * threshold, workers=-1)
    parts = []
    for lo, hi in ((1, 2), (3, 3), (4, 4), (5, 5), (6, 10**6)):
        sel = (num_views >= lo) & (num_views <= hi)
        if sel.any():
            label = f"{lo}" if lo == hi else (f"{lo}+" if hi > 100 else f"<={hi}")
            parts.append(f"{label} views {sel.mean():.2f} P {np.mean(d[sel] < threshold):.3f}")
    pts = []
    for i, depth in dense.depth_maps.items():
        cam = dense.depth_cameras[i]
        X = camera_points(cam, depth).reshape(-1, 3)[(depth > 0).ravel()][::10]
        pts.append((X.astype(np.float64) - cam.t) @ cam.R)  # camera -> world
    if pts:
        X = np.concatenate(pts)
        if region is not None:
            X = X[region(X)]
        dm, _ = tree.query(X, distance_upper_bound=2 * threshold, workers=-1)
        parts.append(f"depth maps before fusion P {np.mean(dm < threshold):.3f}")
    return "; ".join(parts)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS))
    parser.add_argument("--data", default="/tmp/bench_precision")
    parser.add_argument("--repeat", type=int, default=2, help="runs per variant (least CPU)")
    parser.add_argument(
        "--breakdown", action="store_true", help="precision by views and before fusion"
    )
    args = parser.parse_args()
    variants = {}
    for v in args.variants:
        if v in VARIANTS:
            variants[v] = VARIANTS[v]
        else:  # "name=field:value,field:value"
            label, _, spec = v.partition("=")
            variants[label] = {
                k: float(x) if "." in x else int(x)
                for k, x in (kv.split(":") for kv in spec.split(","))
            }
    head = report_header()
    print(f"commit {head['commit']}  {head['date']}  load {os.getloadavg()}", flush=True)
    for name in args.scenes:
        path, t = scene(Path(args.data), name)
        ds = open_dataset(path)
        gt = GroundTruth.open(path)
        ref = gt.reference_cloud(t, part="all", min_views=1)
        region = None
        if name == "object":
            target = np.asarray(gt.meta["config"]["rig"]["target"], float)

            def region(P: np.ndarray, target: np.ndarray = target) -> np.ndarray:
                near = np.linalg.norm(P[:, :2] - target[:2], axis=1) < OBJECT_RADIUS_M
                return near & (P[:, 2] > target[2] - 0.065)

            ref = ref.select(region(ref.points3D))
        dist = median_camera_distance(gt.rig)
        if name == "object":
            ths = [0.001 * dist, 0.002, 0.005]
            th_names = ["0.1%", "2mm", "5mm"]
        else:
            ths, th_names = [0.01, 0.02, 0.05], ["1cm", "2cm", "5cm"]
        with ds.open_frames() as source:
            frames = source.read(t)
        config = ReconstructionConfig()
        views = prepare_task_views(frames, ds.rig, config)
        c0 = time.process_time()
        sparse = reconstruct_sparse(views, config.sparse_config)
        sparse_cpu = time.process_time() - c0
        reconstruct_dense(views, DenseConfig(), sparse, up=ds.rig.up)  # warm-up (numba)
        cols = "  ".join(f"P/R/F@{n:>4}" for n in th_names)
        print(
            f"\n{name} t={t} ({len(ref):,} truth points, {len(sparse)} sparse points, "
            f"sparse {sparse_cpu:.1f} CPU s)  load {os.getloadavg()[0]:.2f}"
        )
        print(f"{'variant':14s} {'points':>9s}  {cols}  mean/med  CPU s", flush=True)
        for label, over in variants.items():
            dense_config = dataclasses.replace(DenseConfig(), **over)
            cpus = []
            for _ in range(args.repeat):
                c0 = time.process_time()
                dense = reconstruct_dense(views, dense_config, sparse, up=ds.rig.up)
                cpus.append(time.process_time() - c0)
            cpu = min(cpus) + sparse_cpu
            cloud = dense.cloud
            if region is not None:
                cloud = cloud.select(region(cloud.points3D))
            [scores] = evaluate_against(cloud, [ref], ths, max_distance=2 * max(ths))
            prf = "  ".join(f"{s.precision:.3f}/{s.recall:.3f}/{s.fscore:.3f}" for s in scores)
            ratio = scores[0].accuracy_mean / max(scores[0].accuracy_median, 1e-12)
            print(f"{label:14s} {len(cloud):9,d}  {prf}  {ratio:8.2f}  {cpu:5.1f}",
                  flush=True)  # fmt: skip
            if args.breakdown:
                views_of = cloud.attributes["num_views"]
                print(
                    "    "
                    + breakdown(dense, cloud.points3D, views_of, ref.points3D, ths[0], region)
                )


if __name__ == "__main__":
    main()
