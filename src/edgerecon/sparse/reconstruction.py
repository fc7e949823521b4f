"""Sparse reconstruction with known poses: features -> epipolar matching -> tracks ->
triangulation -> filters -> guided track extension -> coloured points with visibility."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from edgerecon.geometry.camera import Camera
from edgerecon.sparse.config import DEFAULT_CONFIG, SparseConfig
from edgerecon.sparse.features import Features, extract_all
from edgerecon.sparse.matching import PairMatches, match_pair, select_pairs
from edgerecon.sparse.tracks import Tracks, build_tracks
from edgerecon.sparse.triangulation import (
    max_triangulation_angle_deg,
    project_all,
    refine_points,
    reprojection_errors,
    triangulate_dlt,
)
from edgerecon.threads import thread_map
from edgerecon.types import Colors, DataError, PointCloud, Points2D, StageTimings
from edgerecon.views import View

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True, eq=False)
class SparseReconstruction:
    """Result of :func:`reconstruct_sparse`: triangulated points, who sees them, how well.

    Views are indexed 0..V-1 in the order given to the stage; ``camera_ids[n]`` is the rig id
    of view n. Point k's observations are the rows of the ``observation_*`` arrays with
    ``observation_point_ids == k``.
    """

    cloud: PointCloud
    """Points (rig units), RGB colours averaged over the observing views, and
    ``attributes["num_views"]`` (int32, number of observing views)."""
    camera_ids: tuple[int, ...]
    """Rig camera id of each view given to the stage."""
    visibility: NDArray[np.bool_]
    """(P, V) True where point k is observed by view n (the point-camera matrix A)."""
    observation_point_ids: NDArray[np.int64]
    """(M,) point index of each observation."""
    observation_view_ids: NDArray[np.int64]
    """(M,) view index (0..V-1) of each observation."""
    observation_points2D: Points2D
    """(M, 2) observed pixel (keypoint position in the view)."""
    reprojection_error_px: NDArray[np.float64]
    """(P,) mean reprojection error of each point over its observations, pixels."""
    triangulation_angle_deg: NDArray[np.float64]
    """(P,) largest angle between two observing rays of each point, degrees."""
    timings: StageTimings = field(default_factory=StageTimings)
    """Seconds of the stages ``features``, ``matching``, ``triangulation``."""
    stats: dict[str, Any] = field(default_factory=dict)
    """Counts: features per view, matches per pair, tracks, points rejected by each filter."""

    def __len__(self) -> int:
        return len(self.cloud)

    @property
    def num_points(self) -> int:
        return len(self.cloud)

    @property
    def points3D(self) -> NDArray[np.float64]:
        return self.cloud.points3D

    def visibility_matrix(self, num_cameras: int) -> NDArray[np.bool_]:
        """(P, num_cameras) visibility indexed by rig camera id (False for cameras that were
        not part of this reconstruction)."""
        if self.camera_ids and max(self.camera_ids) >= num_cameras:
            raise ValueError(
                f"num_cameras = {num_cameras} but this reconstruction uses camera id "
                f"{max(self.camera_ids)}"
            )
        out = np.zeros((self.num_points, num_cameras), bool)
        out[:, list(self.camera_ids)] = self.visibility
        return out

    def select(self, index: NDArray[Any]) -> SparseReconstruction:
        """The reconstruction restricted to the points at a boolean mask or index array
        (observations follow; timings and stats are kept)."""
        idx = np.arange(self.num_points)[index]
        new_id = np.full(self.num_points, -1, np.int64)
        new_id[idx] = np.arange(len(idx))
        keep = new_id[self.observation_point_ids] >= 0
        return SparseReconstruction(
            cloud=self.cloud.select(idx),
            camera_ids=self.camera_ids,
            visibility=self.visibility[idx],
            observation_point_ids=new_id[self.observation_point_ids[keep]],
            observation_view_ids=self.observation_view_ids[keep],
            observation_points2D=self.observation_points2D[keep],
            reprojection_error_px=self.reprojection_error_px[idx],
            triangulation_angle_deg=self.triangulation_angle_deg[idx],
            timings=self.timings,
            stats=dict(self.stats),
        )

    @classmethod
    def empty(
        cls,
        camera_ids: Sequence[int] = (),
        timings: StageTimings | None = None,
        stats: dict[str, Any] | None = None,
    ) -> SparseReconstruction:
        return cls(
            cloud=PointCloud(
                points3D=np.zeros((0, 3)),
                colors=np.zeros((0, 3), np.uint8),
                attributes={"num_views": np.zeros(0, np.int32)},
            ),
            camera_ids=tuple(int(i) for i in camera_ids),
            visibility=np.zeros((0, len(camera_ids)), bool),
            observation_point_ids=np.zeros(0, np.int64),
            observation_view_ids=np.zeros(0, np.int64),
            observation_points2D=np.zeros((0, 2)),
            reprojection_error_px=np.zeros(0),
            triangulation_angle_deg=np.zeros(0),
            timings=timings or StageTimings(),
            stats=stats or {},
        )


def _check_views(views: Sequence[View]) -> None:
    ids = [v.camera_id for v in views]
    if len(set(ids)) != len(ids):
        raise ValueError(f"reconstruct_sparse: duplicate camera ids in views: {ids}")
    for v in views:
        image = np.asarray(v.image)
        if (
            image.dtype != np.uint8
            or image.ndim not in (2, 3)
            or (image.ndim == 3 and image.shape[2] != 3)
        ):
            raise DataError(
                f"view {v.name!r} (camera {v.camera_id}): images must be 8-bit BGR (H, W, 3) "
                f"or grey (H, W), got {image.dtype} {image.shape}"
            )


def reconstruct_sparse(
    views: Sequence[View], config: SparseConfig = DEFAULT_CONFIG
) -> SparseReconstruction:
    """Sparse coloured points of a task's views, triangulated with their known poses.

    Fewer than two views, or no consistent matches, give an empty reconstruction (a value,
    not an error). Features are only taken inside each view's mask when it has one.
    """
    _check_views(views)
    camera_ids = tuple(v.camera_id for v in views)
    timings = StageTimings()
    stats: dict[str, Any] = {"num_views": len(views)}
    if len(views) < 2:
        return SparseReconstruction.empty(camera_ids, timings, stats | {"num_points": 0})
    cameras = [v.camera for v in views]

    with timings.stage("features"):
        feats = extract_all(views, config)
    stats["features_per_view"] = {cid: len(f) for cid, f in zip(camera_ids, feats, strict=True)}

    with timings.stage("matching"):
        pairs = select_pairs(cameras, config)
        matches = _match_pairs(feats, cameras, pairs, config)
    stats["candidates_per_pair"] = {
        f"{camera_ids[m.view_a]}-{camera_ids[m.view_b]}": m.num_candidates for m in matches
    }
    stats["matches_per_pair"] = {
        f"{camera_ids[m.view_a]}-{camera_ids[m.view_b]}": len(m) for m in matches
    }

    with timings.stage("triangulation"):
        tracks = build_tracks(
            [f.num_locations for f in feats], matches, strict_ratio=config.two_view_ratio
        )
        stats["num_tracks"] = len(tracks)
        stats["num_conflicting_tracks"] = tracks.num_conflicting
        stats["num_recovered_tracks"] = tracks.num_recovered
        result = _triangulate(views, cameras, feats, tracks, config, stats)
    if result is None:
        stats["num_points"] = 0
        return SparseReconstruction.empty(camera_ids, timings, stats)
    X, locations, err, angle = result
    observed = locations >= 0
    pts2d = _gather_points(feats, locations)
    t_idx, v_idx = np.nonzero(observed)
    colors = _colors(views, pts2d, observed)
    stats["num_points"] = len(X)
    stats["observations_per_point"] = float(observed.sum(axis=1).mean()) if len(X) else 0.0
    logger.debug("sparse: %s", stats)
    return SparseReconstruction(
        cloud=PointCloud(
            points3D=X,
            colors=colors,
            attributes={"num_views": observed.sum(axis=1).astype(np.int32)},
        ),
        camera_ids=camera_ids,
        visibility=observed,
        observation_point_ids=t_idx.astype(np.int64),
        observation_view_ids=v_idx.astype(np.int64),
        observation_points2D=pts2d[t_idx, v_idx],
        reprojection_error_px=err,
        triangulation_angle_deg=angle,
        timings=timings,
        stats=stats,
    )


def _match_pairs(
    feats: Sequence[Features],
    cameras: Sequence[Camera],
    pairs: Sequence[tuple[int, int]],
    config: SparseConfig,
) -> list[PairMatches]:
    def one(p: tuple[int, int]) -> PairMatches:
        a, b = p
        return match_pair(feats[a], feats[b], cameras[a], cameras[b], config, a, b)

    return thread_map(one, pairs, config.num_threads)


def _gather_points(feats: Sequence[Features], locations: NDArray[np.int64]) -> NDArray[np.float64]:
    """(T, V, 2) pixel of each track's location in each view (NaN where not observed)."""
    T, V = locations.shape
    pts = np.full((T, V, 2), np.nan)
    for v in range(V):
        obs = locations[:, v] >= 0
        pts[obs, v] = feats[v].location_points2D[locations[obs, v]]
    return pts


def _triangulate(
    views: Sequence[View],
    cameras: Sequence[Camera],
    feats: Sequence[Features],
    tracks: Tracks,
    config: SparseConfig,
    stats: dict[str, Any],
) -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]] | None:
    if len(tracks) == 0:
        return None
    locations = tracks.locations.copy()
    ratio = tracks.ratio if tracks.ratio is not None else np.zeros(len(tracks), np.float32)
    X = np.zeros((0, 3))
    dropped_obs = 0
    # Two rounds: triangulate, drop observations that do not fit, re-triangulate the rest.
    for _ in range(2):
        observed = locations >= 0
        pts = _gather_points(feats, locations)
        X = triangulate_dlt(cameras, pts, observed)
        X = refine_points(cameras, X, pts, observed, config.refine_iterations)
        err, _ = reprojection_errors(cameras, X, pts, observed)
        bad = observed & ~(err <= config.max_reprojection_error_px)
        if not np.any(bad):
            break
        dropped_obs += int(np.count_nonzero(bad))
        locations[bad] = -1
    stats["dropped_observations"] = dropped_obs
    observed = locations >= 0
    enough = observed.sum(axis=1) >= 2
    stats["rejected_reprojection"] = int(np.count_nonzero(~enough))
    keep = enough & np.all(np.isfinite(X), axis=1)
    locations, X, ratio = locations[keep], X[keep], ratio[keep]

    if config.guided_matching and len(X):
        locations, X, added = _extend_tracks(views, cameras, feats, locations, X, config)
        stats["guided_observations"] = added

    observed = locations >= 0
    pts = _gather_points(feats, locations)
    err, depth = reprojection_errors(cameras, X, pts, observed)
    cheiral = np.all(~observed | (depth > config.min_depth), axis=1)
    angle = max_triangulation_angle_deg(cameras, X, observed)
    wide = angle >= config.min_triangulation_angle_deg
    fits = np.all(~observed | (err <= config.max_reprojection_error_px), axis=1)
    stats["rejected_cheirality"] = int(np.count_nonzero(~cheiral))
    stats["rejected_angle"] = int(np.count_nonzero(cheiral & ~wide))
    # Two-view points have nothing but their match to vouch for them: stricter ratio.
    two = observed.sum(axis=1) == 2
    confirmed = ~two | (ratio <= config.two_view_ratio)
    stats["rejected_two_view_ratio"] = int(np.count_nonzero(cheiral & wide & fits & ~confirmed))
    keep = cheiral & wide & fits & confirmed
    if config.confirm_angle_deg > 0:
        between = _has_view_between(
            views, cameras, X, observed, keep & two, config.confirm_angle_deg
        )
        stats["rejected_unconfirmed_between"] = int(np.count_nonzero(between))
        keep &= ~between
    if not np.any(keep):
        return None
    mean_err = np.nanmean(np.where(observed, err, np.nan), axis=1)
    return X[keep], locations[keep], mean_err[keep], angle[keep]


def _has_view_between(
    views: Sequence[View],
    cameras: Sequence[Camera],
    X: NDArray[np.float64],
    observed: NDArray[np.bool_],
    candidates: NDArray[np.bool_],
    max_angle_deg: float,
) -> NDArray[np.bool_]:
    """(T,) True for candidate points seen by exactly two views a, b when a third view c sees
    the point (in front, inside its image and mask) from *between* them: its ray is closer in
    angle to both a's and b's than they are to each other, and within ``max_angle_deg`` of
    both. Such a view has a viewpoint similar enough to both to have matched the point too; if
    it did not (guided matching included), the pair's match is more likely wrong than the point
    occluded in c. (Measured on the synthetic 7-camera arc: two-view points of non-adjacent
    pairs were ~50% wrong, those of adjacent pairs ~9%.)"""
    out = np.zeros(len(X), bool)
    idx = np.flatnonzero(candidates)
    if len(idx) == 0:
        return out
    Xs = X[idx]
    obs = observed[idx]
    centres = np.array([c.center for c in cameras])
    rays = centres[None] - Xs[:, None]  # (n, V, 3) from the point to each camera
    rays /= np.linalg.norm(rays, axis=2, keepdims=True)
    order = np.argsort(~obs, axis=1, kind="stable")[:, :2]  # the two observing views
    rows = np.arange(len(idx))
    ra, rb = rays[rows, order[:, 0]], rays[rows, order[:, 1]]
    cos_ab = np.einsum("ij,ij->i", ra, rb)
    cos_ca = np.einsum("ivj,ij->iv", rays, ra)
    cos_cb = np.einsum("ivj,ij->iv", rays, rb)
    cos_max = np.cos(np.radians(max_angle_deg))
    closer = np.maximum(cos_ab[:, None], cos_max)
    between = (cos_ca > closer) & (cos_cb > closer) & ~obs
    uv, z = project_all(cameras, Xs)
    for v, cam in enumerate(cameras):
        sees = (z[:, v] > 0) & cam.in_image(uv[:, v], margin=2.0)
        mask = views[v].mask
        if mask is not None:
            px = np.clip(
                np.rint(np.nan_to_num(uv[:, v])).astype(np.int64),
                0,
                [cam.width - 1, cam.height - 1],
            )
            sees &= mask[px[:, 1], px[:, 0]]
        between[:, v] &= sees
    out[idx] = between.any(axis=1)
    return out


def _extend_tracks(
    views: Sequence[View],
    cameras: Sequence[Camera],
    feats: Sequence[Features],
    locations: NDArray[np.int64],
    X: NDArray[np.float64],
    config: SparseConfig,
) -> tuple[NDArray[np.int64], NDArray[np.float64], int]:
    """Add observations in views that do not observe a point: the nearest keypoint location
    within ``guided_radius_px`` of the projection whose descriptor is close to one of the
    track's, and that no other track uses. Points are re-refined; additions that end up
    farther than the reprojection threshold are dropped again."""
    V = locations.shape[1]
    uv, z = project_all(cameras, X)
    rep = [_representative_descriptors(f) for f in feats]
    added = 0
    new_locations = locations.copy()
    for v in range(V):
        f = feats[v]
        if f.num_locations == 0:
            continue
        todo = (locations[:, v] < 0) & (z[:, v] > 0) & cameras[v].in_image(uv[:, v])
        mask = views[v].mask
        if mask is not None:
            idx = np.flatnonzero(todo)
            px = np.clip(
                np.rint(uv[idx, v]).astype(np.int64),
                0,
                [cameras[v].width - 1, cameras[v].height - 1],
            )
            todo[idx] = mask[px[:, 1], px[:, 0]]
        idx = np.flatnonzero(todo)
        if len(idx) == 0:
            continue
        dist, loc = cKDTree(f.location_points2D).query(
            uv[idx, v], k=1, distance_upper_bound=config.guided_radius_px
        )
        found = np.isfinite(dist)
        idx, loc = idx[found], loc[found].astype(np.int64)
        used = np.zeros(f.num_locations, bool)
        used[locations[locations[:, v] >= 0, v]] = True
        free = ~used[loc]
        idx, loc = idx[free], loc[free]
        # Claimed by a single point only.
        uniq, counts = np.unique(loc, return_counts=True)
        single = np.isin(loc, uniq[counts == 1])
        idx, loc = idx[single], loc[single]
        if len(idx) == 0:
            continue
        # Descriptor of the candidate against the track's descriptors in its other views.
        best = np.full(len(idx), np.inf)
        for w in range(V):
            lw = locations[idx, w]
            has = lw >= 0
            if not np.any(has):
                continue
            dots = np.einsum("ij,ij->i", rep[v][loc[has]], rep[w][lw[has]])
            best[has] = np.minimum(best[has], np.sqrt(np.maximum(2 - 2 * dots, 0)))
        ok = best <= config.guided_max_descriptor_distance
        new_locations[idx[ok], v] = loc[ok]
        added += int(np.count_nonzero(ok))
    if added == 0:
        return locations, X, 0
    observed = new_locations >= 0
    pts = _gather_points(feats, new_locations)
    X2 = refine_points(cameras, X, pts, observed, config.refine_iterations)
    err, _ = reprojection_errors(cameras, X2, pts, observed)
    # Keep the extended point only if all its observations still fit; else the old one.
    fits = np.all(~observed | (err <= config.max_reprojection_error_px), axis=1)
    changed = np.any(new_locations != locations, axis=1)
    take = changed & fits
    added = int(np.count_nonzero(new_locations[take] != locations[take]))
    locations = np.where(take[:, None], new_locations, locations)
    X = np.where(take[:, None], X2, X)
    return locations, X, added


def _representative_descriptors(feats: Features) -> NDArray[np.float32]:
    """(L, 128) descriptor of the first keypoint at each location."""
    rep = np.zeros((feats.num_locations, 128), np.float32)
    rep[feats.location[::-1]] = feats.descriptors[::-1]
    return rep


def _colors(views: Sequence[View], pts: NDArray[np.float64], observed: NDArray[np.bool_]) -> Colors:
    """RGB colour of each point: mean over its observing views of the bilinear sample."""
    T, V = observed.shape
    acc = np.zeros((T, 3))
    for v in range(V):
        obs = observed[:, v]
        if not np.any(obs):
            continue
        p = pts[obs, v].astype(np.float32)
        # remap maps must stay below 32767 rows and columns: lay the samples out in rows.
        n = len(p)
        width = 1024
        rows = -(-n // width)
        grid = np.zeros((rows * width, 2), np.float32)
        grid[:n] = p
        image: NDArray[Any] = views[v].image
        if image.ndim == 2:
            image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        sample = cv2.remap(
            image,
            grid[:, 0].reshape(rows, width),
            grid[:, 1].reshape(rows, width),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        ).reshape(-1, 3)[:n]
        acc[obs] += sample[:, ::-1]
    n = np.maximum(observed.sum(axis=1), 1)[:, None]
    return np.clip(np.rint(acc / n), 0, 255).astype(np.uint8)
