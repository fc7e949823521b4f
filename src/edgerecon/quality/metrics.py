"""Point-cloud quality: precision, recall and F-score at a distance threshold, accuracy and
completeness (the paper's metric, after Knapitsch et al.'s Tanks and Temples benchmark).

* precision(d) = share of predicted points within ``d`` of the reference,
* recall(d)    = share of reference points within ``d`` of the prediction,
* F(d)         = 2 P R / (P + R), defined as 0 when P + R = 0,
* accuracy     = mean / median distance from predicted points to the reference,
* completeness = mean / median distance from reference points to the prediction.

Empty clouds have a defined answer: an empty prediction has precision 1 (it claims nothing
wrong), recall 0 and F 0; an empty reference has recall 1, precision 0 and F 0; both empty give
P = R = F = 1. Distances involving an empty cloud are ``inf`` (``None`` in JSON).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from edgerecon.types import PointCloud, Points3D


@dataclass(frozen=True, kw_only=True)
class QualityScore:
    """Scores of one prediction against one reference at one threshold."""

    threshold: float
    """Distance threshold d, in the clouds' unit."""
    precision: float
    recall: float
    fscore: float
    accuracy_mean: float
    """Mean distance from predicted points to the reference."""
    accuracy_median: float
    completeness_mean: float
    """Mean distance from reference points to the prediction."""
    completeness_median: float
    num_pred: int
    num_ref: int

    def to_dict(self) -> dict[str, float | int | None]:
        return {
            k: (None if isinstance(v, float) and not math.isfinite(v) else v)
            for k, v in asdict(self).items()
        }


def _as_points(cloud: PointCloud | Points3D) -> NDArray[np.float64]:
    pts = cloud.points3D if isinstance(cloud, PointCloud) else np.asarray(cloud, np.float64)
    pts = pts.reshape(-1, 3)
    if not np.all(np.isfinite(pts)):
        raise ValueError("point cloud contains NaN or infinite coordinates")
    return pts


def nearest_distances(
    query: PointCloud | Points3D, reference: PointCloud | Points3D, workers: int = -1
) -> NDArray[np.float64]:
    """(len(query),) distance of each query point to its nearest reference point
    (``inf`` when the reference is empty)."""
    q, r = _as_points(query), _as_points(reference)
    if len(q) == 0:
        return np.zeros(0)
    if len(r) == 0:
        return np.full(len(q), np.inf)
    d, _ = cKDTree(r).query(q, k=1, workers=workers)
    return np.asarray(d, dtype=np.float64)


def evaluate_clouds(
    pred: PointCloud | Points3D,
    ref: PointCloud | Points3D,
    thresholds: float | Sequence[float],
) -> list[QualityScore]:
    """Score ``pred`` against ``ref`` at each threshold (one KD-tree query per direction)."""
    ths = (
        [float(thresholds)]
        if isinstance(thresholds, int | float | np.number)
        else [float(t) for t in thresholds]
    )
    for th in ths:
        if not (th > 0 and math.isfinite(th)):
            raise ValueError(f"threshold must be a positive number, got {th!r}")
    p, r = _as_points(pred), _as_points(ref)
    d_pr = nearest_distances(p, r)
    d_rp = nearest_distances(r, p)

    def stat(d: NDArray[np.float64], fn: str) -> float:
        if len(d) == 0:
            return math.inf
        return float(np.mean(d) if fn == "mean" else np.median(d))

    scores = []
    for th in ths:
        if len(p) == 0 and len(r) == 0:
            precision, recall, f = 1.0, 1.0, 1.0
        elif len(p) == 0:
            precision, recall, f = 1.0, 0.0, 0.0
        elif len(r) == 0:
            precision, recall, f = 0.0, 1.0, 0.0
        else:
            precision = float(np.count_nonzero(d_pr <= th)) / len(p)
            recall = float(np.count_nonzero(d_rp <= th)) / len(r)
            f = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
        scores.append(
            QualityScore(
                threshold=th,
                precision=precision,
                recall=recall,
                fscore=f,
                accuracy_mean=stat(d_pr, "mean"),
                accuracy_median=stat(d_pr, "median"),
                completeness_mean=stat(d_rp, "mean"),
                completeness_median=stat(d_rp, "median"),
                num_pred=len(p),
                num_ref=len(r),
            )
        )
    return scores


def fscore(pred: PointCloud | Points3D, ref: PointCloud | Points3D, threshold: float) -> float:
    """F-score at one threshold (see module docstring for empty clouds)."""
    return evaluate_clouds(pred, ref, threshold)[0].fscore
