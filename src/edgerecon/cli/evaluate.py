"""``edgerecon evaluate``: precision / recall / F-score of a cloud against a reference cloud
or against a synthetic scene's ground truth."""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from edgerecon.cli._common import add_json_flag, console, emit_json, print_table
from edgerecon.geometry.camera import Rig
from edgerecon.io.clouds import read_cloud_file
from edgerecon.io.crs import crs_name
from edgerecon.io.ply import read_ply, read_ply_meta
from edgerecon.quality.metrics import QualityScore, evaluate_against, evaluate_nested
from edgerecon.types import DataError, PointCloud

_COLUMNS = [
    "d",
    "precision",
    "recall",
    "F-score",
    "acc. mean",
    "acc. median",
    "compl. mean",
    "compl. median",
]

#: Default thresholds: shares of the median camera distance (the paper's scale).
DEFAULT_THRESHOLDS = ("1%", "2%")
#: Default distance cut-off, in multiples of the largest threshold.
CUTOFF_FACTOR = 2.0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "evaluate",
        help="score a point cloud against a reference cloud or synthetic ground truth",
        description="Precision, recall, F-score (at each threshold), accuracy and "
        "completeness of PRED against REF, or against the ground truth of a synthetic scene "
        "(--gt SCENE_DIR --time T): then against all ground-truth points and against those "
        "seen by at least --min-views cameras. Reads any PLY (list properties such as "
        "openMVS's 'views' are skipped).",
    )
    p.add_argument("pred", help="predicted cloud (PLY, LAS or LAZ)")
    p.add_argument(
        "ref",
        nargs="?",
        help="reference cloud (PLY, or LAS / LAZ such as a laser scan of the site, in "
        "metres: converted to PRED's unit); omit with --gt",
    )
    p.add_argument(
        "--threshold",
        "-d",
        nargs="+",
        default=None,
        metavar="D",
        help="distance threshold(s): a length in the clouds' unit, or N%% of the median camera "
        "distance (of --gt's or --dataset's rig; without a rig: of the reference's bounding-box "
        "diagonal). Default: 1%% 2%%",
    )
    p.add_argument(
        "--max-distance",
        type=float,
        default=None,
        metavar="X",
        help="exact nearest-neighbour distances up to X; beyond it, estimates (never below "
        "the truth, at most 0.44 X above; used only by the accuracy / completeness columns). "
        f"Default {CUTOFF_FACTOR:g} x the largest threshold",
    )
    p.add_argument("--gt", metavar="SCENE_DIR", help="synthetic dataset (or its gt/ folder)")
    p.add_argument(
        "--dataset", metavar="DIR", help="the dataset PRED comes from (its rig sets the scale)"
    )
    p.add_argument("--time", "-t", type=int, help="timestamp of PRED (needed for foreground)")
    p.add_argument(
        "--part",
        choices=["foreground", "background", "all"],
        default="foreground",
        help="which ground truth to compare with (default: foreground)",
    )
    p.add_argument(
        "--min-views",
        type=int,
        default=2,
        help="second reference: ground-truth points seen by at least this many cameras (default 2)",
    )
    p.add_argument(
        "--no-label-filter",
        action="store_true",
        help="with --gt and --part foreground/background, do not drop PRED points whose "
        "label says the other part (labels >= 1 are foreground, 0 background)",
    )
    p.add_argument(
        "--measured-only",
        action="store_true",
        help="score only PRED's measured points: drop those its 'inferred' property marks "
        "(ground-plane completion); a PLY without the property is all measured",
    )
    add_json_flag(p)
    p.set_defaults(func=run)


@dataclass(frozen=True)
class Thresholds:
    """The distance thresholds and cut-off of one evaluation, and how they were chosen."""

    values: list[float]
    max_distance: float
    scale: float | None
    """Length the relative thresholds are shares of (None: all given as lengths)."""
    scale_from: str
    """What ``scale`` is ("median camera distance of ...", "bounding-box diagonal ...")."""
    specs: list[str]

    def describe(self, unit: str | None) -> str:
        u = f" {unit}" if unit else ""
        vals = ", ".join(f"{v:.4g}" for v in self.values)
        text = f"thresholds d = {vals}{u}"
        if self.scale is not None and any(s.endswith("%") for s in self.specs):
            text += f" ({' and '.join(self.specs)} of the {self.scale_from}, {self.scale:.4g}{u})"
        return text + f"; exact distances up to {self.max_distance:.4g}{u}, estimated beyond"

    def to_dict(self) -> dict[str, Any]:
        return {
            "thresholds": self.values,
            "threshold_specs": self.specs,
            "scale": self.scale,
            "scale_from": self.scale_from,
            "max_distance": self.max_distance,
        }


def resolve_thresholds(
    specs: list[str] | None,
    rig: Rig | None,
    ref: PointCloud | None,
    max_distance: float | None,
    rig_name: str = "rig",
) -> Thresholds:
    """Turn ``-d`` values (lengths or ``N%``) into lengths; see ``register``'s help."""
    from edgerecon.runtime.config import median_camera_distance

    specs = list(specs) if specs else list(DEFAULT_THRESHOLDS)
    scale = None
    scale_from = ""
    if any(s.strip().endswith("%") for s in specs):
        if rig is not None:
            scale = median_camera_distance(rig)
            scale_from = f"median camera distance of the {rig_name}"
        elif ref is not None and len(ref):
            ext = ref.points3D.max(axis=0) - ref.points3D.min(axis=0)
            scale = float(np.linalg.norm(ext))
            scale_from = "reference's bounding-box diagonal (no rig: give --dataset)"
        if not scale:
            raise DataError("relative thresholds (N%) need a rig (--dataset) or a reference cloud")
    values = []
    for s in specs:
        text = s.strip()
        try:
            v = float(text[:-1]) / 100 * scale if text.endswith("%") else float(text)  # type: ignore[operator]
        except ValueError:
            raise DataError(f"-d expects lengths or percentages, got {s!r}") from None
        if not (v > 0 and math.isfinite(v)):
            raise DataError(f"thresholds must be positive, got {s!r}")
        values.append(v)
    cut = max_distance if max_distance is not None else CUTOFF_FACTOR * max(values)
    if not cut >= max(values):
        raise DataError(f"--max-distance {cut:g} is below the largest threshold {max(values):g}")
    return Thresholds(
        values=values, max_distance=cut, scale=scale, scale_from=scale_from, specs=specs
    )


def _rows(scores: list[QualityScore]) -> list[list[float]]:
    return [
        [
            s.threshold,
            s.precision,
            s.recall,
            s.fscore,
            s.accuracy_mean,
            s.accuracy_median,
            s.completeness_mean,
            s.completeness_median,
        ]
        for s in scores
    ]


def _dataset_rig(path: str | None) -> Rig | None:
    if path is None:
        return None
    from edgerecon.io.dataset import open_dataset

    return open_dataset(path).rig


def read_pred(path: str, measured_only: bool) -> tuple[PointCloud, dict[str, Any]]:
    """PRED, without its inferred points when ``measured_only``, and the counts: ``inferred``
    (points PRED marks inferred), ``measured_only`` and ``num_pred_read``."""
    return drop_inferred(read_ply(path), measured_only)


def drop_inferred(cloud: PointCloud, measured_only: bool) -> tuple[PointCloud, dict[str, Any]]:
    """``cloud`` without its inferred points when ``measured_only``, and the counts."""
    info = {
        "num_pred_read": len(cloud),
        "inferred": cloud.num_inferred,
        "measured_only": bool(measured_only),
    }
    if measured_only and info["inferred"]:
        cloud = cloud.select(~cloud.inferred)
    return cloud, info


def _inferred_note(info: dict[str, Any]) -> str:
    n, k = info["num_pred_read"], info["inferred"]
    share = f" ({100.0 * k / n:.1f} %)" if n else ""
    if info["measured_only"]:
        return f"PRED: {k:,} of {n:,} points inferred{share}, left out (--measured-only)"
    return f"PRED: {k:,} of {n:,} points inferred{share}, scored with the measured ones"


def run(args: argparse.Namespace) -> int:
    if args.gt is not None:
        return _run_gt(args)
    if args.ref is None:
        raise DataError("give a reference cloud REF or a synthetic scene with --gt SCENE_DIR")
    t0 = time.perf_counter()
    pred_file, ref_file = read_cloud_file(args.pred), read_cloud_file(args.ref)
    # A scan in another coordinate reference system than PRED's: moved into PRED's.
    reprojected = None
    moved = ref_file.reprojected(pred_file.crs)
    if moved is not ref_file:
        reprojected = f"{crs_name(ref_file.crs)} -> {crs_name(pred_file.crs)}"
        ref_file = moved
    pred, inferred = drop_inferred(pred_file.cloud, args.measured_only)
    # REF in PRED's unit (a LAS scan is in metres, a rig's PLY may be in millimetres).
    unit = pred_file.unit or ref_file.unit
    ref, ref_origin = ref_file.world(unit)
    converted = ref_file.unit if ref_file.unit and ref_file.unit != unit else None
    # Clouds of a localised rig are read relative to their origin (io.ply): PRED into REF's.
    shift = np.subtract(pred_file.origin or (0.0, 0.0, 0.0), ref_origin)
    if shift.any():
        pred = dataclasses.replace(pred, points3D=pred.points3D + shift)
    th = resolve_thresholds(args.threshold, _dataset_rig(args.dataset), ref, args.max_distance)
    [scores] = evaluate_against(pred, [ref], th.values, max_distance=th.max_distance)
    seconds = time.perf_counter() - t0
    if args.json:
        emit_json(
            {
                "pred": args.pred,
                "ref": args.ref,
                "unit": unit,
                "ref_converted_from": converted,
                "ref_reprojected": reprojected,
                **th.to_dict(),
                "seconds": round(seconds, 3),
                "num_pred": len(pred),
                **inferred,
                "scores": [s.to_dict() for s in scores],
            }
        )
        return 0
    print_table(
        f"{args.pred} vs {args.ref} ({len(pred):,} vs {len(ref):,} points)",
        _COLUMNS,
        _rows(scores),
    )
    console.print(_inferred_note(inferred), soft_wrap=True)
    if reprojected:
        console.print(f"REF reprojected: {reprojected}", soft_wrap=True)
    if converted:
        console.print(f"REF converted from {converted} to {unit}", soft_wrap=True)
    console.print(f"{th.describe(unit)}; {seconds:.1f} s", soft_wrap=True)
    return 0


def select_part(cloud: PointCloud, part: str) -> PointCloud:
    """The points of ``cloud`` whose labels say ``part`` (all points if it has no labels)."""
    if cloud.labels is None or part == "all":
        return cloud
    keep = cloud.labels >= 1 if part == "foreground" else cloud.labels == 0
    return cloud.select(np.asarray(keep))


def crop_near(cloud: PointCloud, ref: PointCloud, distance: float) -> PointCloud:
    """The points of ``cloud`` within ``distance`` of ``ref`` (an unlabelled cloud scored
    against one part of a scene keeps only what lies near that part)."""
    from edgerecon.quality.metrics import nearest_distances

    if len(ref) == 0:
        return cloud.select(np.zeros(len(cloud), bool))
    d = nearest_distances(cloud, ref, max_distance=distance, estimate_far=False)
    return cloud.select(d <= distance)


def _run_gt(args: argparse.Namespace) -> int:
    from edgerecon.synth.groundtruth import GroundTruth

    if args.ref is not None:
        raise DataError("give either a reference cloud REF or --gt SCENE_DIR, not both")
    if args.min_views < 1:
        raise DataError(f"--min-views must be >= 1, got {args.min_views}")
    t0 = time.perf_counter()
    gt = GroundTruth.open(args.gt)
    if args.part != "background" and args.time is None:
        raise DataError(f"--part {args.part} needs --time T (0..{gt.num_frames - 1})")
    pred_all, inferred = read_pred(args.pred, args.measured_only)
    origin = read_ply_meta(args.pred).origin  # the truth is in world coordinates
    if origin is not None:
        pred_all = dataclasses.replace(pred_all, points3D=pred_all.points3D + np.asarray(origin))
    th = resolve_thresholds(args.threshold, gt.rig, None, args.max_distance, "ground truth's rig")
    ref_all = gt.reference_cloud(args.time, part=args.part, min_views=1)
    seen = np.asarray(ref_all.attributes["num_views"]) >= args.min_views
    ref_seen = ref_all.select(seen)
    note = ""
    if args.no_label_filter or args.part == "all":
        pred = pred_all
    elif pred_all.labels is not None:
        pred = select_part(pred_all, args.part)
    else:
        # No labels: keep the points near the part's ground truth (a crop volume).
        pred = crop_near(pred_all, ref_all, th.max_distance)
        note = (
            f"PRED has no labels: scored its {len(pred):,} points within "
            f"{th.max_distance:.4g} of the ground-truth {args.part}"
        )
    scores_all, scores_seen = evaluate_nested(
        pred, ref_all, [seen], th.values, max_distance=th.max_distance
    )
    seconds = time.perf_counter() - t0
    unit = gt.rig.unit
    if args.json:
        emit_json(
            {
                "pred": args.pred,
                "gt": args.gt,
                "time": args.time,
                "part": args.part,
                "unit": unit,
                **th.to_dict(),
                "num_pred": len(pred),
                "num_pred_total": len(pred_all),
                **inferred,
                "pred_selection": "labels"
                if pred_all.labels is not None and not args.no_label_filter
                else ("crop" if note else "all"),
                "min_views": args.min_views,
                "seconds": round(seconds, 3),
                "scores": [s.to_dict() for s in scores_all],
                "scores_min_views": [s.to_dict() for s in scores_seen],
            }
        )
        return 0
    when = "" if args.time is None else f" at t={args.time}"
    print_table(
        f"{args.pred} ({len(pred):,} of {len(pred_all):,} points) vs ground-truth {args.part}"
        f"{when}: all {len(ref_all):,} visible points",
        _COLUMNS,
        _rows(scores_all),
    )
    print_table(
        f"vs the {len(ref_seen):,} ground-truth points seen by >= {args.min_views} cameras",
        _COLUMNS,
        _rows(scores_seen),
    )
    if note:
        console.print(note, soft_wrap=True)
    console.print(_inferred_note(inferred), soft_wrap=True)
    console.print(f"{th.describe(unit)}; {seconds:.1f} s", soft_wrap=True)
    return 0
