"""Board check on real data: calibration-board corners as a metric reference for a dense cloud.

A real capture has no ground-truth cloud, but a calibration board held in the scene is a
surface whose points are known well: its corners, detected in several calibrated views and
triangulated, lie on the board to a fraction of a millimetre. A dense cloud that reconstructs
the board has a point close to each corner; the distance from each corner to its nearest dense
point is the check (``caliscope_charuco/checks/charuco_corners_2d.csv``: ChArUco corners found
by OpenCV, one row per detection).

The corners also give the board's plane, so the board is a precision check as well
(``board_surface``): the dense points over the area the corners span should lie on that plane,
and their distances to it show how noisy the cloud is on a real, textured surface.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from edgerecon.geometry.camera import Rig
from edgerecon.sparse.triangulation import (
    project_all,
    refine_points,
    triangulate_dlt,
)
from edgerecon.types import DataError, PointCloud, Points3D


@dataclass(frozen=True, kw_only=True, eq=False)
class CornerDetections:
    """Board corners detected in the views: one row per (time, camera, corner)."""

    time_index: NDArray[np.int64]
    """(M,) time index of each detection."""
    camera: NDArray[np.int64]
    """(M,) rig index of the camera."""
    corner_id: NDArray[np.int64]
    """(M,) the board's corner id."""
    points2D: NDArray[np.float64]
    """(M, 2) detected position, pixels of the (distorted) camera image."""

    def __len__(self) -> int:
        return int(self.time_index.shape[0])


def read_corner_csv(path: str | Path, rig: Rig) -> CornerDetections:
    """Read ``time_index,camera,corner_id,x_px,y_px`` rows (camera = a rig camera name)."""
    rows = []
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        need = {"time_index", "camera", "corner_id", "x_px", "y_px"}
        if reader.fieldnames is None or not need <= set(reader.fieldnames):
            raise DataError(f"{path}: needs the columns {sorted(need)}, got {reader.fieldnames}")
        for r in reader:
            try:
                cam = rig.index(r["camera"])
            except (KeyError, ValueError, IndexError) as exc:
                raise DataError(f"{path}: camera {r['camera']!r} is not in the rig") from exc
            rows.append(
                (int(r["time_index"]), cam, int(r["corner_id"]), float(r["x_px"]), float(r["y_px"]))
            )
    a = np.array(rows, dtype=np.float64).reshape(-1, 5)
    return CornerDetections(
        time_index=a[:, 0].astype(np.int64),
        camera=a[:, 1].astype(np.int64),
        corner_id=a[:, 2].astype(np.int64),
        points2D=a[:, 3:5],
    )


@dataclass(frozen=True, kw_only=True, eq=False)
class BoardCorners:
    """Corners triangulated at one time index."""

    corner_id: NDArray[np.int64]
    """(C,) corner ids."""
    points3D: Points3D
    """(C, 3) triangulated positions, rig units."""
    num_views: NDArray[np.int64]
    """(C,) number of views that detected each corner."""
    reprojection_error_px: NDArray[np.float64]
    """(C,) mean reprojection error over those views (undistorted pixels)."""

    def __len__(self) -> int:
        return int(self.corner_id.shape[0])


def triangulate_corners(
    detections: CornerDetections, rig: Rig, time_index: int, min_views: int = 2
) -> BoardCorners:
    """Multi-view DLT (then a few Gauss-Newton steps on the reprojection error) of every corner
    detected by at least ``min_views`` cameras at ``time_index``; detections are undistorted
    with the rig's calibration first. No corners -> an empty result."""
    sel = detections.time_index == time_index
    ids = np.unique(detections.corner_id[sel])
    V = len(rig)
    pix = np.full((len(ids), V, 2), np.nan)
    observed = np.zeros((len(ids), V), bool)
    cams = [c.undistorted() for c in rig]
    row = np.searchsorted(ids, detections.corner_id[sel])
    for v in range(V):
        here = detections.camera[sel] == v
        if not here.any():
            continue
        rays = rig[v].pixel_rays(detections.points2D[sel][here])
        uv = rays @ cams[v].K.T
        pix[row[here], v] = uv[:, :2]
        observed[row[here], v] = True
    keep = observed.sum(axis=1) >= min_views
    ids, pix, observed = ids[keep], pix[keep], observed[keep]
    if len(ids) == 0:
        return BoardCorners(
            corner_id=ids,
            points3D=np.zeros((0, 3)),
            num_views=np.zeros(0, np.int64),
            reprojection_error_px=np.zeros(0),
        )
    X = triangulate_dlt(cams, pix, observed)
    X = refine_points(cams, X, pix, observed, iterations=5)
    uv, _ = project_all(cams, X)
    err = np.linalg.norm(uv - pix, axis=2)
    err = np.where(observed, err, 0.0).sum(axis=1) / observed.sum(axis=1)
    return BoardCorners(
        corner_id=ids,
        points3D=X,
        num_views=observed.sum(axis=1).astype(np.int64),
        reprojection_error_px=err,
    )


@dataclass(frozen=True, kw_only=True)
class BoardCheck:
    """Distances of the board's corners to the nearest point of a dense cloud."""

    time_index: int
    num_corners: int
    distances: NDArray[np.float64]
    """(C,) corner -> nearest dense point, rig units (inf for an empty cloud)."""
    median: float
    max: float
    board_rms: float
    """RMS distance of the corners to their best-fit plane (how flat the triangulation is)."""

    def to_dict(self) -> dict[str, float | int]:
        return {
            "time": self.time_index,
            "num_corners": self.num_corners,
            "median": self.median,
            "max": self.max,
            "board_rms": self.board_rms,
        }


def board_check(cloud: PointCloud | Points3D, corners: BoardCorners, time_index: int) -> BoardCheck:
    """Each corner's distance to the nearest point of ``cloud`` (and the corners' flatness)."""
    pts = cloud.points3D if isinstance(cloud, PointCloud) else np.asarray(cloud, np.float64)
    C = len(corners)
    if C == 0:
        d = np.zeros(0)
    elif len(pts) == 0:
        d = np.full(C, np.inf)
    else:
        d, _ = cKDTree(pts).query(corners.points3D)
    rms = float("nan")
    if C >= 3:
        X = corners.points3D - corners.points3D.mean(axis=0)
        normal = np.linalg.svd(X, full_matrices=False)[2][2]
        rms = float(np.sqrt(np.mean((X @ normal) ** 2)))
    return BoardCheck(
        time_index=time_index,
        num_corners=C,
        distances=np.asarray(d, np.float64),
        median=float(np.median(d)) if C else float("nan"),
        max=float(np.max(d)) if C else float("nan"),
        board_rms=rms,
    )


@dataclass(frozen=True, kw_only=True, eq=False)
class BoardSurface:
    """Distances of the dense points over the board to the plane of its corners."""

    time_index: int
    distances: NDArray[np.float64]
    """(P,) absolute distance to the corners' plane of each point that lies over the corners'
    convex hull and within the band (rig units)."""
    band: float

    @property
    def num_points(self) -> int:
        return int(self.distances.shape[0])

    @property
    def median(self) -> float:
        return float(np.median(self.distances)) if self.num_points else float("nan")

    def within(self, threshold: float) -> float:
        """Share of the points within ``threshold`` of the plane (the cloud's precision on the
        board at that threshold); NaN without points."""
        return float(np.mean(self.distances <= threshold)) if self.num_points else float("nan")


def board_surface(
    cloud: PointCloud | Points3D, corners: BoardCorners, time_index: int, band: float
) -> BoardSurface:
    """The points of ``cloud`` over the convex hull of the board's corners (in the plane fitted
    to them) and within ``band`` of that plane, with their distances to it. The band (rig
    units) keeps what is in front of or behind the board (the hand holding it, the wall
    behind) out; with fewer than 3 corners there is no plane and no point."""
    from scipy.spatial import Delaunay, QhullError

    pts = cloud.points3D if isinstance(cloud, PointCloud) else np.asarray(cloud, np.float64)
    empty = BoardSurface(time_index=time_index, distances=np.zeros(0), band=band)
    if len(corners) < 3 or len(pts) == 0:
        return empty
    center = corners.points3D.mean(axis=0)
    _, _, vt = np.linalg.svd(corners.points3D - center, full_matrices=False)
    try:
        outline = Delaunay((corners.points3D - center) @ vt[:2].T)
    except QhullError:  # collinear corners: no area
        return empty
    rel = pts - center
    d = np.abs(rel @ vt[2])
    near = np.flatnonzero(d <= band)
    inside = outline.find_simplex(rel[near] @ vt[:2].T) >= 0
    return BoardSurface(time_index=time_index, distances=d[near[inside]], band=band)
