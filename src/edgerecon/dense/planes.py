"""Planar-prior completion of floors that stereo left without depth.

Photo-consistency (NCC) cannot place pixels of an untextured floor: every depth looks the
same; and where only two views see a floor at grazing angles, the two depth maps rarely
agree. Planar-prior MVS (e.g. Xu & Tao's ACMP) fills such regions from planes supported by
the reliable depths. Here, the ground plane is perpendicular to the scene's up direction,
at the height of the dominant bin of a height histogram of the consistent stereo points
whose normals are near vertical (refined to the median height of its inliers); then every
pixel that has no depth, whose ray meets the plane within the depth bounds the search had
and whose texture is mild (``DenseConfig.ground_max_texture``) is tested by projecting the
plane point into the other views:

* a view whose own depth lies clearly *behind* the point contradicts it (it sees through
  the point: free-space violation) -> rejected;
* a view whose depth lies clearly in front is occluded there and gives no evidence;
* otherwise the view must see a similar colour (box-filtered BGR, per-channel tolerance)
  and, where the pixel's window is textured (``BLANK_TEXTURE``), the same pattern: the
  view's image warped onto the pixel's window through the plane's homography must match it
  (NCC, ``DenseConfig.ground_min_ncc``). Mean colours alone agree by chance on textured
  surfaces: the textured side of a box would be put onto the floor behind it.

Near-black pixels are never completed (no colour evidence), nor pixels whose colour the
plane's stereo points never showed (walls above a floor), nor points outside the convex hull
of the plane's stereo points (behind the walls of a room). A pixel is kept when at least
``min_consistent_views`` views confirm it, more views confirm than deny, and none
contradicts. Completed points lie exactly on the fitted plane, so they are only as good as
the fit (reported in the stage's stats).

A floor need not be one plane (a raised deck, a platform, a step). ``level_map`` bins the
measured horizontal stereo points in cells of the plane's 2D coordinates: a cell whose
measured points sit clearly above the plane holds another level (its height: their median),
one whose points sit clearly below holds a lower level. Only the dominant level is completed,
and never where another level is: a completed point must not lie in a lower level's cell, and
its ray to its camera must not pass under a raised level (the pixel sees the deck, not the
floor beneath it; a ray march through the map's height field). Raised cells with no measured
point enclosed by raised cells count as raised (a blank deck measured only at its texture).
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.dense.cost import WindowStats, as_f32, ncc, to_grey, window_stats
from edgerecon.geometry.camera import Camera
from edgerecon.threads import thread_map
from edgerecon.types import DepthMap, Image

logger = logging.getLogger(__name__)

#: Pixels darker than this (5x5 mean of the brightest channel, 0..255) are never completed.
MIN_BRIGHTNESS = 24.0
#: Side of the windows whose grey standard deviation decides whether a pixel is blank (under
#: ``BLANK_TEXTURE``: its colour is the only evidence) or textured (its pattern must match
#: in the confirming views, ``complete_with_plane``).
TEXTURE_WINDOW = 7
#: Grey-level standard deviation of a blank window.
BLANK_TEXTURE = 4.0
#: Points whose normal is within this angle of 'up' take part in the ground-plane vote.
_HORIZONTAL_DEG = 40.0
#: Largest share of all points more than 3 bands below a ground-plane candidate.
_MAX_BELOW_SHARE = 0.1


@dataclass(frozen=True)
class Plane:
    """The plane ``normal . X = offset`` (normal: unit, pointing up)."""

    normal: tuple[float, float, float]
    offset: float
    support: int
    """Stereo points within the inlier band of the plane."""
    rms: float
    """RMS distance of those points to the plane (rig units)."""


def fit_ground_plane(
    points: NDArray[np.float64],
    normals: NDArray[np.float32],
    num_views: NDArray[np.integer[Any]],
    up: NDArray[np.float64],
    band: float,
    min_support: int,
) -> Plane | None:
    """The dominant horizontal plane of ``points`` (None if too few horizontal points).

    Only points confirmed by at least 3 views vote when there are enough of them: a pair of
    wide-baseline views can agree on a false line match (two different floor seams whose
    interpretation planes meet below the floor), which produces a tight, spurious horizontal
    cluster that a third view never confirms (utrecht4cam frame 200: 1,491 such points 1.1 m
    below the floor, none seen by 3 views; 306 true floor points are)."""
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    horiz = normals.astype(np.float64) @ up > np.cos(np.radians(_HORIZONTAL_DEG))
    multi = horiz & (num_views >= 3)
    if int(multi.sum()) >= min_support:
        horiz = multi
    if int(horiz.sum()) < min_support:
        return None
    P = points[horiz]
    h = P @ up
    lo, hi = float(h.min()), float(h.max())
    nbins = max(1, int(np.ceil((hi - lo) / band)))
    counts, edges = np.histogram(h, bins=nbins, range=(lo, lo + nbins * band))
    # A ground plane has (almost) nothing under it: the tops of heads, tables or seats can
    # hold the most horizontal points (a foreground-only cloud), but most points lie below.
    # Counted among the points 3 views confirm when there are enough (two-view ghosts below
    # the floor do not count).
    confirmed = num_views >= 3
    heights = np.sort((points[confirmed] if confirmed.sum() >= min_support else points) @ up)
    centres = 0.5 * (edges[:-1] + edges[1:])
    below = np.searchsorted(heights, centres - 3.0 * band) / max(len(heights), 1)
    counts = np.where(below <= _MAX_BELOW_SHARE, counts, 0)
    k = int(np.argmax(counts))
    if counts[k] < min_support:
        return None
    h0 = centres[k]
    inl = np.abs(h - h0) <= band
    if int(inl.sum()) < min_support:
        return None
    # The plane keeps the given up direction: a free normal fitted to a few hundred noisy
    # floor points tilts by degrees (hundreds of millimetres across a room), while the rig's
    # up (or the cameras' mean image-up) is known far better.
    n = up
    # Re-select inliers against the fitted plane and settle the offset on them.
    d = points @ n
    off = float(h0)
    inl_all = horiz & (np.abs(d - off) <= band)
    if int(inl_all.sum()) >= min_support:
        off = float(np.median(d[inl_all]))
    rms = float(np.sqrt(np.mean((d[inl_all] - off) ** 2))) if inl_all.any() else float("inf")
    return Plane(
        normal=(float(n[0]), float(n[1]), float(n[2])),
        offset=off,
        support=int(inl_all.sum()),
        rms=rms,
    )


def below_plane(points: NDArray[np.float64], plane: Plane, band: float) -> NDArray[np.bool_]:
    """(N,) True for points more than ``band`` below the plane (hidden behind an opaque floor
    from every camera above it: stereo errors)."""
    return points @ np.asarray(plane.normal) < plane.offset - band


#: Colour-model bins per channel (16 -> bins of 16 grey levels).
COLOR_BINS = 16


def color_model(colors_rgb: NDArray[np.uint8], min_count: int = 3) -> NDArray[np.bool_]:
    """(B, B, B) occupancy of RGB colour bins (``COLOR_BINS`` per channel) seen at least
    ``min_count`` times, grown by one bin: the colours the plane is known to have."""
    q = (np.asarray(colors_rgb, np.int32) * COLOR_BINS) // 256
    flat = (q[:, 0] * COLOR_BINS + q[:, 1]) * COLOR_BINS + q[:, 2]
    counts = np.bincount(flat, minlength=COLOR_BINS**3).reshape((COLOR_BINS,) * 3)
    occ = (counts >= min_count).astype(np.uint8)
    # Grow by one bin in every direction (3D dilation as three 1D maxima).
    for axis in range(3):
        occ = np.maximum.reduce([occ, np.roll(occ, 1, axis), np.roll(occ, -1, axis)])
    return occ.astype(bool)


def plane_basis(plane: Plane) -> NDArray[np.float64]:
    """(3, 2) orthonormal axes spanning the plane."""
    n = np.asarray(plane.normal)
    a = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    return np.stack([a, np.cross(n, a)], axis=1)


@dataclass(frozen=True, eq=False)
class PlaneRegion:
    """A convex polygon in a plane: ``inside(X)`` for 3D points on the plane."""

    basis: NDArray[np.float64]
    """(3, 2) in-plane axes (``plane_basis``)."""
    vertices: NDArray[np.float64]
    """(E, 2) corners of the polygon in plane coordinates."""

    @functools.cached_property
    def _wedges(
        self,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Centre, corner angles around it (ascending) and the outward normal and offset of
        the edge from each corner to the next."""
        v = np.asarray(self.vertices, np.float64)
        center = v.mean(axis=0)
        angles = np.arctan2(v[:, 1] - center[1], v[:, 0] - center[0])
        order = np.argsort(angles)
        v, angles = v[order], angles[order]
        edge = np.roll(v, -1, axis=0) - v
        normals = np.stack([edge[:, 1], -edge[:, 0]], axis=1)  # the interior is on the left
        return center, angles, normals, np.einsum("ij,ij->i", normals, v)

    def inside(self, points3D: NDArray[np.float64]) -> NDArray[np.bool_]:
        """(N,) True for points inside the polygon (or on its boundary). Each point is tested
        against the one edge of its wedge around the centre (the centre, the edge's corners),
        not every edge: the hull of a floor's stereo points has tens of edges."""
        uv = np.asarray(points3D, np.float64) @ self.basis
        center, angles, normals, offsets = self._wedges
        theta = np.arctan2(uv[:, 1] - center[1], uv[:, 0] - center[0])
        k = np.searchsorted(angles, theta, side="right") - 1  # -1: the wedge that wraps round
        return normals[k, 0] * uv[:, 0] + normals[k, 1] * uv[:, 1] <= offsets[k]


def support_region(
    plane: Plane, inliers: NDArray[np.float64], trim: float = 0.01
) -> PlaneRegion | None:
    """The convex hull of the plane's stereo inliers in plane coordinates, without the
    ``trim`` share farthest from their median; None if degenerate. Completion stays inside
    it: a uniform wall would otherwise extend the floor behind it."""
    from scipy.spatial import ConvexHull, QhullError

    basis = plane_basis(plane)
    uv = inliers @ basis
    if len(uv) < 3:
        return None
    d = np.linalg.norm(uv - np.median(uv, axis=0), axis=1)
    uv = uv[d <= np.quantile(d, 1.0 - trim)]
    try:
        hull = ConvexHull(uv)
    except (QhullError, ValueError):
        return None
    return PlaneRegion(basis=basis, vertices=uv[hull.vertices])


@dataclass(frozen=True, eq=False)
class LevelMap:
    """Measured levels other than ``plane`` on a grid of cells in the plane's coordinates."""

    plane: Plane
    basis: NDArray[np.float64]
    """(3, 2) in-plane axes (``plane_basis``)."""
    origin: NDArray[np.float64]
    """(2,) plane coordinates of cell (0, 0)'s corner."""
    cell: float
    """Cell edge (rig units)."""
    band: float
    """Heights within +-band of the plane are on it (rig units)."""
    raised: NDArray[np.float32]
    """(I, J) height above the plane of a raised level in the cell (0: none)."""
    lower: NDArray[np.bool_]
    """(I, J) True where a measured level lies below the plane."""
    on_plane: NDArray[np.int32]
    """(I, J) measured horizontal points on the plane per cell."""

    def cells(self, points3D: NDArray[np.float64]) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
        """(rows, cols) cell indices of ``points3D`` (clipped to the grid)."""
        uv = (np.asarray(points3D, np.float64) @ self.basis - self.origin) / self.cell
        i = np.clip(np.floor(uv[:, 0]), 0, self.raised.shape[0] - 1).astype(np.intp)
        j = np.clip(np.floor(uv[:, 1]), 0, self.raised.shape[1] - 1).astype(np.intp)
        return i, j

    def _inside(self, points3D: NDArray[np.float64]) -> NDArray[np.bool_]:
        uv = (np.asarray(points3D, np.float64) @ self.basis - self.origin) / self.cell
        shape = np.asarray(self.raised.shape)
        return np.all((uv >= 0) & (uv < shape), axis=1)

    def refused(
        self, points3D: NDArray[np.float64], center: NDArray[np.float64]
    ) -> NDArray[np.bool_]:
        """(N,) True for plane points that another level hides or replaces as seen from the
        camera at ``center``: in a lower level's cell, or behind a raised level on the ray
        to the camera (a march through the height field in half-cell steps, at most 64)."""
        X = np.asarray(points3D, np.float64)
        out = np.zeros(len(X), bool)
        if len(X) == 0:
            return out
        inside = self._inside(X)
        i, j = self.cells(X)
        out |= inside & self.lower[i, j]
        top = float(self.raised.max())
        n = np.asarray(self.plane.normal)
        h_cam = float(center @ n - self.plane.offset)
        if top <= self.band or h_cam <= top:
            # No raised level, or a camera not above it (no ray passes over it): column test.
            return out | (inside & (self.raised[i, j] > self.band))
        # The ray X -> C is at height s * h_cam at X + s (C - X); above ``top`` nothing hides.
        # In grid units, only the 2D footprint matters; rays whose footprint misses the box
        # of the raised cells are not marched.
        s_max = top / h_cam
        uv0 = (X @ self.basis - self.origin) / self.cell
        duv = (np.asarray(center, np.float64) @ self.basis - self.origin) / self.cell - uv0
        end = uv0 + s_max * duv
        ri, rj = np.nonzero(self.raised > self.band)
        near = (
            (np.maximum(uv0[:, 0], end[:, 0]) >= ri.min() - 1)
            & (np.minimum(uv0[:, 0], end[:, 0]) <= ri.max() + 2)
            & (np.maximum(uv0[:, 1], end[:, 1]) >= rj.min() - 1)
            & (np.minimum(uv0[:, 1], end[:, 1]) <= rj.max() + 2)
        )
        idx = np.nonzero(near)[0]
        if len(idx) == 0:
            return out
        uv0, duv = uv0[idx], duv[idx]
        steps = int(min(64, np.ceil(2.0 * s_max * np.abs(duv).max()))) + 1
        shape = self.raised.shape
        hit = np.zeros(len(idx), bool)
        for k in range(steps + 1):
            s = s_max * k / steps
            uv = np.floor(uv0 + s * duv)
            inside = (
                (uv[:, 0] >= 0) & (uv[:, 0] < shape[0]) & (uv[:, 1] >= 0) & (uv[:, 1] < shape[1])
            )
            i = np.clip(uv[:, 0], 0, shape[0] - 1).astype(np.intp)
            j = np.clip(uv[:, 1], 0, shape[1] - 1).astype(np.intp)
            hit |= inside & (self.raised[i, j] > s * h_cam + self.band)
        out[idx] |= hit
        return out

    def stats(self) -> dict[str, Any]:
        """Cell counts and the raised levels' heights (binned by the band)."""
        r = self.raised[self.raised > self.band]
        levels: dict[str, int] = {}
        if len(r):
            q = np.rint(r / self.band) * self.band
            for h, c in zip(*np.unique(q, return_counts=True), strict=True):
                levels[f"{float(h):.4g}"] = int(c)
        return {
            "cell": self.cell,
            "cells_on_plane": int(np.count_nonzero(self.on_plane)),
            "cells_raised": int(np.count_nonzero(self.raised > self.band)),
            "cells_lower": int(np.count_nonzero(self.lower)),
            "raised_levels": levels,
        }


def level_map(
    plane: Plane,
    points: NDArray[np.float64],
    normals: NDArray[np.float32],
    num_views: NDArray[np.integer[Any]],
    band: float,
    cell: float,
    min_points: int,
    min_support: int = 0,
) -> LevelMap:
    """The coarse level map of the measured horizontal ``points`` around ``plane``.

    A cell holds a raised (or lower) level when at least ``min_points`` of its horizontal
    points lie more than ``band`` above (below) the plane and they are at least a quarter of
    its points on the plane; so does a neighbouring cell with any point of that level (the
    level's edge), and, for a raised level, a cell without points that it encloses. Only
    points confirmed by 3 views count when at least ``min_support`` are (two-view ghosts
    below a floor are no level)."""
    from scipy import ndimage

    n = np.asarray(plane.normal)
    basis = plane_basis(plane)
    horiz = normals.astype(np.float64) @ n > np.cos(np.radians(_HORIZONTAL_DEG))
    multi = horiz & (num_views >= 3)
    if int(multi.sum()) >= max(min_support, 1):
        horiz = multi
    P = points[horiz]
    h = P @ n - plane.offset
    uv = P @ basis
    origin = uv.min(axis=0) if len(uv) else np.zeros(2)
    extent = (uv.max(axis=0) - origin) if len(uv) else np.zeros(2)
    shape = tuple(int(x) for x in np.floor(extent / cell).astype(int) + 1)
    ij = np.minimum(np.floor((uv - origin) / cell).astype(np.intp), np.asarray(shape) - 1)
    flat = ij[:, 0] * shape[1] + ij[:, 1] if len(uv) else np.zeros(0, np.intp)
    size = shape[0] * shape[1]

    def count(sel: NDArray[np.bool_]) -> NDArray[np.int64]:
        return np.bincount(flat[sel], minlength=size).reshape(shape)

    on = count(np.abs(h) <= band)
    up, down = h > band, h < -band
    n_up, n_down = count(up), count(down)
    # A level's cells: enough points off the plane, a fifth of the cell's at least (a few
    # specks among a floor's points are no level) ...
    raised_cells = (n_up >= min_points) & (4 * n_up >= on)
    lower = (n_down >= min_points) & (4 * n_down >= on) & ~raised_cells
    # ... and its edge: next to a level, any point on it (the grid ignores the level's edge).
    ring = np.ones((3, 3), bool)
    edge_up = ndimage.binary_dilation(raised_cells, ring) & (n_up > 0)
    lower |= ndimage.binary_dilation(lower, ring) & (n_down > 0) & ~edge_up
    core_up = raised_cells
    raised_cells = edge_up | raised_cells
    # Median height of the raised points per cell: sort by (cell, height), take the middle.
    raised = np.zeros(shape, np.float32)
    if raised_cells.any():
        fu, hu = flat[up], h[up]
        order = np.lexsort((hu, fu))
        fu, hu = fu[order], hu[order]
        first = np.searchsorted(fu, np.arange(size))
        cnt = n_up.ravel()
        mid = np.where(cnt > 0, first + cnt // 2, 0).clip(0, max(len(hu) - 1, 0))
        med = np.where(cnt > 0, hu[mid] if len(hu) else 0.0, 0.0).reshape(shape)
        raised = np.where(raised_cells, med, 0.0).astype(np.float32)
        # Blank parts of a raised level (no measured point at all) enclosed by it: raised,
        # at the height of the nearest raised cell.
        filled = ndimage.binary_fill_holes(raised_cells) & ~raised_cells
        filled &= (on == 0) & (n_down == 0)
        grown = filled | (raised_cells & ~core_up)
        if grown.any() and core_up.any():
            # Edge and enclosed cells take the height of the nearest core cell (few points).
            _, (ri, rj) = ndimage.distance_transform_edt(~core_up, return_indices=True)
            raised[grown] = raised[ri[grown], rj[grown]]
    return LevelMap(
        plane=plane,
        basis=basis,
        origin=origin,
        cell=float(cell),
        band=float(band),
        raised=raised,
        lower=lower,
        on_plane=on.astype(np.int32),
    )


def plane_depth(camera: Camera, plane: Plane) -> DepthMap:
    """(H, W) depth at which each pixel's ray meets the plane (0 where it does not, in front
    of the camera). The rays of a camera with distortion (the scene stage's working cameras)
    are undistorted first."""
    n = np.asarray(plane.normal)
    nc = camera.R @ n  # plane normal in the camera frame
    dist = plane.offset - float(n @ camera.center)  # n . (C + z R^T ray) = offset
    if camera.has_distortion:
        ys, xs = np.mgrid[0 : camera.height, 0 : camera.width]
        rays = camera.pixel_rays(np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64))
        denom = (rays @ nc).reshape(camera.height, camera.width)
    else:
        Kinv = np.linalg.inv(camera.K)
        u = np.arange(camera.width, dtype=np.float64)[None, :]
        v = np.arange(camera.height, dtype=np.float64)[:, None]
        rx = Kinv[0, 0] * u + Kinv[0, 1] * v + Kinv[0, 2]
        ry = Kinv[1, 1] * v + Kinv[1, 2]
        denom = nc[0] * rx + nc[1] * ry + nc[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        z = dist / denom
    return np.where(np.isfinite(z) & (z > 0), z, 0.0).astype(np.float32)


def plane_homography(cam_i: Camera, cam_j: Camera, plane: Plane) -> NDArray[np.float64]:
    """The 3x3 homography that maps a pixel of ``cam_i`` whose ray meets ``plane`` to the
    pixel of ``cam_j`` that sees the same plane point (pinhole cameras)."""
    n = np.asarray(plane.normal, np.float64)
    nc = cam_i.R @ n  # plane in camera i's frame: nc . Xc = dc
    dc = plane.offset + float(nc @ cam_i.t)
    R_ji = cam_j.R @ cam_i.R.T
    t_ji = cam_j.t - R_ji @ cam_i.t
    H = cam_j.K @ (R_ji + np.outer(t_ji, nc) / dc) @ np.linalg.inv(cam_i.K)
    return np.asarray(H / H[2, 2], np.float64)


def _plane_ncc(
    cam_i: Camera,
    crop_i: WindowStats,
    cam_j: Camera,
    grey_j: NDArray[np.float32],
    plane: Plane,
    origin: tuple[int, int],
) -> NDArray[np.float32]:
    """NCC of the windows of view i's crop (``crop_i``, top-left pixel ``origin``) with view
    j's image warped onto it through the plane (NaN where a window leaves view j)."""
    h, w = crop_i.image.shape
    shift = np.array([[1.0, 0.0, origin[0]], [0.0, 1.0, origin[1]], [0.0, 0.0, 1.0]])
    H = plane_homography(cam_i, cam_j, plane) @ shift
    warped = cv2.warpPerspective(
        grey_j,
        H,
        (w, h),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=float("nan"),
    )
    return ncc(crop_i, np.asarray(warped, np.float32))


def _channel_max(a: NDArray[np.float32]) -> NDArray[np.float32]:
    """The largest of the last axis's three channels (``a.max(axis=-1)`` reduces a 3-long
    axis element by element, about 10x slower)."""
    return np.maximum(np.maximum(a[..., 0], a[..., 1]), a[..., 2])


def complete_with_plane(
    plane: Plane,
    depths: Mapping[int, DepthMap],
    cameras: Mapping[int, Camera],
    colors: Mapping[int, Image],
    regions: Mapping[int, NDArray[np.bool_]],
    far: Mapping[int, float | DepthMap],
    rel_tol: float,
    color_tol: float,
    min_views: int,
    colors_known: NDArray[np.bool_] | None = None,
    region: PlaneRegion | None = None,
    num_threads: int = 1,
    textured: Mapping[int, NDArray[np.bool_]] | None = None,
    min_ncc: float = 0.5,
    near: Mapping[int, float | DepthMap] | None = None,
) -> dict[int, tuple[DepthMap, NDArray[np.int16]]]:
    """Per view, (depth map of the accepted plane pixels, number of confirming views).

    Completed depths lie within the view's ``near`` (when given) and ``far`` bounds: numbers
    or per-pixel maps (the depth bounds the dense stage searched).

    A ``textured`` pixel (per view, True where the window has a pattern to compare) is
    confirmed by a view only where that view's image, warped through the plane, also
    matches its window's pattern (NCC of ``TEXTURE_WINDOW`` windows >= ``min_ncc``), and
    denied where it does not: mean colours alone agree by chance on textured surfaces (the
    side of a box completed onto the floor behind it). A view with distortion cannot be
    warped by a homography and gives no evidence on textured pixels.

    ``colors_known`` (``color_model`` of the plane's stereo points) restricts completion to
    pixels of the plane's own colours: a white wall above a green floor is not floor even
    where every view agrees it is white. ``region`` (``support_region``) bounds the completed
    points in the plane. Every view is completed, also one whose floor stereo mostly matched
    already: its pixels left without a depth are judged one by one, and walls, furniture and
    occluders fail the colour and free-space tests there (a rule that left such views alone
    kept 4 of the demo scene's 5 views from completing anything; docs/BENCHMARKS.md). Views
    run on ``num_threads`` threads (``keep_off_levels`` then verifies the result)."""
    blurred = {i: as_f32(cv2.blur(np.asarray(c, np.float32), (5, 5))) for i, c in colors.items()}
    flat_width = {i: b.shape[1] for i, b in blurred.items()}
    greys = {i: to_grey(c) for i, c in colors.items()} if textured is not None else {}

    def one(i: int) -> tuple[DepthMap, NDArray[np.int16]]:
        cam_i = cameras[i]
        zp = plane_depth(cam_i, plane)
        # Near-black pixels carry no colour evidence (unlit background, sensor noise).
        lit = _channel_max(blurred[i]) >= MIN_BRIGHTNESS
        cand = (depths[i] <= 0) & (zp > 0) & (zp < far[i]) & regions[i] & lit
        if near is not None:
            cand &= zp >= near[i]
        if colors_known is not None:
            q = (np.clip(blurred[i], 0, 255).astype(np.int32) * COLOR_BINS) // 256
            cand &= colors_known[q[..., 2], q[..., 1], q[..., 0]]  # BGR image, RGB model
        rows, cols = np.nonzero(cand)
        result = np.zeros(zp.shape, np.float32)
        support = np.zeros(zp.shape, np.int16)
        if len(rows) == 0:
            return result, support
        z = zp[rows, cols].astype(np.float64)
        Kinv = np.linalg.inv(cam_i.K)
        Xc = np.stack(
            [
                (Kinv[0, 0] * cols + Kinv[0, 1] * rows + Kinv[0, 2]) * z,
                (Kinv[1, 1] * rows + Kinv[1, 2]) * z,
                z,
            ],
            axis=1,
        )
        X = (Xc - cam_i.t) @ cam_i.R
        if region is not None:
            inside = region.inside(X)
            rows, cols, z, X = rows[inside], cols[inside], z[inside], X[inside]
            if len(rows) == 0:
                return result, support
        col_i = blurred[i][rows, cols]
        agree = np.zeros(len(z), np.int16)
        deny = np.zeros(len(z), np.int16)
        contra = np.zeros(len(z), bool)
        tex = (
            textured[i][rows, cols]
            if textured is not None and i in textured
            else np.zeros(len(z), bool)
        )
        crop_i = None
        if tex.any():
            # The windows of the textured candidates' bounding box, compared in every view.
            r = TEXTURE_WINDOW // 2 + 1
            ty, tx = rows[tex], cols[tex]
            x0, y0 = max(0, int(tx.min()) - r), max(0, int(ty.min()) - r)
            x1, y1 = (
                min(zp.shape[1], int(tx.max()) + r + 1),
                min(zp.shape[0], int(ty.max()) + r + 1),
            )
            crop_i = window_stats(np.ascontiguousarray(greys[i][y0:y1, x0:x1]), TEXTURE_WINDOW // 2)
        for j, cam_j in cameras.items():
            if j == i:
                continue
            uv, zj = cam_j.project(X)
            with np.errstate(invalid="ignore"):
                inside = (zj > 0) & cam_j.in_image(uv, margin=0.5)
            idx = np.nonzero(inside)[0]
            if len(idx) == 0:
                continue
            cj = np.rint(uv[idx, 0]).astype(np.intp)
            rj = np.rint(uv[idx, 1]).astype(np.intp)
            dj = depths[j][rj, cj].astype(np.float64)
            zz = zj[idx]
            behind = (dj > 0) & (dj > zz * (1 + rel_tol))
            front = (dj > 0) & (dj < zz * (1 - rel_tol))
            visible = ~behind & ~front
            flat = blurred[j].reshape(-1, blurred[j].shape[-1])
            cdiff = _channel_max(np.abs(flat[rj * flat_width[j] + cj] - col_i[idx]))
            t_idx = tex[idx]
            # The pattern test, for the textured candidates this view sees (NaN: no evidence
            # either way; a view with distortion has none).
            p_idx = np.full(len(idx), np.nan, np.float32)
            judge = t_idx & visible
            if crop_i is not None and judge.any():
                if not (cam_i.has_distortion or cam_j.has_distortion):
                    k = idx[judge]
                    ky, kx = rows[k] - y0, cols[k] - x0
                    # Only the part of the crop that holds these candidates' windows.
                    sy = slice(max(0, int(ky.min()) - r), int(ky.max()) + r + 1)
                    sx = slice(max(0, int(kx.min()) - r), int(kx.max()) + r + 1)
                    sub = WindowStats(
                        image=crop_i.image[sy, sx],
                        mean=crop_i.mean[sy, sx],
                        std=crop_i.std[sy, sx],
                        radius=crop_i.radius,
                    )
                    nmap = _plane_ncc(
                        cam_i, sub, cam_j, greys[j], plane, (x0 + sx.start, y0 + sy.start)
                    )
                    p_idx[judge] = nmap[ky - sy.start, kx - sx.start]
            matches = ~t_idx | (p_idx >= min_ncc)
            differs = t_idx & (p_idx < min_ncc)
            good = visible & (cdiff <= color_tol) & matches
            bad = visible & ((cdiff > color_tol) | differs)
            contra[idx[behind]] = True
            agree[idx[good]] += 1
            deny[idx[bad]] += 1
        ok = ~contra & (agree >= min_views) & (agree > deny)
        result[rows[ok], cols[ok]] = z[ok]
        support[rows[ok], cols[ok]] = agree[ok]
        return result, support

    ids = list(cameras)
    return dict(zip(ids, thread_map(one, ids, num_threads), strict=True))


def keep_off_levels(
    levels: LevelMap,
    completed: Mapping[int, tuple[DepthMap, NDArray[np.int16]]],
    cameras: Mapping[int, Camera],
    num_threads: int = 1,
) -> tuple[dict[int, tuple[DepthMap, NDArray[np.int16]]], dict[int, int]]:
    """``complete_with_plane``'s result without the pixels ``levels`` refuses (another
    measured level is there, or hides the plane from the view), and per view how many."""

    def one(i: int) -> tuple[tuple[DepthMap, NDArray[np.int16]], int]:
        depth, support = completed[i]
        rows, cols = np.nonzero(depth > 0)
        if len(rows) == 0:
            return (depth, support), 0
        X = cameras[i].backproject(
            np.stack([cols, rows], axis=1).astype(np.float64),
            depth[rows, cols].astype(np.float64),
        )
        off = levels.refused(X, cameras[i].center)
        if not off.any():
            return (depth, support), 0
        depth, support = depth.copy(), support.copy()
        depth[rows[off], cols[off]] = 0.0
        support[rows[off], cols[off]] = 0
        return (depth, support), int(off.sum())

    ids = [i for i in completed if i in cameras]
    results = thread_map(one, ids, num_threads)
    return (
        {i: r[0] for i, r in zip(ids, results, strict=True)},
        {i: r[1] for i, r in zip(ids, results, strict=True)},
    )
