"""``edgerecon evaluate``: precision / recall / F-score of a cloud against a reference."""

from __future__ import annotations

import argparse

from edgerecon.cli._common import add_json_flag, emit_json, print_table
from edgerecon.io.ply import read_ply
from edgerecon.quality import evaluate_clouds


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser(
        "evaluate",
        help="score a point cloud against a reference cloud",
        description="Precision, recall, F-score (at each threshold), accuracy and "
        "completeness of PRED against REF.",
    )
    p.add_argument("pred", help="predicted cloud (PLY)")
    p.add_argument("ref", help="reference cloud (PLY)")
    p.add_argument(
        "--threshold",
        "-d",
        type=float,
        nargs="+",
        default=[0.01, 0.02],
        help="distance threshold(s) d in the clouds' unit (default: 0.01 0.02)",
    )
    add_json_flag(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    pred = read_ply(args.pred)
    ref = read_ply(args.ref)
    scores = evaluate_clouds(pred, ref, args.threshold)
    if args.json:
        emit_json({"pred": args.pred, "ref": args.ref, "scores": [s.to_dict() for s in scores]})
        return 0
    print_table(
        f"{args.pred} vs {args.ref} ({len(pred):,} vs {len(ref):,} points)",
        [
            "d",
            "precision",
            "recall",
            "F-score",
            "acc. mean",
            "acc. median",
            "compl. mean",
            "compl. median",
        ],
        [
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
        ],
    )
    return 0
