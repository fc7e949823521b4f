"""Feature matching between camera pairs, guided by the KNOWN epipolar geometry.

With calibrated static cameras, a feature in view a can only match features of view b that lie
near its epipolar line, in front of both cameras. Applying this constraint *before* comparing
descriptors is what makes wide baselines work: a global nearest-neighbour ratio test compares
each feature with every feature of the other view and fails as soon as the viewpoint change
makes descriptors only moderately similar (COLMAP's exhaustive matching finds 3 points on
utrecht4cam frame 200); among the handful of features near an epipolar line, the correct one is
usually clearly the most similar.

Per camera pair (vectorised NumPy, no per-feature Python loop):

1. epipolar candidates: ``|l_b(x_a) . x_b| <= t`` with normalised lines, in both views, found by
   sorting the keypoints of b by their angle around the epipole (all epipolar lines pass
   through it) instead of testing every pair: 0.28 s -> 0.02 s for 3.5k x 3.5k keypoints;
2. cheirality and depth range: two-view midpoint triangulation of each candidate, depth in
   ``(min_depth, max_depth)`` in both cameras;
3. candidates are reduced to *locations* (SIFT's several orientations at one position count
   once, with the smallest descriptor distance);
4. ratio test among the candidates of each location in both directions, where the second best
   must lie at another position (more than ``_SAME_PLACE_PX`` away), an absolute descriptor
   distance bound, and mutual consistency;
5. the same ratio test against the keypoints *near* the match off the epipolar line
   (``neighbour_competitors``): a feature on a straight seam or a repeated texture has a single
   candidate on each epipolar line, so step 4 cannot see its ambiguity, but its neighbours
   along the seam look just like it.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from edgerecon.geometry.camera import Camera, fundamental_matrix
from edgerecon.sparse.config import DEFAULT_CONFIG, SparseConfig
from edgerecon.sparse.features import Features

logger = logging.getLogger(__name__)

#: Two keypoints closer than this (px) are treated as the same place in the ratio test.
_SAME_PLACE_PX = 2.0
#: Candidate pairs whose descriptors are compared at once (bounds the gathered memory).
_DESC_CHUNK = 4096  # small chunks reuse cached buffers: 2.5x faster than 128k here


@dataclass(frozen=True, kw_only=True, eq=False)
class PairMatches:
    """Matches between two views, as indices of unique keypoint locations."""

    view_a: int
    """Index of the first view (in the list given to the stage)."""
    view_b: int
    """Index of the second view."""
    location_a: NDArray[np.int64]
    """(M,) location index in view a (``Features.location_points2D``)."""
    location_b: NDArray[np.int64]
    """(M,) location index in view b."""
    distance: NDArray[np.float32]
    """(M,) descriptor distance of each match."""
    ratio: NDArray[np.float32]
    """(M,) best / second-best distance among the epipolar candidates (the larger of the two
    directions when ``mutual``); lower is more distinctive."""
    num_candidates: int = 0
    """Epipolar candidates (location pairs) before the ratio and mutual tests."""

    def __len__(self) -> int:
        return int(self.location_a.shape[0])


def select_pairs(
    cameras: Sequence[Camera], config: SparseConfig = DEFAULT_CONFIG
) -> list[tuple[int, int]]:
    """Index pairs (a < b) of the cameras worth matching: those whose optical axes are within
    ``max_pair_angle_deg`` of each other (all pairs by default)."""
    pairs = []
    cos_max = np.cos(np.radians(config.max_pair_angle_deg))
    for a in range(len(cameras)):
        for b in range(a + 1, len(cameras)):
            if config.max_pair_angle_deg < 180.0:
                cos = float(cameras[a].R[2] @ cameras[b].R[2])
                if cos < cos_max:
                    continue
            pairs.append((a, b))
    return pairs


def _normalised_lines(lines: NDArray[np.float64]) -> NDArray[np.float64]:
    n = np.hypot(lines[:, 0], lines[:, 1])
    return lines / np.maximum(n, 1e-300)[:, None]


def epipolar_candidates(
    points_a: NDArray[np.float64],
    points_b: NDArray[np.float64],
    F: NDArray[np.float64],
    threshold_px: float,
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """All index pairs (i, j) with ``points_b[j]`` within ``threshold_px`` of the epipolar line
    of ``points_a[i]`` and vice versa (``x_b^T F x_a = 0``).

    All epipolar lines of view b pass through its epipole, so a line is an angle and a point
    of b at distance r from the epipole lies within t of a line when their angles differ by at
    most asin(t / r). Points of b are binned by r (doubling shells) and sorted by angle in
    each shell; each line then takes a ``searchsorted`` range per shell. This superset costs
    O((N_a + N_b) log N_b + candidates) instead of the N_a x N_b distance matrix; the exact
    distances in both views are checked afterwards.
    """
    na, nb = len(points_a), len(points_b)
    empty = np.zeros(0, np.int64), np.zeros(0, np.int64)
    if na == 0 or nb == 0:
        return empty
    ha = np.hstack([points_a, np.ones((na, 1))])
    hb = np.hstack([points_b, np.ones((nb, 1))])
    raw_b = ha @ F.T
    valid = np.hypot(raw_b[:, 0], raw_b[:, 1]) > 1e-12 * np.abs(raw_b).max(initial=0.0)
    lines_b = _normalised_lines(raw_b)  # line in b of each point of a
    lines_a = _normalised_lines(hb @ F)  # line in a of each point of b
    ia, ib = _pencil_candidates(lines_b, valid, points_b, F, threshold_px)
    if len(ia) == 0:
        return empty
    # Exact checks in float64, both directions.
    d_b = np.abs(np.einsum("ij,ij->i", lines_b[ia], hb[ib]))
    d_a = np.abs(np.einsum("ij,ij->i", lines_a[ib], ha[ia]))
    keep = (d_b <= threshold_px) & (d_a <= threshold_px)
    return ia[keep], ib[keep]


def _pencil_candidates(
    lines_b: NDArray[np.float64],
    valid: NDArray[np.bool_],
    points_b: NDArray[np.float64],
    F: NDArray[np.float64],
    t: float,
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Superset of the (line, point) pairs of view b closer than ``t`` (see
    :func:`epipolar_candidates`)."""
    _, _, vt = np.linalg.svd(F.T)
    e = vt[-1]  # epipole of view b (F^T e = 0), homogeneous
    scale = float(np.abs(points_b).max()) + 1.0
    lines_idx = np.flatnonzero(valid)
    lines = lines_b[lines_idx]
    if abs(e[2]) * 1e6 <= np.hypot(e[0], e[1]) / scale:
        # Epipole at infinity: parallel lines, distance = difference of offsets along the
        # common normal (the lines' normals are +-n; orient them all the same way).
        n = lines[:, :2]
        sign = np.where(n @ n[0] < 0, -1.0, 1.0)
        offset = -lines[:, 2] * sign
        normal = n[0]
        keys = [(points_b @ normal, np.arange(len(points_b)), np.full(1, t))]
        query = offset
    else:
        ep = e[:2] / e[2]
        d = points_b - ep
        r = np.hypot(d[:, 0], d[:, 1])
        phi = np.mod(np.arctan2(d[:, 1], d[:, 0]), np.pi)
        # A line (a, b, c) through the epipole has direction (-b, a).
        query = np.mod(np.arctan2(lines[:, 0], -lines[:, 1]), np.pi)
        keys = []
        near = r <= t  # within t of every line through the epipole
        if np.any(near):
            idx = np.flatnonzero(near)
            keys.append((np.zeros(len(idx)), idx, np.full(1, np.inf)))
        r_far = r[~near]
        if len(r_far):
            k = np.floor(np.log2(r_far / t)).astype(np.int64)  # shell k: r in [t 2^k, t 2^(k+1))
            far_idx = np.flatnonzero(~near)
            for shell in np.unique(k):
                idx = far_idx[k == shell]
                half = float(np.arcsin(min(1.0, 1.0 / 2.0**shell)))
                # Angles are mod pi: replicate around the period so ranges never wrap.
                ang = phi[idx]
                keys.append(
                    (
                        np.concatenate([ang - np.pi, ang, ang + np.pi]),
                        np.concatenate([idx, idx, idx]),
                        np.full(1, half),
                    )
                )
    ia_parts, ib_parts = [], []
    for key, idx, half_arr in keys:
        half = float(half_arr[0])
        if not np.isfinite(half):  # candidates for every line
            ia_parts.append(np.repeat(lines_idx, len(idx)))
            ib_parts.append(np.tile(idx, len(lines_idx)))
            continue
        order = np.argsort(key, kind="stable")
        sk, si = key[order], idx[order]
        lo = np.searchsorted(sk, query - half, side="left")
        hi = np.searchsorted(sk, query + half, side="right")
        cnt = hi - lo
        total = int(cnt.sum())
        if total == 0:
            continue
        ia_parts.append(np.repeat(lines_idx, cnt))
        pos = np.arange(total) - np.repeat(np.cumsum(cnt) - cnt, cnt) + np.repeat(lo, cnt)
        ib_parts.append(si[pos])
    if not ia_parts:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    ia = np.concatenate(ia_parts).astype(np.int64)
    ib = np.concatenate(ib_parts).astype(np.int64)
    # A point replicated around the period can fall in a range twice only if half >= pi/2,
    # which the shells exclude (half = pi/2 for shell 0 is covered once by construction);
    # still, deduplicate cheaply to keep the contract exact.
    key = ia * len(points_b) + ib
    key, first = np.unique(key, return_index=True)
    return ia[first], ib[first]


def two_view_depths(
    cam_a: Camera,
    cam_b: Camera,
    points_a: NDArray[np.float64],
    points_b: NDArray[np.float64],
    index_a: NDArray[np.int64] | None = None,
    index_b: NDArray[np.int64] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Depths (along each optical axis) of the midpoint triangulation of pixel pairs; NaN for
    (near-)parallel rays.

    Pairs are ``(points_a[k], points_b[k])``, or ``(points_a[index_a[k]],
    points_b[index_b[k]])`` when indices are given (per-point terms are then computed once).
    """
    ra = cam_a.pixel_rays(points_a) @ cam_a.R  # world directions with camera z = 1
    rb = cam_b.pixel_rays(points_b) @ cam_b.R
    w0 = cam_a.center - cam_b.center
    a, d = np.einsum("ij,ij->i", ra, ra), ra @ w0
    c, e = np.einsum("ij,ij->i", rb, rb), rb @ w0
    if index_a is not None and index_b is not None:
        ra, rb = ra[index_a], rb[index_b]
        a, d, c, e = a[index_a], d[index_a], c[index_b], e[index_b]
    b = np.einsum("ij,ij->i", ra, rb)
    denom = a * c - b * b
    ok = denom > 1e-12 * a * c
    denom = np.where(ok, denom, 1.0)
    s = np.where(ok, (b * e - c * d) / denom, np.nan)
    u = np.where(ok, (a * e - b * d) / denom, np.nan)
    return s, u


def _descriptor_distances(
    da: NDArray[np.float32], db: NDArray[np.float32], ia: NDArray[np.int64], ib: NDArray[np.int64]
) -> NDArray[np.float32]:
    out = np.empty(len(ia), np.float32)
    for s in range(0, len(ia), _DESC_CHUNK):
        sl = slice(s, s + _DESC_CHUNK)
        dots = np.einsum("ij,ij->i", da[ia[sl]], db[ib[sl]])
        out[sl] = np.sqrt(np.maximum(2.0 - 2.0 * dots, 0.0))
    return out


def _best_with_ratio(
    key: NDArray[np.int64],
    other: NDArray[np.int64],
    dist: NDArray[np.float32],
    other_points: NDArray[np.float64],
    ratio: float,
    max_distance: float,
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float32], NDArray[np.float32]]:
    """For each distinct ``key``: its best ``other`` if it passes the ratio test (second best
    at another place) and the distance bound. Returns (key, other, distance, ratio) of the
    winners."""
    # One argsort on a combined key: by key, then by distance (distances are < 2).
    order = np.argsort(key + dist.astype(np.float64) * 0.25, kind="stable")
    k, o, d = key[order], other[order], dist[order]
    first = np.ones(len(k), bool)
    first[1:] = k[1:] != k[:-1]
    group = np.cumsum(first) - 1
    best_o = o[first]
    best_d = d[first]
    far = np.linalg.norm(other_points[o] - other_points[best_o[group]], axis=1) > _SAME_PLACE_PX
    second = np.full(len(best_o), np.inf, np.float32)
    gi = group[far]
    # Sorted by distance within a group: the first far entry is the second best.
    first_far = np.ones(len(gi), bool)
    first_far[1:] = gi[1:] != gi[:-1]
    second[gi[first_far]] = d[far][first_far]
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(np.isfinite(second), best_d / second, 0.0).astype(np.float32)
    ok = (best_d <= max_distance) & (r < ratio)
    return k[first][ok], best_o[ok], best_d[ok], r[ok]


def match_pair(
    feats_a: Features,
    feats_b: Features,
    cam_a: Camera,
    cam_b: Camera,
    config: SparseConfig = DEFAULT_CONFIG,
    view_a: int = 0,
    view_b: int = 1,
) -> PairMatches:
    """Epipolar-guided matches between two views (see the module docstring)."""
    empty = PairMatches(
        view_a=view_a,
        view_b=view_b,
        location_a=np.zeros(0, np.int64),
        location_b=np.zeros(0, np.int64),
        distance=np.zeros(0, np.float32),
        ratio=np.zeros(0, np.float32),
    )
    if len(feats_a) == 0 or len(feats_b) == 0:
        return empty
    baseline = float(np.linalg.norm(cam_a.center - cam_b.center))
    if not baseline > 1e-9 * (1.0 + float(np.linalg.norm(cam_a.center))):
        return empty  # same centre: no epipolar geometry, nothing to triangulate
    F = fundamental_matrix(cam_a, cam_b)
    # Epipolar geometry is a property of locations: test unique positions only.
    la, lb = epipolar_candidates(
        feats_a.location_points2D, feats_b.location_points2D, F, config.epipolar_threshold_px
    )
    if len(la):
        sa, sb = two_view_depths(
            cam_a, cam_b, feats_a.location_points2D, feats_b.location_points2D, la, lb
        )
        with np.errstate(invalid="ignore"):
            ok = (
                (sa > config.min_depth)
                & (sb > config.min_depth)
                & (sa < config.max_depth)
                & (sb < config.max_depth)
            )
        la, lb = la[ok], lb[ok]
    if len(la) == 0:
        return empty
    num_candidates = len(la)
    # Expand location pairs to feature pairs (several orientations per location).
    fa_of = _features_of_locations(feats_a)
    fb_of = _features_of_locations(feats_b)
    ia, ib, pair = _expand(la, lb, fa_of, fb_of)
    dist = _descriptor_distances(feats_a.descriptors, feats_b.descriptors, ia, ib)
    # Candidates farther than max_distance / ratio can neither win nor change a ratio test's
    # outcome (a second best above it passes any best <= max_distance): drop them early.
    near = dist <= config.max_descriptor_distance / min(config.ratio, config.two_view_ratio)
    ia, ib, pair, dist = ia[near], ib[near], pair[near], dist[near]
    # Smallest distance per location pair.
    order = np.argsort(pair + dist.astype(np.float64) * 0.25, kind="stable")
    pair_s, dist_s = pair[order], dist[order]
    first = np.ones(len(pair_s), bool)
    first[1:] = pair_s[1:] != pair_s[:-1]
    la, lb, dist = la[pair_s[first]], lb[pair_s[first]], dist_s[first]
    fa, fb, fd, fr = _best_with_ratio(
        la, lb, dist, feats_b.location_points2D, config.ratio, config.max_descriptor_distance
    )
    if config.mutual:
        gb, ga, _, gr = _best_with_ratio(
            lb, la, dist, feats_a.location_points2D, config.ratio, config.max_descriptor_distance
        )
        nb = feats_b.num_locations
        fwd, bwd = fa * nb + fb, ga * nb + gb
        order = np.argsort(bwd)
        pos = np.clip(np.searchsorted(bwd[order], fwd), 0, max(len(bwd) - 1, 0))
        both = (bwd[order][pos] == fwd) if len(bwd) else np.zeros(len(fwd), bool)
        fr = np.maximum(fr, gr[order][pos]) if len(bwd) else fr
        fa, fb, fd, fr = fa[both], fb[both], fd[both], fr[both]
    if config.neighbour_competitors > 0 and len(fa):
        # Look-alikes *near* the match but off the epipolar line (a line feature, a repeated
        # texture) make the match ambiguous even when the line holds no competitor.
        k = config.neighbour_competitors
        rad_a = config.neighbour_radius * float(np.hypot(cam_a.width, cam_a.height))
        rad_b = config.neighbour_radius * float(np.hypot(cam_b.width, cam_b.height))
        r_b = _local_ratio(fa, fb, fd, feats_a, feats_b, fa_of, fb_of, k, rad_b)
        r_a = _local_ratio(fb, fa, fd, feats_b, feats_a, fb_of, fa_of, k, rad_a)
        fr = np.maximum(fr, np.maximum(r_a, r_b)).astype(np.float32)
        ok = fr < config.ratio
        fa, fb, fd, fr = fa[ok], fb[ok], fd[ok], fr[ok]
    return PairMatches(
        view_a=view_a,
        view_b=view_b,
        location_a=fa,
        location_b=fb,
        distance=fd,
        ratio=fr,
        num_candidates=num_candidates,
    )


def _local_ratio(
    loc_a: NDArray[np.int64],
    loc_b: NDArray[np.int64],
    dist: NDArray[np.float32],
    feats_a: Features,
    feats_b: Features,
    fa_of: tuple[NDArray[np.int64], NDArray[np.int64]],
    fb_of: tuple[NDArray[np.int64], NDArray[np.int64]],
    k: int,
    radius: float,
) -> NDArray[np.float32]:
    """(M,) match distance / smallest distance from a's descriptors to the ``k`` locations of
    b nearest to the matched one within ``radius`` px (excluding the same place)."""
    pts_b = feats_b.location_points2D
    dd, nn = cKDTree(pts_b).query(
        pts_b[loc_b], k=min(k + 1, len(pts_b)), distance_upper_bound=radius
    )
    dd, nn = dd.reshape(len(loc_b), -1), nn.reshape(len(loc_b), -1)
    valid = np.isfinite(dd) & (dd > _SAME_PLACE_PX)
    rows, cols = np.nonzero(valid)
    out = np.zeros(len(loc_b), np.float32)
    if len(rows) == 0:
        return out
    la, lb = loc_a[rows], nn[rows, cols].astype(np.int64)
    ia, ib, pair = _expand(la, lb, fa_of, fb_of)
    d = _descriptor_distances(feats_a.descriptors, feats_b.descriptors, ia, ib)
    best = np.full(len(la), np.inf, np.float32)
    np.minimum.at(best, pair, d)
    second = np.full(len(loc_b), np.inf, np.float32)
    np.minimum.at(second, rows, best)
    with np.errstate(divide="ignore"):
        out = np.where(np.isfinite(second), dist / second, 0.0).astype(np.float32)
    return out


def _features_of_locations(feats: Features) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """CSR-style (offsets, feature indices) listing the features of each location."""
    order = np.argsort(feats.location, kind="stable")
    counts = np.bincount(feats.location, minlength=feats.num_locations)
    offsets = np.concatenate([[0], np.cumsum(counts)])
    return offsets, order


def _expand(
    la: NDArray[np.int64],
    lb: NDArray[np.int64],
    fa_of: tuple[NDArray[np.int64], NDArray[np.int64]],
    fb_of: tuple[NDArray[np.int64], NDArray[np.int64]],
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """All feature pairs (ia, ib) of location pairs (la, lb), with the location pair's index."""
    off_a, fa = fa_of
    off_b, fb = fb_of
    ca = off_a[la + 1] - off_a[la]
    cb = off_b[lb + 1] - off_b[lb]
    n = ca * cb
    pair = np.repeat(np.arange(len(la)), n)
    within = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
    cbr = np.repeat(cb, n)
    ia = fa[off_a[la][pair] + within // cbr]
    ib = fb[off_b[lb][pair] + within % cbr]
    return ia, ib, pair
