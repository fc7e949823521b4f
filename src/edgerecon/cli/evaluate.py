"""``edgerecon evaluate``: precision / recall / F-score of a cloud against a reference cloud
or against a synthetic scene's ground truth."""

from __future__ import annotations

import argparse

import numpy as np

from edgerecon.cli._common import add_json_flag, emit_json, print_table
from edgerecon.io.ply import read_ply
from edgerecon.quality import evaluate_clouds
from edgerecon.quality.metrics import QualityScore
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


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "evaluate",
        help="score a point cloud against a reference cloud or synthetic ground truth",
        description="Precision, recall, F-score (at each threshold), accuracy and "
        "completeness of PRED against REF, or against the ground truth of a synthetic scene "
        "(--gt SCENE_DIR --time T): then against all ground-truth points and against those "
        "seen by at least --min-views cameras.",
    )
    p.add_argument("pred", help="predicted cloud (PLY)")
    p.add_argument("ref", nargs="?", help="reference cloud (PLY); omit with --gt")
    p.add_argument(
        "--threshold",
        "-d",
        type=float,
        nargs="+",
        default=[0.01, 0.02],
        help="distance threshold(s) d in the clouds' unit (default: 0.01 0.02)",
    )
    p.add_argument("--gt", metavar="SCENE_DIR", help="synthetic dataset (or its gt/ folder)")
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
    add_json_flag(p)
    p.set_defaults(func=run)


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


def run(args: argparse.Namespace) -> int:
    if args.gt is not None:
        return _run_gt(args)
    if args.ref is None:
        raise DataError("give a reference cloud REF or a synthetic scene with --gt SCENE_DIR")
    pred = read_ply(args.pred)
    ref = read_ply(args.ref)
    scores = evaluate_clouds(pred, ref, args.threshold)
    if args.json:
        emit_json({"pred": args.pred, "ref": args.ref, "scores": [s.to_dict() for s in scores]})
        return 0
    print_table(
        f"{args.pred} vs {args.ref} ({len(pred):,} vs {len(ref):,} points)",
        _COLUMNS,
        _rows(scores),
    )
    return 0


def select_part(cloud: PointCloud, part: str) -> PointCloud:
    """The points of ``cloud`` whose labels say ``part`` (all points if it has no labels)."""
    if cloud.labels is None or part == "all":
        return cloud
    keep = cloud.labels >= 1 if part == "foreground" else cloud.labels == 0
    return cloud.select(np.asarray(keep))


def _run_gt(args: argparse.Namespace) -> int:
    from edgerecon.synth.groundtruth import GroundTruth

    if args.ref is not None:
        raise DataError("give either a reference cloud REF or --gt SCENE_DIR, not both")
    if args.min_views < 1:
        raise DataError(f"--min-views must be >= 1, got {args.min_views}")
    gt = GroundTruth.open(args.gt)
    if args.part != "background" and args.time is None:
        raise DataError(f"--part {args.part} needs --time T (0..{gt.num_frames - 1})")
    pred_all = read_ply(args.pred)
    pred = pred_all if args.no_label_filter else select_part(pred_all, args.part)
    ref_all = gt.reference_cloud(args.time, part=args.part, min_views=1)
    ref_seen = gt.reference_cloud(args.time, part=args.part, min_views=args.min_views)
    scores_all = evaluate_clouds(pred, ref_all, args.threshold)
    scores_seen = evaluate_clouds(pred, ref_seen, args.threshold)
    if args.json:
        emit_json(
            {
                "pred": args.pred,
                "gt": args.gt,
                "time": args.time,
                "part": args.part,
                "num_pred": len(pred),
                "num_pred_total": len(pred_all),
                "min_views": args.min_views,
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
    return 0
