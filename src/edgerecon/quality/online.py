"""The online quality estimate Q(r, pi(N')) the controller feeds on (paper, Section V-B).

During the run there is no ground truth. The paper scores the *foreground sparse cloud* of the
chosen configuration against the foreground sparse cloud of the *golden* configuration (r = 1,
all cameras) of the same task, which the back-end computes in parallel: F-score at a threshold
d (:func:`online_quality`). On wide-baseline rigs the foreground sparse clouds hold a handful to
a few tens of points and that estimate is mostly noise (Pearson 0.2-0.5 with the offline
foreground F); :func:`silhouette_quality` judges the task's *dense* foreground against the
foreground masks of every camera instead (Pearson 0.83-0.95), needs nothing from the back-end
and is what the online system uses by default.

Defined behaviour at the edges (the controller takes ``OnlineQuality.value``):

* golden foreground empty or with fewer than ``min_reference_points`` points: the estimate is
  *uninformative* (``value`` None — e.g. nobody in the scene, or the golden SfM failed); the
  controller then uses the task's time only;
* candidate foreground empty while the golden one is not: F = 0 (the configuration lost the
  whole foreground the golden one reconstructed);
* both non-empty: F-score at d, with ``d`` absolute (rig units) or relative to the diagonal of
  the golden foreground's bounding box.

:func:`online_offline_correlation` checks that the online estimate moves with an offline score
(dense foreground against the golden dense foreground, or against ground truth on synthetic
scenes) across image scales, as the paper's Table IV does.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry.camera import Camera
from edgerecon.quality.frames import local_contrast
from edgerecon.quality.metrics import evaluate_clouds
from edgerecon.types import Mask, PointCloud, Points3D

#: ``textured``'s least local standard deviation of the grey level (8-bit levels).
TEXTURE_MIN_STD = 3.0

logger = logging.getLogger(__name__)

OnlineStatus = Literal["ok", "empty_candidate", "empty_reference", "few_reference_points"]


@dataclass(frozen=True, kw_only=True)
class OnlineQualityConfig:
    """How the online quality estimate is computed."""

    threshold: float | None = None
    """Distance threshold d in rig units; None = ``threshold_rel`` x the golden foreground's
    bounding-box diagonal."""
    threshold_rel: float = 0.01
    """Relative threshold (share of the golden foreground's bounding-box diagonal), used when
    ``threshold`` is None."""
    min_reference_points: int = 10
    """Golden foregrounds with fewer points give an uninformative estimate (value None)."""
    foreground_only: bool = True
    """When a cloud has labels, score only its foreground points (label >= 1); clouds without
    labels are taken as foreground already."""

    def __post_init__(self) -> None:
        if self.threshold is not None and not (
            math.isfinite(self.threshold) and self.threshold > 0
        ):
            raise ValueError(f"threshold must be a positive number or None, got {self.threshold}")
        if not (math.isfinite(self.threshold_rel) and self.threshold_rel > 0):
            raise ValueError(f"threshold_rel must be a positive number, got {self.threshold_rel}")
        if self.min_reference_points < 1:
            raise ValueError(f"min_reference_points must be >= 1, got {self.min_reference_points}")


@dataclass(frozen=True, kw_only=True)
class OnlineQuality:
    """The online estimate of one task."""

    fscore: float | None
    """F-score at ``threshold`` (None when uninformative)."""
    precision: float | None
    recall: float | None
    threshold: float | None
    """d used, rig units (None when there was no reference to size it)."""
    num_candidate: int
    num_reference: int
    status: OnlineStatus

    @property
    def informative(self) -> bool:
        return self.fscore is not None

    @property
    def value(self) -> float | None:
        """What to pass to ``BisectionController.observe`` as the quality."""
        return self.fscore

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def _points(cloud: PointCloud | Points3D, foreground_only: bool) -> NDArray[np.float64]:
    if isinstance(cloud, PointCloud):
        if foreground_only and cloud.labels is not None:
            return cloud.points3D[cloud.labels >= 1]
        return cloud.points3D
    return np.asarray(cloud, np.float64).reshape(-1, 3)


def online_quality(
    candidate: PointCloud | Points3D,
    golden: PointCloud | Points3D,
    config: OnlineQualityConfig | None = None,
) -> OnlineQuality:
    """F-score of the candidate configuration's foreground sparse cloud against the golden
    configuration's foreground sparse cloud of the same task (see module docstring)."""
    cfg = config or OnlineQualityConfig()
    cand = _points(candidate, cfg.foreground_only)
    ref = _points(golden, cfg.foreground_only)
    nc, nr = len(cand), len(ref)
    if nr == 0 or nr < cfg.min_reference_points:
        status: OnlineStatus = "empty_reference" if nr == 0 else "few_reference_points"
        logger.debug("online quality uninformative: golden foreground has %d points", nr)
        return OnlineQuality(
            fscore=None,
            precision=None,
            recall=None,
            threshold=cfg.threshold,
            num_candidate=nc,
            num_reference=nr,
            status=status,
        )
    if cfg.threshold is not None:
        d = cfg.threshold
    else:
        diag = float(np.linalg.norm(ref.max(axis=0) - ref.min(axis=0)))
        d = cfg.threshold_rel * diag if diag > 0 else cfg.threshold_rel
    if nc == 0:
        return OnlineQuality(
            fscore=0.0,
            precision=1.0,
            recall=0.0,
            threshold=d,
            num_candidate=0,
            num_reference=nr,
            status="empty_candidate",
        )
    score = evaluate_clouds(cand, ref, d)[0]
    return OnlineQuality(
        fscore=score.fscore,
        precision=score.precision,
        recall=score.recall,
        threshold=d,
        num_candidate=nc,
        num_reference=nr,
        status="ok",
    )


def textured(image: NDArray[Any], min_std: float = TEXTURE_MIN_STD, window: int = 7) -> Mask:
    """(h, w) pixels whose grey level varies by at least ``min_std`` (standard deviation,
    ``quality.frames.local_contrast``) in a ``window`` x ``window`` neighbourhood: where
    stereo can measure anything."""
    return np.asarray(local_contrast(image, window) >= min_std, bool)


def silhouette_quality(
    points3D: Points3D,
    cameras: Sequence[Camera],
    masks: Sequence[Mask | None],
    *,
    splat_px: int = 1,
    images: Sequence[NDArray[Any] | None] | None = None,
) -> OnlineQuality:
    """The task's dense foreground judged against every camera's foreground mask — no golden
    reference needed, so the front-end computes it right after its critical path in a few
    milliseconds.

    ``cameras`` / ``masks``: all rig cameras (also those the task left out) with their masks
    at any resolution (``ForegroundResult.cameras`` / ``.masks``). Recall = share of mask
    pixels within ``splat_px`` of a projected point (what of each view's foreground the cloud
    explains: a dropped camera's side of an actor, a coarse scale's gaps); precision = share of
    the points that fall inside an image and land in its mask grown by ``splat_px`` (streaks
    and floaters land outside); the estimate is their F-score. Measured against the offline
    foreground F (``benchmarks/bench_online_quality.py``, scales x camera subsets): Pearson
    0.95 / 0.91 at 1 % / 2 % on the hd4 preset vs truth, 0.89 / 0.83 on caliscope_charuco vs
    the golden dense foreground, where the paper's sparse-vs-golden-sparse F gave 0.2-0.5.

    ``images`` (the masks' frames, e.g. the background models' working images): recall
    counts only the mask pixels with texture (:func:`textured`): a black, textureless shirt
    has no points at any configuration, and its share of the masks changes from one moment
    to the next, which moved the estimate between timestamps without telling configurations
    apart (caliscope_charuco with the person model, docs/BENCHMARKS.md).

    No foreground in any mask: uninformative (``value`` None); foreground but no points: 0.
    """
    import cv2

    pts = np.asarray(points3D, np.float64).reshape(-1, 3)
    k = np.ones((2 * splat_px + 1, 2 * splat_px + 1), np.uint8)
    hit = total = inside = landed = 0
    ims = list(images) if images is not None else [None] * len(masks)
    for cam, mask, im in zip(cameras, masks, ims, strict=True):
        if mask is None or not mask.any():
            continue
        judged = mask if im is None else mask & textured(im)
        total += int(np.count_nonzero(judged))
        if not len(pts):
            continue
        uv, depth = cam.project(pts)
        ok = (depth > 0) & cam.in_image(uv)
        u = np.clip(np.rint(uv[ok, 0]).astype(np.intp), 0, cam.width - 1)
        v = np.clip(np.rint(uv[ok, 1]).astype(np.intp), 0, cam.height - 1)
        splat = np.zeros(mask.shape, np.uint8)
        splat[v, u] = 1
        if splat_px > 0:
            splat = np.asarray(cv2.dilate(splat, k), np.uint8)
            grown = cv2.dilate(mask.view(np.uint8), k).astype(bool)
        else:
            grown = mask
        hit += int(np.count_nonzero(splat.astype(bool) & judged))
        inside += int(np.count_nonzero(grown[v, u]))
        landed += len(u)
    if total == 0:
        return OnlineQuality(
            fscore=None,
            precision=None,
            recall=None,
            threshold=None,
            num_candidate=len(pts),
            num_reference=0,
            status="empty_reference",
        )
    recall = hit / total
    precision = inside / landed if landed else 0.0
    f = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return OnlineQuality(
        fscore=f,
        precision=precision,
        recall=recall,
        threshold=float(splat_px),
        num_candidate=len(pts),
        num_reference=total,
        status="ok" if len(pts) else "empty_candidate",
    )


@dataclass(frozen=True, kw_only=True)
class CorrelationReport:
    """How an online score tracks an offline score across configurations (e.g. scales)."""

    num_samples: int
    pearson: float
    """Pearson correlation (NaN with < 3 samples or a constant series)."""
    spearman: float
    """Spearman rank correlation (NaN likewise)."""
    trend_agreement: float
    """Share of consecutive pairs (in the given order, e.g. by scale) where both scores move
    in the same direction (NaN with < 2 pairs that move)."""

    def to_dict(self) -> dict[str, float | int | None]:
        return {
            k: (None if isinstance(v, float) and not math.isfinite(v) else v)
            for k, v in self.__dict__.items()
        }


def _pearson(x: NDArray[np.float64], y: NDArray[np.float64]) -> float:
    if len(x) < 3 or np.ptp(x) == 0 or np.ptp(y) == 0:
        return math.nan
    xc, yc = x - x.mean(), y - y.mean()
    return float((xc @ yc) / math.sqrt(float(xc @ xc) * float(yc @ yc)))


def _ranks(x: NDArray[np.float64]) -> NDArray[np.float64]:
    from scipy.stats import rankdata

    return np.asarray(rankdata(x), np.float64)


def online_offline_correlation(
    online: Sequence[float | None], offline: Sequence[float | None]
) -> CorrelationReport:
    """Correlation between online and offline scores of the same configurations (pairs with
    a missing value on either side are left out)."""
    if len(online) != len(offline):
        raise ValueError(f"online has {len(online)} scores, offline {len(offline)}")
    pairs = [
        (float(a), float(b))
        for a, b in zip(online, offline, strict=True)
        if a is not None and b is not None and math.isfinite(a) and math.isfinite(b)
    ]
    x = np.array([p[0] for p in pairs], np.float64)
    y = np.array([p[1] for p in pairs], np.float64)
    dx, dy = np.sign(np.diff(x)), np.sign(np.diff(y))
    moving = (dx != 0) | (dy != 0)
    trend = float(np.mean(dx[moving] == dy[moving])) if moving.sum() >= 2 else math.nan
    spearman = _pearson(_ranks(x), _ranks(y)) if len(x) >= 3 else math.nan
    return CorrelationReport(
        num_samples=len(x), pearson=_pearson(x, y), spearman=spearman, trend_agreement=trend
    )
