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

**Distance cut-off** (``max_distance``): a KD-tree query far from the other cloud visits
every leaf within that distance (a point 1 m from a dense wall: hundreds of thousands), which
made a 10^6 x 10^6 evaluation take minutes. With a cut-off, distances up to it are exact (so
are precision and recall at thresholds up to it), and a point farther away gets its distance
to the other cloud thinned to one point per cube of a quarter of the cut-off: an estimate that
is never below the true distance and at most ``0.44 x max_distance`` above it
(``FAR_ERROR``), which keeps accuracy / completeness means meaningful with outliers metres away.
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
    max_distance: float | None = None
    """Distance cut-off: exact distances up to it, estimates beyond (see the module
    docstring); None = exact everywhere."""

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
    query: PointCloud | Points3D,
    reference: PointCloud | Points3D,
    workers: int = -1,
    max_distance: float | None = None,
    *,
    estimate_far: bool = True,
) -> NDArray[np.float64]:
    """(len(query),) distance of each query point to its nearest reference point (``inf``
    when the reference is empty). With ``max_distance``, exact up to it and estimated beyond
    (see the module docstring), or ``inf`` beyond with ``estimate_far=False``."""
    q, r = _as_points(query), _as_points(reference)
    if len(q) == 0:
        return np.zeros(0)
    if len(r) == 0:
        return np.full(len(q), np.inf)
    return _query(_Indexed(r) if estimate_far else _tree(r), q, workers, max_distance)


#: Beyond the cut-off, distances are estimated within this share of ``max_distance``.
FAR_ERROR = 0.25 * math.sqrt(3)


def _tree(points: NDArray[np.float64]) -> cKDTree:
    # Unbalanced trees without compacted nodes build 3x and query 3x faster on scan-like
    # clouds (1.3 M ground-truth points: 0.19 s + 0.7 s per 200k queries vs 0.54 + 2.4 s).
    return cKDTree(points, balanced_tree=False, compact_nodes=False)


class _Indexed:
    """A cloud with its KD-tree and, on demand, a thinned tree for far queries."""

    def __init__(self, points: NDArray[np.float64]) -> None:
        self.points = points
        self.tree = _tree(points)
        self._coarse: dict[float, cKDTree] = {}

    def coarse(self, voxel: float) -> cKDTree:
        if voxel not in self._coarse:
            key = np.floor(self.points / voxel).astype(np.int64)
            key -= key.min(axis=0)
            span = key.max(axis=0) + 1
            flat = (key[:, 0] * span[1] + key[:, 1]) * span[2] + key[:, 2]
            _, first = np.unique(flat, return_index=True)
            self._coarse[voxel] = _tree(self.points[first])
        return self._coarse[voxel]


def _spatial_order(q: NDArray[np.float64], cells: int = 128) -> NDArray[np.intp]:
    """An order of the points cell by cell of a ``cells``^3 grid over their extent: KD-tree
    queries in that order reuse the cache (1 M random-order queries against 1.4 M points:
    3.3 CPU-s; in this order 0.75 s plus 0.24 s for the sort)."""
    lo = q.min(axis=0)
    size = float((q.max(axis=0) - lo).max()) / cells or 1.0
    k = np.minimum(((q - lo) / size).astype(np.int32), cells - 1)
    return np.argsort((k[:, 0] * cells + k[:, 1]) * cells + k[:, 2])


def _query(
    ref: cKDTree | _Indexed,
    q: NDArray[np.float64],
    workers: int,
    max_distance: float | None,
) -> NDArray[np.float64]:
    return _query_idx(ref, q, workers, max_distance)[0]


def _query_idx(
    ref: cKDTree | _Indexed,
    q: NDArray[np.float64],
    workers: int,
    max_distance: float | None,
    *,
    sort: bool = True,
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Distances and nearest indices (-1 where the distance is an estimate or none)."""
    if sort and len(q) > 10_000:
        order = _spatial_order(q)
        d_out = np.empty(len(q))
        i_out = np.empty(len(q), np.int64)
        d_out[order], i_out[order] = _query_idx(ref, q[order], workers, max_distance, sort=False)
        return d_out, i_out
    tree = ref.tree if isinstance(ref, _Indexed) else ref
    bound = np.inf if max_distance is None else float(np.nextafter(max_distance, np.inf))
    d, idx = tree.query(q, k=1, workers=workers, distance_upper_bound=bound)
    d = np.asarray(d, dtype=np.float64)
    idx = np.asarray(idx, dtype=np.int64)
    far = ~np.isfinite(d)
    idx[far] = -1
    if max_distance is not None and far.any() and isinstance(ref, _Indexed):
        coarse = ref.coarse(0.25 * max_distance)
        est, _ = coarse.query(q[far], k=1, workers=workers)
        d[far] = np.maximum(est, max_distance)
    return d, idx


def _thresholds(thresholds: float | Sequence[float]) -> list[float]:
    ths = (
        [float(thresholds)]
        if isinstance(thresholds, int | float | np.number)
        else [float(t) for t in thresholds]
    )
    for th in ths:
        if not (th > 0 and math.isfinite(th)):
            raise ValueError(f"threshold must be a positive number, got {th!r}")
    return ths


def evaluate_clouds(
    pred: PointCloud | Points3D,
    ref: PointCloud | Points3D,
    thresholds: float | Sequence[float],
    *,
    max_distance: float | None = None,
) -> list[QualityScore]:
    """Score ``pred`` against ``ref`` at each threshold (one KD-tree query per direction).

    ``max_distance`` (>= every threshold) bounds the exact searches (see the module
    docstring)."""
    return evaluate_against(pred, [ref], thresholds, max_distance=max_distance)[0]


def evaluate_against(
    pred: PointCloud | Points3D,
    refs: Sequence[PointCloud | Points3D],
    thresholds: float | Sequence[float],
    *,
    max_distance: float | None = None,
    workers: int = -1,
) -> list[list[QualityScore]]:
    """``evaluate_clouds`` of one prediction against several references, building the
    prediction's KD-tree once."""
    ths = _thresholds(thresholds)
    if max_distance is not None and not max_distance >= max(ths):
        raise ValueError(
            f"max_distance {max_distance!r} must be at least the largest threshold {max(ths)}"
        )
    p = _as_points(pred)
    p_tree = _Indexed(p) if len(p) else None
    out = []
    for ref in refs:
        r = _as_points(ref)
        if len(p) == 0:
            d_pr = np.zeros(0)
        elif len(r) == 0:
            d_pr = np.full(len(p), np.inf)
        else:
            d_pr = _query(_Indexed(r), p, workers, max_distance)
        if len(r) == 0:
            d_rp = np.zeros(0)
        elif p_tree is None:
            d_rp = np.full(len(r), np.inf)
        else:
            d_rp = _query(p_tree, r, workers, max_distance)
        out.append(_scores(d_pr, d_rp, ths, max_distance))
    return out


def _scores(
    d_pr: NDArray[np.float64],
    d_rp: NDArray[np.float64],
    ths: list[float],
    max_distance: float | None,
) -> list[QualityScore]:
    n_p, n_r = len(d_pr), len(d_rp)

    def stat(d: NDArray[np.float64], fn: str) -> float:
        if len(d) == 0:
            return math.inf
        return float(np.mean(d) if fn == "mean" else np.median(d))

    scores = []
    for th in ths:
        if n_p == 0 and n_r == 0:
            precision, recall, f = 1.0, 1.0, 1.0
        elif n_p == 0:
            precision, recall, f = 1.0, 0.0, 0.0
        elif n_r == 0:
            precision, recall, f = 0.0, 1.0, 0.0
        else:
            precision = float(np.count_nonzero(d_pr <= th)) / n_p
            recall = float(np.count_nonzero(d_rp <= th)) / n_r
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
                num_pred=n_p,
                num_ref=n_r,
                max_distance=max_distance,
            )
        )
    return scores


def evaluate_nested(
    pred: PointCloud | Points3D,
    ref: PointCloud | Points3D,
    subsets: Sequence[NDArray[np.bool_]],
    thresholds: float | Sequence[float],
    *,
    max_distance: float | None = None,
    workers: int = -1,
) -> list[list[QualityScore]]:
    """``evaluate_against(pred, [ref, ref[m] for m in subsets])`` computed once: the
    distances from a subset's points are the whole reference's, and a predicted point whose
    nearest reference point lies in the subset keeps its distance; only the others are
    searched again (ground truth seen by >= k cameras is such a subset)."""
    ths = _thresholds(thresholds)
    p, r = _as_points(pred), _as_points(ref)
    if len(p) == 0 or len(r) == 0:
        return evaluate_against(
            p, [r, *(r[m] for m in subsets)], ths, max_distance=max_distance, workers=workers
        )
    if max_distance is not None and not max_distance >= max(ths):
        raise ValueError(
            f"max_distance {max_distance!r} must be at least the largest threshold {max(ths)}"
        )
    d_pr, nearest = _query_idx(_Indexed(r), p, workers, max_distance)
    d_rp = _query(_Indexed(p), r, workers, max_distance)
    out = [_scores(d_pr, d_rp, ths, max_distance)]
    for m in subsets:
        m = np.asarray(m, bool)
        sub = r[m]
        if len(sub) == 0:
            out.append(_scores(np.full(len(p), np.inf), np.zeros(0), ths, max_distance))
            continue
        d_sub = d_pr.copy()
        redo = (nearest < 0) | ~m[np.maximum(nearest, 0)]
        if redo.any():
            d_sub[redo] = _query(_Indexed(sub), p[redo], workers, max_distance)
        out.append(_scores(d_sub, d_rp[m], ths, max_distance))
    return out


def fscore(pred: PointCloud | Points3D, ref: PointCloud | Points3D, threshold: float) -> float:
    """F-score at one threshold (see module docstring for empty clouds). The searches stop
    at the threshold: only whether a neighbour lies within it matters."""
    return evaluate_clouds(pred, ref, threshold, max_distance=threshold)[0].fscore
