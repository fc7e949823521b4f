"""Calibrated pinhole cameras with OpenCV distortion, and rigs of static cameras.

Conventions (used everywhere in edgerecon):

* Camera frame is OpenCV's: x right, y down, z forward (depth = z > 0 in front).
* ``cam_from_world``: ``X_cam = R @ X_world + t``; the centre is ``C = -R.T @ t``.
* Pixel coordinates are continuous with the *centre* of the top-left pixel at (0, 0), as
  OpenCV's ``projectPoints`` / ``remap`` use them.
* Distortion is OpenCV's ``(k1, k2, p1, p2, k3)`` plumb-bob model (openMVG's
  ``pinhole_radial_k3`` is the special case p1 = p2 = 0).
* Rescaling an image by ``r`` maps pixel centres so that the image borders stay put: a pixel
  ``x`` in the original maps to ``(x + 0.5) * s - 0.5`` where ``s = new_width / width``.
* Lengths are in the rig's unit (``Rig.unit``: "m" for synthetic scenes and Middlebury,
  "mm" for utrecht4cam); nothing in the core assumes metres.
"""

from __future__ import annotations

import dataclasses
import math
import threading
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry._kernels import (
    nearest_pixels_world,
    project_world_points,
    rigid_transform,
)
from edgerecon.types import CalibrationError, Points2D, Points3D

#: Tolerance for ``R @ R.T == I`` when validating a rotation.
ORTHONORMAL_TOL = 1e-5


def _as_matrix(value: Any, shape: tuple[int, ...], name: str, camera: str) -> NDArray[np.float64]:
    arr = np.asarray(value, dtype=np.float64)
    if arr.size != int(np.prod(shape)):
        raise CalibrationError(
            f"camera {camera!r}: {name} must have shape {shape}, got {arr.shape}"
        )
    arr = arr.reshape(shape).copy()
    if not np.all(np.isfinite(arr)):
        raise CalibrationError(f"camera {camera!r}: {name} contains NaN or infinite values")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, kw_only=True, eq=False)
class Camera:
    """One static, calibrated camera.

    Immutable; ``scaled`` / ``undistorted`` return new cameras. Equality is by value.
    """

    name: str
    """Identifier used in messages, file names and ``--cameras`` (e.g. "cam1")."""
    width: int
    """Image width in pixels."""
    height: int
    """Image height in pixels."""
    K: NDArray[np.float64]
    """(3, 3) intrinsic matrix in pixels (skew allowed)."""
    R: NDArray[np.float64]
    """(3, 3) rotation of ``cam_from_world``."""
    t: NDArray[np.float64]
    """(3,) translation of ``cam_from_world``, in rig units."""
    dist: NDArray[np.float64] = field(default_factory=lambda: np.zeros(5))
    """(5,) OpenCV distortion coefficients k1, k2, p1, p2, k3 (zeros: ideal pinhole)."""

    def __post_init__(self) -> None:
        name = self.name
        object.__setattr__(self, "K", _as_matrix(self.K, (3, 3), "K", name))
        object.__setattr__(self, "R", _as_matrix(self.R, (3, 3), "rotation", name))
        object.__setattr__(self, "t", _as_matrix(self.t, (3,), "translation", name))
        dist = np.asarray(self.dist, dtype=np.float64).ravel()
        if dist.size > 5:
            if np.any(dist[5:] != 0):
                raise CalibrationError(
                    f"camera {name!r}: only 5 distortion coefficients (k1 k2 p1 p2 k3) are "
                    f"supported, got {dist.size} with non-zero extras"
                )
            dist = dist[:5]
        dist = np.pad(dist, (0, 5 - dist.size))
        object.__setattr__(self, "dist", _as_matrix(dist, (5,), "distortion", name))
        if int(self.width) != self.width or int(self.height) != self.height:
            raise CalibrationError(f"camera {name!r}: image size must be integers")
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        if self.width <= 0 or self.height <= 0:
            raise CalibrationError(
                f"camera {name!r}: image size must be positive, got {self.width}x{self.height}"
            )
        K = self.K
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CalibrationError(
                f"camera {name!r}: focal lengths must be positive, got fx={K[0, 0]:g}, fy={K[1, 1]:g}"
            )
        if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
            raise CalibrationError(
                f"camera {name!r}: K must be upper triangular with K[2,2] = 1, got\n{K}"
            )
        err = float(np.abs(self.R @ self.R.T - np.eye(3)).max())
        if err > ORTHONORMAL_TOL:
            raise CalibrationError(
                f"camera {name!r}: rotation is not orthonormal (max |R R^T - I| = {err:.2e})"
            )
        if np.linalg.det(self.R) < 0:
            raise CalibrationError(f"camera {name!r}: rotation has determinant -1 (a reflection)")

    # ----------------------------------------------------------------------------- identity
    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Camera):
            return NotImplemented
        return (
            self.name == other.name
            and self.width == other.width
            and self.height == other.height
            and np.array_equal(self.K, other.K)
            and np.array_equal(self.R, other.R)
            and np.array_equal(self.t, other.t)
            and np.array_equal(self.dist, other.dist)
        )

    def __hash__(self) -> int:
        return hash(
            (
                self.name,
                self.width,
                self.height,
                self.K.tobytes(),
                self.R.tobytes(),
                self.t.tobytes(),
                self.dist.tobytes(),
            )
        )

    # ----------------------------------------------------------------------------- derived
    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels, as OpenCV takes it."""
        return (self.width, self.height)

    @property
    def focal_px(self) -> float:
        """Mean focal length in pixels."""
        return float(0.5 * (self.K[0, 0] + self.K[1, 1]))

    @property
    def center(self) -> NDArray[np.float64]:
        """(3,) camera centre in world coordinates."""
        return -self.R.T @ self.t

    @property
    def world_from_cam(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(R, t) of the inverse transform: ``X_world = R @ X_cam + t``."""
        return self.R.T.copy(), self.center

    @property
    def cam_from_world(self) -> NDArray[np.float64]:
        """(3, 4) matrix ``[R | t]``."""
        return np.hstack([self.R, self.t[:, None]])

    @property
    def P(self) -> NDArray[np.float64]:
        """(3, 4) projection matrix ``K [R | t]`` (ignores distortion)."""
        return self.K @ self.cam_from_world

    @property
    def viewing_direction(self) -> NDArray[np.float64]:
        """(3,) unit optical axis in world coordinates."""
        return self.R[2].copy()

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0))

    # ----------------------------------------------------------------------------- variants
    def scaled(self, scale: float) -> Camera:
        """The same camera for an image resized by ``scale`` (K scales with the image).

        The new size is ``round(width * scale)`` x ``round(height * scale)``; the actual
        per-axis factors are used for K so that the image borders map onto each other.
        """
        if not (scale > 0 and np.isfinite(scale)):
            raise ValueError(f"scale must be a positive number, got {scale!r}")
        w = max(1, round(self.width * scale))
        h = max(1, round(self.height * scale))
        return self.resized(w, h)

    def resized(self, width: int, height: int) -> Camera:
        """The same camera for an image resized to ``width`` x ``height`` pixels."""
        if (width, height) == (self.width, self.height):
            return self
        sx, sy = width / self.width, height / self.height
        S = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])
        return dataclasses.replace(self, width=width, height=height, K=S @ self.K)

    def undistorted(self) -> Camera:
        """The ideal pinhole camera with the same K (what ``undistort_maps`` produces)."""
        if not self.has_distortion:
            return self
        return dataclasses.replace(self, dist=np.zeros(5))

    # ----------------------------------------------------------------------------- geometry
    def world_to_cam(self, points3D: Points3D) -> Points3D:
        """(N, 3) world points -> (N, 3) camera-frame points."""
        pts = np.ascontiguousarray(np.asarray(points3D, dtype=np.float64).reshape(-1, 3))
        out = np.empty_like(pts)
        # Compiled, not ``pts @ R.T``: see ``geometry._kernels`` (OpenBLAS's spinning threads).
        rigid_transform(pts, self.R, self.t, out)
        return out

    def project(self, points3D: Points3D) -> tuple[Points2D, NDArray[np.float64]]:
        """Project (N, 3) world points to pixels, applying distortion.

        Returns ``(points2D, depth)``: (N, 2) pixel coordinates and (N,) depth along the
        optical axis. Points with ``depth <= 0`` get NaN pixel coordinates.
        """
        pts = np.ascontiguousarray(np.asarray(points3D, dtype=np.float64).reshape(-1, 3))
        uv = np.empty((len(pts), 2))
        depth = np.empty(len(pts))
        # One compiled pass: rigid transform, division, distortion, intrinsics
        # (``world_to_cam`` and ``_distort``'s arithmetic, the same numbers).
        project_world_points(pts, self.R, self.t, self.K, self.dist, self.has_distortion, uv, depth)
        return uv, depth

    def nearest_pixels(
        self, points3D: Points3D
    ) -> tuple[
        Points2D, NDArray[np.float64], NDArray[np.intp], NDArray[np.intp], NDArray[np.bool_]
    ]:
        """``project`` and where the points land: ``(points2D, depth, u, v, inside)``, with
        ``inside`` (N,) in front of the camera and in the image (``in_image``) and (u, v)
        (N,) the nearest pixel of each (rounded half to even, clipped into the image; (0, 0)
        for a point not inside), in one compiled pass."""
        pts = np.ascontiguousarray(np.asarray(points3D, dtype=np.float64).reshape(-1, 3))
        n = len(pts)
        uv, depth = np.empty((n, 2)), np.empty(n)
        u, v, inside = np.empty(n, np.intp), np.empty(n, np.intp), np.empty(n, bool)
        nearest_pixels_world(
            pts,
            self.R,
            self.t,
            self.K,
            self.dist,
            self.has_distortion,
            self.width,
            self.height,
            uv,
            depth,
            u,
            v,
            inside,
        )
        return uv, depth, u, v, inside

    def pixel_rays(self, points2D: Points2D) -> NDArray[np.float64]:
        """(N, 2) (distorted) pixels -> (N, 3) normalised camera-frame rays with z = 1."""
        pts = np.asarray(points2D, dtype=np.float64).reshape(-1, 2)
        if pts.shape[0] == 0:
            return np.zeros((0, 3))
        if self.has_distortion:
            und = cv2.undistortPoints(
                pts.reshape(-1, 1, 2),
                self.K,
                self.dist,
                None,
                None,
                None,
                (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-12),
            ).reshape(-1, 2)
            und = _refine_undistortion(np.asarray(und, np.float64), pts, self.K, self.dist)
        else:
            Kinv = np.linalg.inv(self.K)
            und = pts @ Kinv[:2, :2].T + Kinv[:2, 2]
        return np.hstack([und, np.ones((und.shape[0], 1))])

    def backproject(self, points2D: Points2D, depth: NDArray[np.float64]) -> Points3D:
        """Pixels and their depths (along the optical axis) -> (N, 3) world points."""
        rays = self.pixel_rays(points2D)
        Xc = rays * np.asarray(depth, dtype=np.float64).reshape(-1, 1)
        Xc -= self.t
        out = np.empty_like(Xc)
        rigid_transform(Xc, np.ascontiguousarray(self.R.T), np.zeros(3), out)  # R^T (Xc - t)
        return out

    def in_image(self, points2D: Points2D, margin: float = 0.0) -> NDArray[np.bool_]:
        """(N,) True where a pixel lies inside the image (minus ``margin`` pixels)."""
        uv = np.asarray(points2D, dtype=np.float64).reshape(-1, 2)
        with np.errstate(invalid="ignore"):
            return (
                (uv[:, 0] >= -0.5 + margin)
                & (uv[:, 0] <= self.width - 0.5 - margin)
                & (uv[:, 1] >= -0.5 + margin)
                & (uv[:, 1] <= self.height - 0.5 - margin)
            )

    # ----------------------------------------------------------------------------- images
    def undistort_maps(self, scale: float = 1.0) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """``cv2.remap`` maps from a full-resolution distorted frame to the undistorted image at
        ``scale`` (one remap undistorts and resizes). The target camera is
        ``self.scaled(scale).undistorted()``. Cached per camera and scale."""
        return _undistort_maps_cached(self, float(scale))

    def prepare_image(self, image: NDArray[np.uint8], scale: float = 1.0) -> NDArray[np.uint8]:
        """Undistort and resize a frame of this camera to ``self.scaled(scale).undistorted()``.

        Raises ``CalibrationError`` if the frame's size does not match the calibration.
        """
        h, w = image.shape[:2]
        if (w, h) != (self.width, self.height):
            raise CalibrationError(
                f"camera {self.name!r}: frame is {w}x{h} but the calibration says "
                f"{self.width}x{self.height}"
            )
        if not self.has_distortion:
            if scale == 1.0:
                return image
            target = self.scaled(scale)
            return np.asarray(
                cv2.resize(image, target.size, interpolation=cv2.INTER_AREA), np.uint8
            )
        if scale < 1.0:
            # Smooth before resampling with remap (which does no area averaging) to avoid
            # aliasing; cheaper than undistorting at full size then resizing.
            sigma = 0.5 / scale
            image = np.asarray(cv2.GaussianBlur(image, (0, 0), sigmaX=sigma * 0.8), np.uint8)
        mx, my = self.undistort_maps(scale)
        return np.asarray(
            cv2.remap(
                image, mx, my, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT
            ),
            np.uint8,
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe representation (floats written with full precision by ``json``)."""
        return {
            "name": self.name,
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
            "R": self.R.tolist(),
            "t": self.t.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Camera:
        try:
            return cls(
                name=str(d["name"]),
                width=d["width"],
                height=d["height"],
                K=d["K"],
                R=d["R"],
                t=d["t"],
                dist=d.get("dist", np.zeros(5)),
            )
        except KeyError as exc:
            raise CalibrationError(
                f"camera {d.get('name', '?')!r}: missing field {exc.args[0]!r}"
            ) from None


#: Bytes of undistortion maps kept (the newest used first). Each (camera, scale) pair's maps
#: are 8 bytes per target pixel (16.6 MB for one 1080p camera at r = 1; 64 of them, the old
#: count limit, were 1 GB). The online controller moves r in small steps: a live run's
#: tasks hardly ever meet a scale again (60 tasks of caliscope_charuco computed 333 maps at
#: 60 sizes), so what the cache serves is one task's cameras (its views, then its masks)
#: and the fixed scales (the scene stage's working size, the golden r = 1): 96 MiB holds a
#: 4-camera 1080p rig's golden maps. A 256 MiB cache filled with stale scales in minutes;
#: maps cost 3-8 ms per camera to compute, nothing beside the task at that scale.
UNDISTORT_CACHE_BYTES = 96 * 2**20
_maps_cache: OrderedDict[tuple[Camera, float], tuple[NDArray[np.float32], NDArray[np.float32]]]
_maps_cache = OrderedDict()
_maps_lock = threading.Lock()


def _undistort_maps_cached(
    camera: Camera, scale: float
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """The maps of ``camera`` at ``scale``, from the cache when there (the least recently
    used go once the cache holds more than ``UNDISTORT_CACHE_BYTES``; the newest stays)."""
    key = (camera, scale)
    with _maps_lock:
        hit = _maps_cache.get(key)
        if hit is not None:
            _maps_cache.move_to_end(key)
            return hit
    target = camera.scaled(scale).undistorted()
    mx, my = cv2.initUndistortRectifyMap(
        camera.K, camera.dist, None, target.K, target.size, cv2.CV_32FC1
    )
    maps = np.asarray(mx, np.float32), np.asarray(my, np.float32)
    for m in maps:
        m.flags.writeable = False  # shared by every caller
    with _maps_lock:
        _maps_cache[key] = maps
        _maps_cache.move_to_end(key)
        total = sum(a.nbytes + b.nbytes for a, b in _maps_cache.values())
        while total > UNDISTORT_CACHE_BYTES and len(_maps_cache) > 1:
            _, (a, b) = _maps_cache.popitem(last=False)
            total -= a.nbytes + b.nbytes
    return maps


def _refine_undistortion(
    und: NDArray[np.float64],
    pixels: NDArray[np.float64],
    K: NDArray[np.float64],
    dist: NDArray[np.float64],
    iterations: int = 4,
) -> NDArray[np.float64]:
    """Newton steps on ``distort(x) = observed`` (OpenCV's fixed-point iteration stalls near
    the borders of strongly distorted lenses)."""
    Kinv = np.linalg.inv(K)
    target = pixels @ Kinv[:2, :2].T + Kinv[:2, 2]
    x, y = und[:, 0].copy(), und[:, 1].copy()
    h = 1e-7
    for _ in range(iterations):
        fx, fy = _distort(x, y, dist)
        rx, ry = fx - target[:, 0], fy - target[:, 1]
        ax, ay = _distort(x + h, y, dist)
        bx, by = _distort(x, y + h, dist)
        j11, j21 = (ax - fx) / h, (ay - fy) / h
        j12, j22 = (bx - fx) / h, (by - fy) / h
        det = j11 * j22 - j12 * j21
        ok = np.abs(det) > 1e-12
        det = np.where(ok, det, 1.0)
        x = np.where(ok, x - (j22 * rx - j12 * ry) / det, x)
        y = np.where(ok, y - (-j21 * rx + j11 * ry) / det, y)
    return np.stack([x, y], axis=1)


def _distort(
    xn: NDArray[np.float64], yn: NDArray[np.float64], dist: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    k1, k2, p1, p2, k3 = dist
    # Points near the camera's plane (a hull voxel beside a camera) have huge normalised
    # coordinates: their polynomial overflows to inf / nan, pixels no image holds, which
    # callers drop like any other pixel outside the image.
    with np.errstate(over="ignore", invalid="ignore"):
        r2 = xn * xn + yn * yn
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
        yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
    return xd, yd


@dataclass(frozen=True, kw_only=True)
class Rig:
    """N >= 3 static calibrated cameras sharing one world frame."""

    cameras: tuple[Camera, ...]
    """The cameras, in a fixed order; indices into this tuple are the camera ids."""
    unit: str = "m"
    """Length unit of the world frame ("m", "mm", ...)."""
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    """World 'up' direction (utrecht4cam's board frame has up = -Z), for viewers and floors."""
    min_cameras: int = 3
    """Smallest rig accepted (3 for reconstruction; sub-rigs may lower it explicitly)."""
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """World position of the frame the cameras are given in: a point's world coordinates are
    its coordinates in this frame plus ``origin``. Zero unless the rig was ``localised`` (a
    rig far from its world's origin, in georeferenced UTM or ECEF coordinates)."""
    crs: str | None = None
    """The coordinate reference system of the world frame, as the user gave it ("EPSG:32633",
    WKT): a georeferenced rig's; written into LAS exports (``io.crs`` checks it). None: a
    local frame."""

    def __post_init__(self) -> None:
        cams = tuple(self.cameras)
        object.__setattr__(self, "cameras", cams)
        if len(cams) < self.min_cameras:
            raise CalibrationError(
                f"a rig needs at least {self.min_cameras} cameras, got {len(cams)}"
                + (f" ({', '.join(c.name for c in cams)})" if cams else "")
            )
        names = [c.name for c in cams]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise CalibrationError(f"duplicate camera names in rig: {sorted(dup)}")
        centers = np.array([c.center for c in cams])
        for i in range(len(cams)):
            for j in range(i + 1, len(cams)):
                if np.linalg.norm(centers[i] - centers[j]) == 0:
                    raise CalibrationError(
                        f"cameras {cams[i].name!r} and {cams[j].name!r} have the same centre"
                    )
        object.__setattr__(self, "up", tuple(float(x) for x in self.up))
        origin = tuple(float(x) for x in self.origin)
        if len(origin) != 3 or not all(np.isfinite(origin)):
            raise CalibrationError(f"a rig's origin must be 3 finite numbers, got {self.origin}")
        object.__setattr__(self, "origin", origin)

    def __len__(self) -> int:
        return len(self.cameras)

    def __iter__(self) -> Iterator[Camera]:
        return iter(self.cameras)

    def __getitem__(self, i: int) -> Camera:
        return self.cameras[i]

    @property
    def num_cameras(self) -> int:
        return len(self.cameras)

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def index(self, name_or_index: str | int) -> int:
        """Camera id from a name or an index (as given on the command line)."""
        if isinstance(name_or_index, int | np.integer):
            i = int(name_or_index)
            if not 0 <= i < len(self.cameras):
                raise ValueError(f"camera index {i} out of range 0..{len(self.cameras) - 1}")
            return i
        names = self.names
        if name_or_index in names:
            return names.index(name_or_index)
        if str(name_or_index).lstrip("-").isdigit():
            return self.index(int(name_or_index))
        raise ValueError(f"unknown camera {name_or_index!r}; this rig has {names}")

    def subset(self, camera_ids: Sequence[int], min_cameras: int | None = None) -> Rig:
        """The rig restricted to ``camera_ids`` (in that order)."""
        ids = [self.index(i) for i in camera_ids]
        return dataclasses.replace(
            self,
            cameras=tuple(self.cameras[i] for i in ids),
            min_cameras=self.min_cameras if min_cameras is None else min_cameras,
        )

    def scaled(self, scale: float) -> Rig:
        return dataclasses.replace(self, cameras=tuple(c.scaled(scale) for c in self.cameras))

    def undistorted(self) -> Rig:
        return dataclasses.replace(self, cameras=tuple(c.undistorted() for c in self.cameras))

    @property
    def centers(self) -> NDArray[np.float64]:
        """(N, 3) camera centres."""
        return np.array([c.center for c in self.cameras])

    def scene_scale(self) -> float:
        """Median distance between camera centres (a natural length scale of the rig)."""
        c = self.centers
        d = np.linalg.norm(c[:, None] - c[None], axis=2)
        return float(np.median(d[np.triu_indices(len(c), 1)]))

    def localised(self, max_offset: float = 100.0) -> Rig:
        """The rig in a frame near its cameras (``origin`` set) when their mean centre is
        more than ``max_offset`` times the rig's size from the world's origin, else itself.

        Georeferenced rigs (UTM: millions of metres; ECEF) lose millimetres to metres in
        float32 arithmetic (depth maps, fusion, voxel grids, PLY coordinates); in the local
        frame the same arithmetic is as exact as for any rig. The origin is the mean centre
        rounded to a power of ten below the rig's size; poses are moved in float64."""
        if any(self.origin):
            return self
        mean = self.centers.mean(axis=0)
        size = self.scene_scale()
        if not size > 0 or float(np.linalg.norm(mean)) <= max_offset * size:
            return self
        step = 10.0 ** np.floor(np.log10(size))
        o = np.round(mean / step) * step
        cams = tuple(dataclasses.replace(c, t=c.t + c.R @ o) for c in self.cameras)
        return dataclasses.replace(
            self, cameras=cams, origin=(float(o[0]), float(o[1]), float(o[2]))
        )

    def in_world(self) -> Rig:
        """The rig with its cameras in world coordinates (``origin`` zero)."""
        if not any(self.origin):
            return self
        o = np.asarray(self.origin, np.float64)
        cams = tuple(dataclasses.replace(c, t=c.t - c.R @ o) for c in self.cameras)
        return dataclasses.replace(self, cameras=cams, origin=(0.0, 0.0, 0.0))

    def to_dict(self) -> dict[str, Any]:
        d = {
            "format": "edgerecon-rig",
            "version": 1,
            "unit": self.unit,
            "up": list(self.up),
            "cameras": [c.to_dict() for c in self.cameras],
        }
        if any(self.origin):
            d["origin"] = list(self.origin)
        if self.crs:
            d["crs"] = self.crs
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Rig:
        if d.get("format") != "edgerecon-rig":
            raise CalibrationError("not an edgerecon rig file (missing format: edgerecon-rig)")
        cams = tuple(Camera.from_dict(c) for c in d.get("cameras", []))
        return cls(
            cameras=cams,
            unit=str(d.get("unit", "m")),
            up=tuple(d.get("up", (0.0, 0.0, 1.0))),
            origin=tuple(d.get("origin", (0.0, 0.0, 0.0))),
            crs=str(d["crs"]) if d.get("crs") else None,
        )


def fundamental_matrix(cam_a: Camera, cam_b: Camera) -> NDArray[np.float64]:
    """F such that ``x_b^T F x_a = 0`` for undistorted pixels of the same 3D point."""
    R = cam_b.R @ cam_a.R.T
    t = cam_b.t - R @ cam_a.t
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    E = tx @ R
    F = np.linalg.inv(cam_b.K).T @ E @ np.linalg.inv(cam_a.K)
    return F / np.linalg.norm(F)


def rotation_angle_deg(Ra: NDArray[np.float64], Rb: NDArray[np.float64]) -> float:
    """The angle (degrees) of the rotation that takes ``Rb`` to ``Ra``."""
    c = (float(np.trace(Ra @ Rb.T)) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


def triangulation_angle_deg(
    cam_a: Camera, cam_b: Camera, points3D: Points3D
) -> NDArray[np.float64]:
    """(N,) angle in degrees between the rays from both camera centres to each point."""
    pts = np.asarray(points3D, dtype=np.float64).reshape(-1, 3)
    da = pts - cam_a.center
    db = pts - cam_b.center
    cos = np.einsum("ij,ij->i", da, db) / (
        np.linalg.norm(da, axis=1) * np.linalg.norm(db, axis=1) + 1e-300
    )
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def look_at(
    center: Sequence[float], target: Sequence[float], up: Sequence[float] = (0.0, 0.0, 1.0)
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(R, t) of ``cam_from_world`` for a camera at ``center`` looking at ``target`` with the
    image's 'up' (-y) as close to ``up`` as possible."""
    c = np.asarray(center, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - c
    z /= np.linalg.norm(z)
    u = np.asarray(up, dtype=np.float64)
    x = np.cross(z, u)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: viewing direction is parallel to 'up'")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ c
