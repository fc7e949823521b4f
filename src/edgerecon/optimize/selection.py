"""Camera selection, the paper's problem P2: choose exactly N' of N cameras so that as many
sparse points as possible are seen by at least two chosen cameras (a point seen by one camera
cannot be triangulated), and the mapping pi(N') for every N' from N down to 3.

Input is the point-camera visibility matrix A (P points x N cameras, bool), indexed by rig
camera id (``SparseReconstruction.visibility_matrix(num_cameras)``). The objective only depends
on a point through its visibility *pattern* (the set of cameras that see it), so every solver
works on the distinct patterns weighted by how many points share them; patterns seen by fewer
than ``min_views`` cameras can never count and are dropped.

Solvers (all deterministic, all return the lexicographically smallest id set among the optima
they prove; see ``docs/OPTIMIZER.md`` for the measurements behind the automatic choice):

* ``brute_force`` — exact, all N' at once, independent of P: with ``Z(T)`` the number of
  points whose pattern lies inside camera set ``T`` (a subset-sum / zeta transform of the
  pattern histogram, O(N 2^N)), the points a set ``S`` leaves uncovered are
  ``(1 - |S|) Z(~S) + sum_{n in S} Z(~S + n)``. N = 20: all 2^20 subsets in ~0.1 s.
* ``enumerate`` — exact for one N' when C(N, N') x patterns is small (e.g. N' near 3 or N).
* ``cpsat`` — exact ILP with OR-Tools CP-SAT on the aggregated patterns
  (``sum_{n in S_k} o_n >= min_views`` enforced when ``y_k``), warm-started from local search,
  with a *deterministic* work limit so the result is reproducible.
* ``milp`` — exact ILP with SciPy's ``milp`` (HiGHS): the paper's ``2 y_k <= sum_n A_kn o_n``
  on weighted patterns (``naive``), or ``strong``, which adds ``y_k <= sum_{m in S_k, m != n}
  o_m`` for every n in S_k (tighter where the LP concentrates on few cameras; faster on
  structured visibility, slower on random; HiGHS is the slowest exact solver either way).
* ``local_search`` — reverse greedy (drop the least useful camera, N -> 1) followed by
  best-improvement swaps and a few seeded 2-swap kicks (iterated local search): within 1 % of
  the best known solution at N = 30 in 0.02-0.2 s, the ``auto`` choice above 20 cameras.

For ``cpsat`` / ``milp``, problems with many distinct patterns are first reduced to at most
``max_key_points`` weighted key patterns by k-means on the visibility rows (the paper's
"k-means key points", done in pattern space: points with the same pattern are interchangeable
for this objective, so the reduction is exact while the number of distinct patterns fits the
budget — the case on real sparse clouds). The chosen set is always re-scored on the full data,
and the local-search answer competes with it.

Without points (P = 0 or no point seen twice) selection does not fail: given camera centres
(and optionally viewing directions) it solves the same problem on *virtual* points — surface
orientations around the point the cameras look at, seen by a camera when they face it
(:func:`geometric_visibility`): the chosen cameras form overlapping groups that cover as many
surface orientations twice as possible. Without geometry either, every subset ties and the tie-break picks the
lowest ids (a logged warning).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from itertools import combinations
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from edgerecon.types import DataError, StageTimings

logger = logging.getLogger(__name__)

Visibility = NDArray[np.bool_]  # (P, N) True where point k is seen by camera n
SolverName = Literal["auto", "brute_force", "enumerate", "cpsat", "milp", "local_search"]
_SOLVERS = ("auto", "brute_force", "enumerate", "cpsat", "milp", "local_search")

#: Largest candidate count the subset-sum brute force accepts (2^26 int64 entries = 512 MiB).
BRUTE_FORCE_HARD_LIMIT = 26


@dataclass(frozen=True, kw_only=True)
class SelectionConfig:
    """How camera subsets are chosen (problem P2)."""

    solver: SolverName = "auto"
    """``auto`` picks per size (brute force up to ``brute_force_max_cameras``, else exact
    enumeration where cheap, else iterated local search, which beat the key-point ILP in
    ``benchmarks/bench_camera_selection.py``); or force one solver."""
    min_views: int = 2
    """A point counts as covered when at least this many chosen cameras see it (paper: 2)."""
    min_cameras: int = 3
    """Smallest subset in the mapping pi(N') (the pipeline needs 3 cameras)."""
    brute_force_max_cameras: int = 20
    """``auto`` uses the exact subset-sum brute force up to this many candidate cameras
    (memory and time grow as 2^N: N = 20 takes ~0.1 s and 8 MiB per array, N = 22 ~1 s)."""
    enumerate_max_work: int = 20_000_000
    """``auto`` enumerates all C(N, N') subsets exactly when C(N, N') x patterns <= this."""
    max_key_points: int = 256
    """Reduce to this many k-means key patterns when there are more distinct visibility
    patterns (0 = never reduce). Only used by the ILP solvers and ``enumerate``."""
    local_search_rounds: int = 8
    """Perturbation rounds of the iterated local search (0 = plain swap search)."""
    kmeans_iterations: int = 25
    """Lloyd iterations of the key-point k-means."""
    time_limit_s: float = 10.0
    """Wall-clock cap per N' of ``cpsat`` / ``milp``, seconds (milp's only limit)."""
    cpsat_work_limit: float | None = 0.1
    """CP-SAT's deterministic time limit per solve (its work units; 0.1 took 0.1-0.8 s wall
    here). With one worker the answer is then the same on any machine load; None = stop
    only at ``time_limit_s`` (wall clock: not reproducible when the limit is hit)."""
    num_workers: int = 1
    """CP-SAT workers (more than 1 is not reproducible)."""
    milp_formulation: Literal["strong", "naive"] = "strong"
    """``naive`` is the paper's ``2 y_k <= sum_n A_kn o_n`` (weak LP relaxation, slow);
    ``strong`` adds ``y_k <= sum_{m in S_k, m != n} o_m`` for each camera n of a pattern."""
    seed: int = 0
    """Seed of the k-means initialisation (the only randomness)."""

    def __post_init__(self) -> None:
        if self.solver not in _SOLVERS:
            raise ValueError(f"solver must be one of {_SOLVERS}, got {self.solver!r}")
        if self.min_views < 1:
            raise ValueError(f"min_views must be >= 1, got {self.min_views}")
        if self.min_cameras < 1:
            raise ValueError(f"min_cameras must be >= 1, got {self.min_cameras}")
        if not 1 <= self.brute_force_max_cameras <= BRUTE_FORCE_HARD_LIMIT:
            raise ValueError(
                f"brute_force_max_cameras must be in 1..{BRUTE_FORCE_HARD_LIMIT}, "
                f"got {self.brute_force_max_cameras}"
            )
        if self.enumerate_max_work < 0:
            raise ValueError(f"enumerate_max_work must be >= 0, got {self.enumerate_max_work}")
        if self.max_key_points < 0 or 0 < self.max_key_points < 2:
            raise ValueError(f"max_key_points must be 0 or >= 2, got {self.max_key_points}")
        if self.local_search_rounds < 0:
            raise ValueError(f"local_search_rounds must be >= 0, got {self.local_search_rounds}")
        if self.kmeans_iterations < 1:
            raise ValueError(f"kmeans_iterations must be >= 1, got {self.kmeans_iterations}")
        if not (self.time_limit_s > 0 and math.isfinite(self.time_limit_s)):
            raise ValueError(f"time_limit_s must be a positive number, got {self.time_limit_s}")
        if self.cpsat_work_limit is not None and not self.cpsat_work_limit > 0:
            raise ValueError(
                f"cpsat_work_limit must be positive or None, got {self.cpsat_work_limit}"
            )
        if self.num_workers < 1:
            raise ValueError(f"num_workers must be >= 1, got {self.num_workers}")
        if self.milp_formulation not in ("strong", "naive"):
            raise ValueError(
                f"milp_formulation must be 'strong' or 'naive', got {self.milp_formulation!r}"
            )


@dataclass(frozen=True, kw_only=True)
class Selection:
    """The chosen cameras for one subset size N'."""

    num_cameras: int
    """N', the subset size."""
    camera_ids: tuple[int, ...]
    """Chosen rig camera ids, ascending."""
    covered: int
    """Points (of the full input, not key points) seen by >= min_views chosen cameras."""
    solver: str
    """Solver that produced the subset."""
    optimal: bool
    """True when the subset is proven optimal on the full input (never after a key-point
    reduction or a time-limited solve that did not close the gap)."""
    upper_bound: int | None = None
    """A proven upper bound on ``covered`` when the solver gave one, else None."""
    seconds: float = 0.0
    """Solver seconds spent on this N' (the brute force reports its one-off cost on each)."""

    def to_dict(self) -> dict[str, Any]:
        return {
            "num_cameras": self.num_cameras,
            "camera_ids": list(self.camera_ids),
            "covered": self.covered,
            "solver": self.solver,
            "optimal": self.optimal,
            "upper_bound": self.upper_bound,
            "seconds": round(self.seconds, 6),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Selection:
        return cls(
            num_cameras=int(d["num_cameras"]),
            camera_ids=tuple(int(i) for i in d["camera_ids"]),
            covered=int(d["covered"]),
            solver=str(d["solver"]),
            optimal=bool(d["optimal"]),
            upper_bound=None if d.get("upper_bound") is None else int(d["upper_bound"]),
            seconds=float(d.get("seconds", 0.0)),
        )


@dataclass(frozen=True, kw_only=True)
class CameraMapping:
    """pi(N'): the chosen camera subset for every N' from the candidate count down to
    ``min_cameras``. Callable: ``mapping(n)`` returns the ids for N' = n."""

    selections: dict[int, Selection]
    """N' -> its selection."""
    candidates: tuple[int, ...]
    """Camera ids that could be chosen (the available cameras), ascending."""
    num_points: int
    """P, rows of the visibility matrix (virtual points for the geometric criterion)."""
    num_coverable: int
    """Points seen by >= min_views candidate cameras (the most any subset can cover)."""
    criterion: Literal["visibility", "geometric", "none"]
    """What the subsets maximise: real point visibility, the geometric fallback's virtual
    points, or nothing (no points and no geometry: every subset ties, lowest ids win)."""
    num_patterns: int = 0
    """Distinct visibility patterns seen by >= min_views candidate cameras."""
    num_key_points: int | None = None
    """Key patterns after the k-means reduction (None: no reduction)."""
    timings: StageTimings = field(default_factory=StageTimings)
    """Seconds of ``aggregate``, ``reduce``, ``solve``."""

    def __call__(self, num_cameras: int) -> tuple[int, ...]:
        return self.selection(num_cameras).camera_ids

    def selection(self, num_cameras: int) -> Selection:
        if num_cameras not in self.selections:
            raise ValueError(
                f"no camera subset of size {num_cameras}: this mapping covers "
                f"{min(self.selections)}..{max(self.selections)}"
            )
        return self.selections[num_cameras]

    @property
    def sizes(self) -> list[int]:
        """The N' values, descending."""
        return sorted(self.selections, reverse=True)

    def coverage_fraction(self, num_cameras: int) -> float:
        """Share of the coverable points that pi(N') covers (1.0 when nothing is coverable)."""
        if self.num_coverable == 0:
            return 1.0
        return self.selection(num_cameras).covered / self.num_coverable

    def to_dict(self) -> dict[str, Any]:
        return {
            "selections": [self.selections[n].to_dict() for n in self.sizes],
            "candidates": list(self.candidates),
            "num_points": self.num_points,
            "num_coverable": self.num_coverable,
            "criterion": self.criterion,
            "num_patterns": self.num_patterns,
            "num_key_points": self.num_key_points,
            "timings": self.timings.to_dict(),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> CameraMapping:
        sels = [Selection.from_dict(s) for s in d["selections"]]
        return cls(
            selections={s.num_cameras: s for s in sels},
            candidates=tuple(int(i) for i in d["candidates"]),
            num_points=int(d["num_points"]),
            num_coverable=int(d["num_coverable"]),
            criterion=d["criterion"],
            num_patterns=int(d.get("num_patterns", 0)),
            num_key_points=None if d.get("num_key_points") is None else int(d["num_key_points"]),
            timings=StageTimings(dict(d.get("timings", {}))),
        )


@dataclass(frozen=True, kw_only=True, eq=False)
class VisibilityPatterns:
    """Distinct visibility patterns over the candidate cameras, weighted by point counts."""

    masks: NDArray[np.bool_]
    """(K, M) pattern k seen by candidate camera m (columns follow ``candidates``)."""
    weights: NDArray[np.int64]
    """(K,) number of points with each pattern."""
    candidates: tuple[int, ...]
    """Rig camera id of each column, ascending."""

    @property
    def num_patterns(self) -> int:
        return int(self.masks.shape[0])

    @property
    def num_candidates(self) -> int:
        return len(self.candidates)

    @property
    def total_weight(self) -> int:
        return int(self.weights.sum())


# --------------------------------------------------------------------------- validation


def _check_visibility(visibility: Any, name: str = "visibility") -> Visibility:
    arr = np.asarray(visibility)
    if arr.ndim != 2:
        raise DataError(f"{name} must be a 2-D (points x cameras) matrix, got shape {arr.shape}")
    if arr.dtype != np.bool_:
        if arr.size and not np.isin(arr, (0, 1)).all():
            raise DataError(f"{name} must be boolean or 0/1, got values outside {{0, 1}}")
        arr = arr.astype(bool)
    return arr


def _check_candidates(available: Iterable[int] | None, num_cameras: int) -> tuple[int, ...]:
    if available is None:
        return tuple(range(num_cameras))
    ids = sorted({int(i) for i in available})
    bad = [i for i in ids if not 0 <= i < num_cameras]
    if bad:
        raise DataError(
            f"available camera ids {bad} are out of range for {num_cameras} cameras "
            f"(0..{num_cameras - 1})"
        )
    return tuple(ids)


# --------------------------------------------------------------------------- patterns


def aggregate_patterns(
    visibility: Visibility,
    available: Iterable[int] | None = None,
    min_views: int = 2,
) -> VisibilityPatterns:
    """Distinct rows of ``visibility`` restricted to the available cameras, with counts;
    rows seen by fewer than ``min_views`` available cameras are dropped (never coverable)."""
    vis = _check_visibility(visibility)
    cand = _check_candidates(available, vis.shape[1])
    sub = vis[:, list(cand)]
    sub = sub[sub.sum(axis=1) >= min_views]
    if sub.shape[0] == 0:
        return VisibilityPatterns(
            masks=np.zeros((0, len(cand)), bool), weights=np.zeros(0, np.int64), candidates=cand
        )
    packed = np.packbits(sub, axis=1)
    uniq, counts = np.unique(packed, axis=0, return_counts=True)
    masks = np.unpackbits(uniq, axis=1, count=len(cand)).astype(bool)
    return VisibilityPatterns(masks=masks, weights=counts.astype(np.int64), candidates=cand)


def coverage(visibility: Visibility, camera_ids: Iterable[int], min_views: int = 2) -> int:
    """Number of points seen by >= ``min_views`` of ``camera_ids``."""
    vis = _check_visibility(visibility)
    ids = list(camera_ids)
    if not ids:
        return 0
    return int(np.count_nonzero(vis[:, ids].sum(axis=1) >= min_views))


def _pattern_coverage(pat: VisibilityPatterns, cols: Sequence[int], min_views: int) -> int:
    if not len(cols) or pat.num_patterns == 0:
        return 0
    counts = pat.masks[:, list(cols)].sum(axis=1)
    return int(pat.weights[counts >= min_views].sum())


def reduce_patterns_kmeans(
    patterns: VisibilityPatterns, num_key_points: int, iterations: int = 25, seed: int = 0
) -> VisibilityPatterns:
    """The paper's key-point reduction, in pattern space: weighted k-means (k-means++ seeding,
    Lloyd iterations) on the 0/1 pattern rows; each cluster becomes one key pattern (the
    majority vote of its members, weight = its number of points). Identity when there are at
    most ``num_key_points`` patterns. Deterministic for a given seed."""
    if patterns.num_patterns <= num_key_points:
        return patterns
    x = patterns.masks.astype(np.float64)
    w = patterns.weights.astype(np.float64)
    rng = np.random.default_rng(seed)
    k = num_key_points
    # k-means++ seeding (weighted), on the distinct patterns.
    centers = np.empty((k, x.shape[1]))
    first = int(np.argmax(w))  # the heaviest pattern: deterministic and always a good seed
    centers[0] = x[first]
    d2 = ((x - centers[0]) ** 2).sum(axis=1)
    for j in range(1, k):
        p = w * d2
        total = p.sum()
        if total <= 0:
            centers[j:] = centers[0]
            break
        idx = int(rng.choice(len(x), p=p / total))
        centers[j] = x[idx]
        d2 = np.minimum(d2, ((x - centers[j]) ** 2).sum(axis=1))
    x2 = (x**2).sum(axis=1)
    labels = np.zeros(len(x), np.int64)
    for it in range(iterations):
        dist = x2[:, None] - 2 * x @ centers.T + (centers**2).sum(axis=1)[None]
        new = np.argmin(dist, axis=1)
        if it > 0 and np.array_equal(new, labels):
            break
        labels = new
        wsum = np.bincount(labels, weights=w, minlength=k)
        for c in range(x.shape[1]):
            centers[:, c] = np.bincount(labels, weights=w * x[:, c], minlength=k)
        nz = wsum > 0
        centers[nz] /= wsum[nz, None]
    used = np.unique(labels)
    wsum = np.bincount(labels, weights=w, minlength=k)
    key = np.zeros((len(used), x.shape[1]), bool)
    for c in range(x.shape[1]):
        share = np.bincount(labels, weights=w * x[:, c], minlength=k)[used] / wsum[used]
        key[:, c] = share >= 0.5
    weights = np.bincount(labels, weights=patterns.weights, minlength=k)[used]
    # Identical key patterns (two clusters rounding to the same rows) are merged.
    packed = np.packbits(key, axis=1)
    uniq, inverse = np.unique(packed, axis=0, return_inverse=True)
    merged = np.bincount(inverse.ravel(), weights=weights, minlength=len(uniq))
    masks = np.unpackbits(uniq, axis=1, count=x.shape[1]).astype(bool)
    return VisibilityPatterns(
        masks=masks, weights=np.rint(merged).astype(np.int64), candidates=patterns.candidates
    )


# --------------------------------------------------------------------------- geometry


def _fibonacci_sphere(n: int) -> NDArray[np.float64]:
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    r = np.sqrt(np.maximum(0.0, 1 - z**2))
    phi = np.pi * (1 + 5**0.5) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _look_at_point(
    centers: NDArray[np.float64], directions: NDArray[np.float64] | None
) -> NDArray[np.float64]:
    """Least-squares closest point to all optical axes (the centroid without directions or
    when the axes are near-parallel)."""
    if directions is None:
        return np.asarray(centers.mean(axis=0), np.float64)
    d = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    lhs = proj.sum(axis=0)
    rhs = np.einsum("nij,nj->i", proj, centers)
    if np.linalg.cond(lhs) > 1e8:
        return np.asarray(centers.mean(axis=0), np.float64)
    return np.asarray(np.linalg.solve(lhs, rhs), np.float64)


def geometric_visibility(
    camera_centers: NDArray[np.float64],
    viewing_directions: NDArray[np.float64] | None = None,
    num_virtual_points: int = 512,
    max_angle_deg: float = 75.0,
) -> Visibility:
    """Visibility of virtual points for selection without a point cloud.

    The virtual points are surface orientations (Fibonacci-sphere normals) at the point the
    cameras look at (the least-squares intersection of the optical axes, or the centroid of the
    centres); camera n sees orientation d when the angle between d and the direction to the
    camera is below ``max_angle_deg`` (and the camera faces that point). Maximising the
    orientations seen by two chosen cameras spreads the subset around the scene while keeping
    neighbouring cameras overlapping.
    """
    c = np.asarray(camera_centers, np.float64).reshape(-1, 3)
    if not np.all(np.isfinite(c)):
        raise DataError("camera centres contain NaN or infinite values")
    dirs = None
    if viewing_directions is not None:
        dirs = np.asarray(viewing_directions, np.float64).reshape(-1, 3)
        if dirs.shape != c.shape:
            raise DataError(
                f"viewing_directions has shape {dirs.shape}, expected {c.shape} (one per camera)"
            )
    target = _look_at_point(c, dirs)
    to_cam = c - target
    dist = np.linalg.norm(to_cam, axis=1, keepdims=True)
    to_cam = to_cam / np.where(dist > 0, dist, 1.0)
    normals = _fibonacci_sphere(num_virtual_points)
    vis = normals @ to_cam.T >= math.cos(math.radians(max_angle_deg))
    if dirs is not None:
        facing = np.einsum("nj,nj->n", dirs, -to_cam) > 0
        vis &= facing[None, :]
    return vis


def visibility_from_points(
    points3D: NDArray[np.float64],
    cameras: Sequence[Any],
    normals: NDArray[np.floating[Any]] | None = None,
    max_angle_deg: float = 80.0,
) -> Visibility:
    """(P, N) visibility of arbitrary points (dense or visual-hull points when the sparse
    cloud is nearly empty): in front of camera n and inside its image, and — when normals are
    given — facing it within ``max_angle_deg``. There is no occlusion test. ``cameras`` are
    ``edgerecon.geometry.Camera`` objects in rig order."""
    pts = np.asarray(points3D, np.float64).reshape(-1, 3)
    vis = np.zeros((len(pts), len(cameras)), bool)
    nrm = None if normals is None else np.asarray(normals, np.float64).reshape(-1, 3)
    if nrm is not None and len(nrm) != len(pts):
        raise DataError(f"normals has {len(nrm)} rows, expected {len(pts)} (one per point)")
    cos_max = math.cos(math.radians(max_angle_deg))
    for n, cam in enumerate(cameras):
        uv, depth = cam.project(pts)
        ok = (depth > 0) & cam.in_image(uv)
        if nrm is not None:
            ray = cam.center[None] - pts
            ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-12)
            ok &= np.einsum("pj,pj->p", ray, nrm) >= cos_max
        vis[:, n] = ok
    return vis


# --------------------------------------------------------------------------- solvers


def _lex_key(ids: Sequence[int]) -> tuple[int, ...]:
    return tuple(sorted(ids))


def _better(cov_a: int, ids_a: Sequence[int], cov_b: int, ids_b: Sequence[int]) -> bool:
    """Is (cov_a, ids_a) better than (cov_b, ids_b): more coverage, then lexicographically
    smaller id set."""
    if cov_a != cov_b:
        return cov_a > cov_b
    return _lex_key(ids_a) < _lex_key(ids_b)


def _brute_force_all(
    pat: VisibilityPatterns, min_views: int
) -> dict[int, tuple[tuple[int, ...], int]]:
    """Exact optimum for every subset size k = 0..M at once (columns are candidate indices).

    Camera column j is bit M-1-j, so for sets of equal size the lexicographically smallest id
    set is the largest integer: the tie-break is a max. Only min_views = 2 has the closed form
    below; other values use the generic per-size enumeration.
    """
    m = pat.num_candidates
    if min_views != 2:
        return {k: _enumerate_exact(pat, k, min_views)[:2] for k in range(m + 1)}
    size = 1 << m
    full = size - 1
    bits = (1 << (m - 1 - np.arange(m))).astype(np.int64)
    idx = pat.masks.astype(np.int64) @ bits if pat.num_patterns else np.zeros(0, np.int64)
    hist = np.bincount(idx, weights=pat.weights, minlength=size)
    h = np.rint(hist).astype(np.int64)
    total = int(h.sum())
    z = h  # zeta transform in place: z[T] = points whose pattern is a subset of T
    for i in range(m):
        v = z.reshape(-1, 2, 1 << i)
        v[:, 1, :] += v[:, 0, :]
    u = np.zeros_like(z)  # u[T] = sum over n not in T of z[T + n]
    for i in range(m):
        v = z.reshape(-1, 2, 1 << i)
        uu = u.reshape(-1, 2, 1 << i)
        uu[:, 0, :] += v[:, 1, :]
    subsets = np.arange(size, dtype=np.int64)
    popcount = np.bitwise_count(subsets).astype(np.int64)
    # complement of S is full - S, i.e. the reversed arrays indexed by S
    covered = total - (1 - popcount) * z[::-1] - u[::-1]
    del z, u, h
    # key orders by coverage, then by the integer (lexicographic tie-break); coverage fits in
    # 63 - m bits for any realistic P.
    if total >= (1 << (62 - m)):
        raise DataError(f"too many points ({total}) for the brute force at {m} cameras")
    key = (covered << m) | subsets
    order = np.argsort(popcount, kind="stable")
    starts = np.searchsorted(popcount[order], np.arange(m + 1))
    best = np.maximum.reduceat(key[order], starts)
    out = {}
    for k in range(m + 1):
        b = int(best[k])
        cov, s = b >> m, b & full
        cols = tuple(j for j in range(m) if (s >> (m - 1 - j)) & 1)
        out[k] = (cols, cov)
    _ = full
    return out


def _enumerate_exact(
    pat: VisibilityPatterns, k: int, min_views: int, chunk: int = 1 << 16
) -> tuple[tuple[int, ...], int, float]:
    """Exact optimum of one size k by enumerating C(M, k) subsets in lexicographic order
    (chunks of subsets x patterns through one matrix product)."""
    t0 = time.perf_counter()
    m = pat.num_candidates
    best_cols: tuple[int, ...] = tuple(range(k))
    best_cov = -1
    a = pat.masks.astype(np.float32)
    w = pat.weights.astype(np.float64)
    it = combinations(range(m), k)
    while True:
        block = list(_take(it, chunk))
        if not block:
            break
        sel = np.zeros((m, len(block)), np.float32)
        arr = np.asarray(block, np.int64).reshape(len(block), k)
        sel[arr.T, np.arange(len(block))[None, :]] = 1.0
        counts = a @ sel if pat.num_patterns else np.zeros((0, len(block)), np.float32)
        cov = w @ (counts >= min_views - 0.5)
        j = int(np.argmax(cov))  # first maximum = lexicographically smallest in this block
        c = round(cov[j]) if len(cov) else 0
        if c > best_cov:  # strictly better: earlier blocks are lexicographically smaller
            best_cov, best_cols = c, tuple(int(i) for i in arr[j])
    return best_cols, max(best_cov, 0), time.perf_counter() - t0


def _take(it: Iterable[tuple[int, ...]], n: int) -> Iterable[tuple[int, ...]]:
    for _, item in zip(range(n), it, strict=False):
        yield item


def _reverse_greedy(pat: VisibilityPatterns, min_views: int) -> dict[int, tuple[int, ...]]:
    """Nested subsets M -> 1: repeatedly drop the camera whose removal loses the fewest points
    (lowest id on ties)."""
    m = pat.num_candidates
    a = pat.masks.astype(np.int16)
    w = pat.weights
    chosen = list(range(m))
    counts = a.sum(axis=1)
    out = {m: tuple(chosen)}
    while len(chosen) > 1:
        loss = [
            int(w[(counts >= min_views) & (counts - a[:, j] < min_views)].sum()) for j in chosen
        ]
        drop = chosen[int(np.argmin(loss))]
        counts = counts - a[:, drop]
        chosen.remove(drop)
        out[len(chosen)] = tuple(chosen)
    return out


def _swap_search(
    pat: VisibilityPatterns, start: Sequence[int], min_views: int, max_sweeps: int = 100
) -> tuple[tuple[int, ...], int]:
    """Best-improvement 1-swap local search. All swaps (a out, b in) are scored at once: with
    ``c_a`` the per-pattern counts without a, the coverage after the swap is
    ``w . [c_a >= v] + (w * [c_a == v - 1]) . A[:, b]`` — two matrix products."""
    m = pat.num_candidates
    chosen = sorted(start)
    if pat.num_patterns == 0 or len(chosen) in (0, m):
        return tuple(chosen), _pattern_coverage(pat, chosen, min_views)
    a = pat.masks.astype(np.float32)
    w = pat.weights.astype(np.float32)
    counts = a[:, chosen].sum(axis=1)
    cur = float(pat.weights[counts >= min_views].sum())
    for _ in range(max_sweeps):
        out_cols = np.array(chosen)
        in_mask = np.ones(m, bool)
        in_mask[out_cols] = False
        in_cols = np.flatnonzero(in_mask)
        base = counts[:, None] - a[:, out_cols]  # (K, k) counts without each chosen camera
        kept = w @ (base >= min_views)  # (k,)
        gain = kept[:, None] + ((base == min_views - 1) * w[:, None]).T @ a[:, in_cols]
        i, j = np.unravel_index(int(np.argmax(gain)), gain.shape)
        if gain[i, j] <= cur + 0.5:
            break
        counts = base[:, i] + a[:, in_cols[j]]
        chosen = sorted((set(chosen) - {int(out_cols[i])}) | {int(in_cols[j])})
        cur = float(pat.weights[counts >= min_views].sum())
    return tuple(chosen), round(cur)


def _iterated_local_search(
    pat: VisibilityPatterns, start: Sequence[int], min_views: int, rounds: int, seed: int
) -> tuple[tuple[int, ...], int]:
    """Swap search, then ``rounds`` perturbations (swap 2 random cameras, search again),
    keeping the best (lowest ids on ties). Deterministic for a given seed."""
    best_cols, best_cov = _swap_search(pat, start, min_views)
    m, k = pat.num_candidates, len(best_cols)
    if k < 2 or m - k < 2:
        return best_cols, best_cov
    rng = np.random.default_rng(seed)
    for _ in range(rounds):
        cur = list(best_cols)
        rest = [j for j in range(m) if j not in set(cur)]
        drop = set(rng.choice(cur, 2, replace=False).tolist())
        add = set(rng.choice(rest, 2, replace=False).tolist())
        cols, cov = _swap_search(pat, sorted((set(cur) - drop) | add), min_views)
        if _better(cov, cols, best_cov, best_cols):
            best_cols, best_cov = cols, cov
    return best_cols, best_cov


def _cpsat_solve(
    pat: VisibilityPatterns,
    k: int,
    min_views: int,
    config: SelectionConfig,
    hint: Sequence[int] | None,
) -> tuple[tuple[int, ...], int, bool, int | None]:
    """CP-SAT on the weighted patterns. Returns (cols, covered on pat, proven, upper bound)."""
    from ortools.sat.python import cp_model

    m = pat.num_candidates
    model = cp_model.CpModel()
    o = [model.new_bool_var(f"o{j}") for j in range(m)]
    model.add(sum(o) == k)
    ys = []
    weights = []
    for row, wk in zip(pat.masks, pat.weights, strict=True):
        support = np.flatnonzero(row)
        y = model.new_bool_var("")
        model.add(sum(o[int(j)] for j in support) >= min_views).only_enforce_if(y)
        ys.append(y)
        weights.append(int(wk))
    model.maximize(sum(wk * y for wk, y in zip(weights, ys, strict=True)))
    if hint is not None:
        # a complete hint (cameras and the patterns they cover) so CP-SAT starts from it
        hs = set(hint)
        for j in range(m):
            model.add_hint(o[j], j in hs)
        hcount = pat.masks[:, sorted(hs)].sum(axis=1)
        for y, c in zip(ys, hcount, strict=True):
            model.add_hint(y, bool(c >= min_views))
    solver = cp_model.CpSolver()
    params = solver.parameters
    params.num_workers = config.num_workers
    params.random_seed = config.seed
    params.max_time_in_seconds = config.time_limit_s
    if config.cpsat_work_limit is not None:
        params.max_deterministic_time = config.cpsat_work_limit
    status = solver.solve(model)
    if status not in (cp_model.OPTIMAL, cp_model.FEASIBLE):
        cols = tuple(sorted(hint)) if hint is not None else tuple(range(k))
        return cols, _pattern_coverage(pat, cols, min_views), False, None
    cols = tuple(j for j in range(m) if solver.boolean_value(o[j]))
    best = round(solver.objective_value)
    proven = status == cp_model.OPTIMAL
    bound = math.floor(solver.best_objective_bound + 1e-6)
    if proven:
        # Second phase: among the optima, the lexicographically smallest id set (max of the
        # binary number with the lowest id as the most significant bit).
        model.add(sum(wk * y for wk, y in zip(weights, ys, strict=True)) >= best)
        model.maximize(sum((1 << (m - 1 - j)) * o[j] for j in range(m)))
        model.clear_hints()
        for j in range(m):
            model.add_hint(o[j], j in set(cols))
        ccount = pat.masks[:, list(cols)].sum(axis=1)
        for y, c in zip(ys, ccount, strict=True):
            model.add_hint(y, bool(c >= min_views))
        status2 = solver.solve(model)
        if status2 == cp_model.OPTIMAL:
            cols = tuple(j for j in range(m) if solver.boolean_value(o[j]))
        else:  # time ran out in phase 2: keep phase 1's optimum, tie-break not guaranteed
            logger.debug("CP-SAT tie-break phase did not finish for k=%d", k)
    return cols, best, proven, bound


def _milp_solve(
    pat: VisibilityPatterns,
    k: int,
    min_views: int,
    config: SelectionConfig,
) -> tuple[tuple[int, ...], int, bool, int | None]:
    """SciPy milp (HiGHS). Variables [o_0..o_{M-1}, y_0..y_{K-1}]."""
    from scipy.optimize import Bounds, LinearConstraint, milp
    from scipy.sparse import coo_matrix

    m, kk = pat.num_candidates, pat.num_patterns
    nvar = m + kk
    rows: list[int] = []
    cols_: list[int] = []
    vals: list[float] = []
    ub: list[float] = []
    r = 0
    # sum o = k
    rows += [r] * m
    cols_ += list(range(m))
    vals += [1.0] * m
    lb = [float(k)]
    ub.append(float(k))
    r += 1
    for p, row in enumerate(pat.masks):
        support = [int(j) for j in np.flatnonzero(row)]
        # min_views * y_p - sum_{S_p} o <= 0  (the paper's linearisation)
        rows += [r] * (len(support) + 1)
        cols_ += [m + p, *support]
        vals += [float(min_views)] + [-1.0] * len(support)
        lb.append(-np.inf)
        ub.append(0.0)
        r += 1
        if config.milp_formulation == "strong" and min_views == 2:
            for n in support:
                others = [j for j in support if j != n]
                rows += [r] * (len(others) + 1)
                cols_ += [m + p, *others]
                vals += [1.0] + [-1.0] * len(others)
                lb.append(-np.inf)
                ub.append(0.0)
                r += 1
    a = coo_matrix((vals, (rows, cols_)), shape=(r, nvar)).tocsr()
    cons = LinearConstraint(a, np.array(lb), np.array(ub))
    c = np.concatenate([np.zeros(m), -pat.weights.astype(np.float64)])
    opts = {"time_limit": config.time_limit_s, "mip_rel_gap": 0.0, "disp": False}
    res = milp(c, integrality=np.ones(nvar), bounds=Bounds(0, 1), constraints=cons, options=opts)
    if res.x is None:
        return tuple(range(k)), _pattern_coverage(pat, range(k), min_views), False, None
    chosen = tuple(int(j) for j in np.flatnonzero(res.x[:m] > 0.5))
    cov = _pattern_coverage(pat, chosen, min_views)
    proven = res.status == 0
    bound = None
    dual = getattr(res, "mip_dual_bound", None)
    if dual is not None and np.isfinite(dual):
        bound = math.floor(-dual + 1e-6)
    if proven and m <= 40:
        # Tie-break among the optima: maximise sum 2^(M-1-j) o_j with coverage >= optimum.
        cov_row = np.concatenate([np.zeros(m), pat.weights.astype(np.float64)])
        cons2 = [cons, LinearConstraint(cov_row[None, :], cov - 0.5, np.inf)]
        c2 = np.concatenate([-(2.0 ** (m - 1 - np.arange(m))), np.zeros(kk)])
        res2 = milp(
            c2, integrality=np.ones(nvar), bounds=Bounds(0, 1), constraints=cons2, options=opts
        )
        if res2.status == 0 and res2.x is not None:
            chosen2 = tuple(int(j) for j in np.flatnonzero(res2.x[:m] > 0.5))
            if _pattern_coverage(pat, chosen2, min_views) == cov:
                chosen = chosen2
    return chosen, cov, proven, bound


# --------------------------------------------------------------------------- selector


class CameraSelector:
    """Solves P2 for one visibility matrix, lazily per subset size (results are cached, so the
    controller can ask for pi(N') only when its search reaches N').

    >>> vis = np.array([[1, 1, 0, 0], [1, 1, 0, 0], [0, 0, 1, 1], [1, 0, 1, 1]], bool)
    >>> CameraSelector(vis, SelectionConfig(min_cameras=2))(2)
    (0, 1)
    """

    def __init__(
        self,
        visibility: Visibility,
        config: SelectionConfig | None = None,
        *,
        available: Iterable[int] | None = None,
        camera_centers: NDArray[np.float64] | None = None,
        viewing_directions: NDArray[np.float64] | None = None,
    ) -> None:
        self.config = config or SelectionConfig()
        cfg = self.config
        self.timings = StageTimings()
        vis = _check_visibility(visibility)
        num_cameras = vis.shape[1]
        if camera_centers is not None:
            num_cameras = max(num_cameras, len(np.asarray(camera_centers).reshape(-1, 3)))
            if vis.shape[0] == 0 and vis.shape[1] != num_cameras:
                vis = np.zeros((0, num_cameras), bool)
        self.candidates = _check_candidates(available, num_cameras)
        if len(self.candidates) < cfg.min_cameras:
            raise DataError(
                f"camera selection needs at least {cfg.min_cameras} available cameras, got "
                f"{len(self.candidates)} ({list(self.candidates)})"
            )
        with self.timings.stage("aggregate"):
            pat = aggregate_patterns(vis, self.candidates, cfg.min_views)
        self.num_points = int(vis.shape[0])
        self.criterion: Literal["visibility", "geometric", "none"] = "visibility"
        if pat.num_patterns == 0:
            if camera_centers is not None:
                centers = np.asarray(camera_centers, np.float64).reshape(-1, 3)
                if len(centers) < num_cameras:
                    raise DataError(
                        f"camera_centers has {len(centers)} rows, expected {num_cameras}"
                    )
                logger.info(
                    "no point seen by %d available cameras (P = %d): selecting cameras by the "
                    "geometric criterion",
                    cfg.min_views,
                    vis.shape[0],
                )
                geo = geometric_visibility(centers, viewing_directions)
                vis = geo
                self.num_points = int(geo.shape[0])
                pat = aggregate_patterns(geo, self.candidates, cfg.min_views)
                self.criterion = "geometric"
            if pat.num_patterns == 0:
                logger.warning(
                    "camera selection without points or camera geometry: every subset ties, "
                    "choosing the lowest camera ids"
                )
                self.criterion = "none"
        self.patterns = pat
        self.num_coverable = pat.total_weight
        self._work: VisibilityPatterns | None = None
        self._cache: dict[int, Selection] = {}
        self._greedy: dict[int, tuple[int, ...]] | None = None

    # -- helpers
    @property
    def num_candidates(self) -> int:
        return len(self.candidates)

    def _ids(self, cols: Sequence[int]) -> tuple[int, ...]:
        return tuple(sorted(self.candidates[j] for j in cols))

    def _solver_for(self, k: int) -> str:
        cfg = self.config
        if cfg.solver != "auto":
            return cfg.solver
        m = self.num_candidates
        if self.criterion == "none" or self.patterns.num_patterns == 0:
            return "enumerate"
        if m <= cfg.brute_force_max_cameras:
            return "brute_force"
        if math.comb(m, k) * self.patterns.num_patterns <= cfg.enumerate_max_work:
            return "enumerate"
        return "local_search"

    def _working(self) -> VisibilityPatterns:
        """The patterns the ILP / enumeration solvers see (k-means key patterns when large)."""
        if self._work is None:
            cfg = self.config
            if cfg.max_key_points and self.patterns.num_patterns > cfg.max_key_points:
                with self.timings.stage("reduce"):
                    self._work = reduce_patterns_kmeans(
                        self.patterns, cfg.max_key_points, cfg.kmeans_iterations, cfg.seed
                    )
            else:
                self._work = self.patterns
        return self._work

    @property
    def num_key_points(self) -> int | None:
        if self._work is None or self._work is self.patterns:
            return None
        return self._work.num_patterns

    def _greedy_chain(self) -> dict[int, tuple[int, ...]]:
        if self._greedy is None:
            self._greedy = _reverse_greedy(self.patterns, self.config.min_views)
        return self._greedy

    def _check_size(self, k: int) -> None:
        if not self.config.min_cameras <= k <= self.num_candidates:
            raise ValueError(
                f"subset size N' = {k} out of range {self.config.min_cameras}.."
                f"{self.num_candidates} (available cameras: {list(self.candidates)})"
            )

    # -- public
    def selection(self, num_cameras: int) -> Selection:
        """The selection for N' = ``num_cameras`` (computed on first request)."""
        k = int(num_cameras)
        self._check_size(k)
        if k not in self._cache:
            solver = self._solver_for(k)
            with self.timings.stage("solve"):
                if solver == "brute_force":
                    self._solve_brute_force()
                else:
                    self._cache[k] = self._solve_one(k, solver)
        return self._cache[k]

    def __call__(self, num_cameras: int) -> tuple[int, ...]:
        return self.selection(num_cameras).camera_ids

    def mapping(self, sizes: Iterable[int] | None = None) -> CameraMapping:
        """pi(N') for ``sizes`` (default: every N' from the candidate count down to
        ``min_cameras``)."""
        ks = (
            range(self.num_candidates, self.config.min_cameras - 1, -1)
            if sizes is None
            else sorted({int(s) for s in sizes}, reverse=True)
        )
        sels = {k: self.selection(k) for k in ks}
        return CameraMapping(
            selections=sels,
            candidates=self.candidates,
            num_points=self.num_points,
            num_coverable=self.num_coverable,
            criterion=self.criterion,
            num_patterns=self.patterns.num_patterns,
            num_key_points=self.num_key_points,
            timings=StageTimings(dict(self.timings.seconds)),
        )

    def _solve_brute_force(self) -> None:
        m = self.num_candidates
        if m > BRUTE_FORCE_HARD_LIMIT:
            raise ValueError(
                f"brute force over {m} cameras needs 2^{m} entries; the limit is "
                f"{BRUTE_FORCE_HARD_LIMIT} cameras (use solver 'auto' or 'cpsat')"
            )
        t0 = time.perf_counter()
        res = _brute_force_all(self.patterns, self.config.min_views)
        dt = time.perf_counter() - t0
        for k in range(self.config.min_cameras, m + 1):
            cols, cov = res[k]
            self._cache.setdefault(
                k,
                Selection(
                    num_cameras=k,
                    camera_ids=self._ids(cols),
                    covered=cov,
                    solver="brute_force",
                    optimal=True,
                    upper_bound=cov,
                    seconds=dt,
                ),
            )

    def _solve_one(self, k: int, solver: str) -> Selection:
        cfg = self.config
        t0 = time.perf_counter()
        full = self.patterns
        mv = cfg.min_views
        if full.num_patterns == 0:
            cols = tuple(range(k))
            return Selection(
                num_cameras=k,
                camera_ids=self._ids(cols),
                covered=0,
                solver=solver,
                optimal=True,
                upper_bound=0,
                seconds=time.perf_counter() - t0,
            )
        if solver == "enumerate":
            # exact on the full patterns (auto only picks it when C(M, k) x K is small)
            cols, cov, _ = _enumerate_exact(full, k, mv)
            return Selection(
                num_cameras=k,
                camera_ids=self._ids(cols),
                covered=cov,
                solver=solver,
                optimal=True,
                upper_bound=cov,
                seconds=time.perf_counter() - t0,
            )
        # Iterated local search on the full patterns: the heuristic answer and the ILPs'
        # warm start.
        ls_cols, ls_cov = _iterated_local_search(
            full, self._greedy_chain()[k], mv, cfg.local_search_rounds, cfg.seed
        )
        if solver == "local_search":
            return Selection(
                num_cameras=k,
                camera_ids=self._ids(ls_cols),
                covered=ls_cov,
                solver=solver,
                optimal=ls_cov == self.num_coverable,
                upper_bound=self.num_coverable if ls_cov == self.num_coverable else None,
                seconds=time.perf_counter() - t0,
            )
        work = self._working()
        reduced = work is not full
        bound: int | None
        if solver == "cpsat":
            cols, _, proven, bound = _cpsat_solve(work, k, mv, cfg, hint=ls_cols)
        elif solver == "milp":
            cols, _, proven, bound = _milp_solve(work, k, mv, cfg)
        else:
            raise ValueError(f"unknown solver {solver!r}")
        cov = _pattern_coverage(full, cols, mv)
        optimal = proven and not reduced
        if not optimal and _better(ls_cov, self._ids(ls_cols), cov, self._ids(cols)):
            # the key-point (or time-limited) answer is worse on the full data than local search
            cols, cov = ls_cols, ls_cov
        if reduced:
            bound = None  # a bound on the key-point problem is not a bound on the full one
        elif proven:
            bound = cov
        return Selection(
            num_cameras=k,
            camera_ids=self._ids(cols),
            covered=cov,
            solver=solver + ("+keypoints" if reduced else ""),
            optimal=optimal or (bound is not None and cov >= bound),
            upper_bound=bound,
            seconds=time.perf_counter() - t0,
        )


def select_cameras(
    visibility: Visibility,
    num_cameras: int,
    config: SelectionConfig | None = None,
    *,
    available: Iterable[int] | None = None,
    camera_centers: NDArray[np.float64] | None = None,
    viewing_directions: NDArray[np.float64] | None = None,
) -> Selection:
    """Choose exactly ``num_cameras`` cameras maximising the points seen by >= 2 of them."""
    return CameraSelector(
        visibility,
        config,
        available=available,
        camera_centers=camera_centers,
        viewing_directions=viewing_directions,
    ).selection(num_cameras)


def camera_mapping(
    visibility: Visibility,
    config: SelectionConfig | None = None,
    *,
    available: Iterable[int] | None = None,
    camera_centers: NDArray[np.float64] | None = None,
    viewing_directions: NDArray[np.float64] | None = None,
    sizes: Iterable[int] | None = None,
) -> CameraMapping:
    """pi(N') for every N' from the number of available cameras down to ``min_cameras``."""
    return CameraSelector(
        visibility,
        config,
        available=available,
        camera_centers=camera_centers,
        viewing_directions=viewing_directions,
    ).mapping(sizes)
