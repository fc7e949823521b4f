"""Analytic surfaces of the synthetic scene and their vectorised ray intersections.

Rays come in the renderer's form: a camera centre ``origin`` (world) and, per pixel, the
normalised camera-frame coordinates ``(xn, yn)`` of its ray, so that the world direction is
``D = world_from_cam @ (xn, yn, 1)``. With that (un-normalised) direction the ray parameter
``s`` of a hit *is* the depth along the optical axis (Camera.project's convention), which the
renderer writes straight into the depth map.

Each primitive computes ``s`` (float32, ``inf`` where the ray misses) and, for points known to
lie on it, the surface normal, texture coordinates (metres) and material index. Intersections
use numerically stable forms (closest approach of the ray to the centre, not the textbook
discriminant) because they run in float32.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]

#: Smallest accepted ray parameter (hits closer to the camera than this are ignored), metres.
MIN_DEPTH = 1e-3


@dataclass(frozen=True)
class Surface:
    """Shading inputs at points on a primitive (one row per point)."""

    normals: F32
    """(N, 3) unit outward normals (world)."""
    u: F32
    """(N,) first texture coordinate, metres."""
    v: F32
    """(N,) second texture coordinate, metres."""
    material: NDArray[np.int32]
    """(N,) index into the scene's texture list."""


def local_directions(B: F64, xn: F32, yn: F32) -> tuple[F32, F32, F32]:
    """Components of ``B @ (xn, yn, 1)`` for every ray, float32."""
    b = B.astype(np.float32)
    return (
        b[0, 0] * xn + b[0, 1] * yn + b[0, 2],
        b[1, 0] * xn + b[1, 1] * yn + b[1, 2],
        b[2, 0] * xn + b[2, 1] * yn + b[2, 2],
    )


def _rot_z(yaw: float) -> F64:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _box_corners(center: F64, rot: F64, half: F64) -> F64:
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
    return center + (signs * half) @ rot.T


@dataclass(frozen=True, eq=False)
class Room:
    """The inside of an axis-aligned box: floor (z = 0), ceiling and four walls.

    Cameras must be inside; every ray leaves the room through exactly one face.
    Faces, in material order: floor, ceiling, wall x-, wall x+, wall y-, wall y+.
    """

    half_x: float
    half_y: float
    height: float
    materials: tuple[int, int, int, int, int, int]

    def contains(self, point: F64, margin: float = 0.0) -> bool:
        x, y, z = point
        return bool(
            abs(x) < self.half_x - margin
            and abs(y) < self.half_y - margin
            and margin < z < self.height - margin
        )

    def intersect(self, origin: F64, world_from_cam: F64, xn: F32, yn: F32) -> F32:
        dx, dy, dz = local_directions(world_from_cam, xn, yn)
        lo = np.array([-self.half_x, -self.half_y, 0.0]) - origin
        hi = np.array([self.half_x, self.half_y, self.height]) - origin
        s = None
        with np.errstate(divide="ignore", invalid="ignore"):
            for d, a, b in ((dx, lo[0], hi[0]), (dy, lo[1], hi[1]), (dz, lo[2], hi[2])):
                exit_s = np.where(d > 0, np.float32(b) / d, np.float32(a) / d)
                exit_s = np.where(d == 0, np.float32(np.inf), exit_s)
                s = exit_s if s is None else np.minimum(s, exit_s)
        assert s is not None
        return s.astype(np.float32, copy=False)

    def surface(self, points: F32) -> Surface:
        x, y, z = points[:, 0], points[:, 1], points[:, 2]
        dist = np.stack(
            [
                z,
                self.height - z,
                x + self.half_x,
                self.half_x - x,
                y + self.half_y,
                self.half_y - y,
            ],
            axis=1,
        )
        face = np.argmin(np.abs(dist), axis=1)
        normals_table = np.array(
            [[0, 0, 1], [0, 0, -1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]], np.float32
        )
        normals = normals_table[face]
        # Floor/ceiling use (x, y); walls use (horizontal coordinate, z).
        u = np.where(face < 2, x, np.where(face < 4, y, x)).astype(np.float32)
        v = np.where(face < 2, y, z).astype(np.float32)
        material = np.asarray(self.materials, np.int32)[face]
        return Surface(normals=normals, u=u, v=v, material=material)


@dataclass(frozen=True, eq=False)
class Box:
    """A solid box standing upright, rotated by ``yaw`` about the vertical axis."""

    center: F64
    """(3,) centre, metres."""
    half: F64
    """(3,) half sizes along the box's own x, y, z axes."""
    yaw: float
    """Rotation about world z, radians."""
    side_material: int
    top_material: int

    @property
    def rotation(self) -> F64:
        return _rot_z(self.yaw)

    def corners(self) -> F64:
        return _box_corners(np.asarray(self.center, float), self.rotation, np.asarray(self.half))

    def intersect(self, origin: F64, world_from_cam: F64, xn: F32, yn: F32) -> F32:
        rot = self.rotation
        o = rot.T @ (origin - self.center)
        dirs = local_directions(rot.T @ world_from_cam, xn, yn)
        near = far = None
        with np.errstate(divide="ignore", invalid="ignore"):
            for d, ok, hk in zip(dirs, o, self.half, strict=True):
                inv = np.float32(1.0) / d
                t1 = np.float32(-hk - ok) * inv
                t2 = np.float32(hk - ok) * inv
                tmin, tmax = np.minimum(t1, t2), np.maximum(t1, t2)
                near = tmin if near is None else np.maximum(near, tmin)
                far = tmax if far is None else np.minimum(far, tmax)
        assert near is not None and far is not None
        hit = (near <= far) & (near > MIN_DEPTH)
        return np.where(hit, near, np.float32(np.inf)).astype(np.float32, copy=False)

    def surface(self, points: F32) -> Surface:
        rot = self.rotation.astype(np.float32)
        local = (points - self.center.astype(np.float32)) @ rot
        rel = np.abs(local) / self.half.astype(np.float32)
        axis = np.argmax(rel, axis=1)
        sign = np.sign(local[np.arange(len(local)), axis]).astype(np.float32)
        n_local = np.zeros_like(local)
        n_local[np.arange(len(local)), axis] = sign
        normals = n_local @ rot.T
        lx, ly, lz = local[:, 0], local[:, 1], local[:, 2]
        # Each face gets its own region of the texture (offsets) so faces do not look alike.
        u = np.where(axis == 0, ly + 1.3 * sign, np.where(axis == 1, lx + 2.9 * sign, lx))
        v = np.where(axis == 2, ly, lz + 0.7 * axis)
        top = (axis == 2) & (sign > 0)
        material = np.where(top, self.top_material, self.side_material).astype(np.int32)
        return Surface(
            normals=normals.astype(np.float32),
            u=u.astype(np.float32),
            v=v.astype(np.float32),
            material=material,
        )


@dataclass(frozen=True, eq=False)
class Cylinder:
    """An upright solid cylinder (pillar, barrel, round table) from ``z0`` to ``z1``."""

    center_xy: tuple[float, float]
    radius: float
    z0: float
    z1: float
    side_material: int
    top_material: int

    def corners(self) -> F64:
        cx, cy = self.center_xy
        half = np.array([self.radius, self.radius, 0.5 * (self.z1 - self.z0)])
        return _box_corners(np.array([cx, cy, 0.5 * (self.z0 + self.z1)]), np.eye(3), half)

    def intersect(self, origin: F64, world_from_cam: F64, xn: F32, yn: F32) -> F32:
        cx, cy = self.center_xy
        ox, oy, oz = (np.float32(v) for v in (origin[0] - cx, origin[1] - cy, origin[2]))
        dx, dy, dz = local_directions(world_from_cam, xn, yn)
        r = np.float32(self.radius)
        inf = np.float32(np.inf)
        with np.errstate(divide="ignore", invalid="ignore"):
            a = dx * dx + dy * dy
            sc = -(ox * dx + oy * dy) / a
            qx, qy = ox + sc * dx, oy + sc * dy
            disc = (r * r - (qx * qx + qy * qy)) / a
            s_side = sc - np.sqrt(np.maximum(disc, 0))
            z = oz + s_side * dz
            side_ok = (disc >= 0) & (z >= self.z0) & (z <= self.z1) & (s_side > MIN_DEPTH)
            s = np.where(side_ok, s_side, inf)
            for zc in (self.z1, self.z0):
                s_cap = (np.float32(zc) - oz) / dz
                px, py = ox + s_cap * dx, oy + s_cap * dy
                cap_ok = (px * px + py * py <= r * r) & (s_cap > MIN_DEPTH)
                s = np.where(cap_ok, np.minimum(s, s_cap), s)
        return s.astype(np.float32, copy=False)

    def surface(self, points: F32) -> Surface:
        cx, cy = self.center_xy
        x = points[:, 0] - np.float32(cx)
        y = points[:, 1] - np.float32(cy)
        z = points[:, 2]
        rho = np.sqrt(x * x + y * y)
        d_side = np.abs(rho - self.radius)
        d_top = np.abs(z - self.z1)
        d_bot = np.abs(z - self.z0)
        cap = np.minimum(d_top, d_bot) < d_side
        top = cap & (d_top <= d_bot)
        with np.errstate(invalid="ignore", divide="ignore"):
            nx = np.where(cap, 0.0, x / np.maximum(rho, 1e-9))
            ny = np.where(cap, 0.0, y / np.maximum(rho, 1e-9))
        nz = np.where(cap, np.where(top, 1.0, -1.0), 0.0)
        normals = np.stack([nx, ny, nz], axis=1).astype(np.float32)
        angle = np.arctan2(y, x)
        u = np.where(cap, x, angle * self.radius).astype(np.float32)
        v = np.where(cap, y, z).astype(np.float32)
        material = np.where(cap, self.top_material, self.side_material).astype(np.int32)
        return Surface(normals=normals, u=u, v=v, material=material)


@dataclass(frozen=True, eq=False)
class Ellipsoid:
    """An ellipsoid ``|diag(1/radii) rotation^T (X - center)| = 1`` (a body part).

    The local z axis is the long axis of a limb; texture coordinates wrap around it:
    ``u = angle / 2 pi * u_period_m``, ``v = local z`` (metres) + ``v_offset_m``.
    """

    center: F64
    """(3,) centre, world."""
    rotation: F64
    """(3, 3) columns = the ellipsoid's local x, y, z axes in world coordinates."""
    radii: F64
    """(3,) semi-axes along local x, y, z, metres."""
    material: int
    u_period_m: float
    """Texture length mapped once around the long axis (a whole number of texture periods)."""
    v_offset_m: float = 0.0

    def corners(self) -> F64:
        return _box_corners(self.center, self.rotation, self.radii)

    def _to_unit(self) -> F64:
        return (self.rotation / self.radii[None, :]).T  # diag(1/r) Q^T

    def intersect(self, origin: F64, world_from_cam: F64, xn: F32, yn: F32) -> F32:
        A = self._to_unit()
        o = (A @ (origin - self.center)).astype(np.float32)
        dx, dy, dz = local_directions(A @ world_from_cam, xn, yn)
        with np.errstate(divide="ignore", invalid="ignore"):
            a = dx * dx + dy * dy + dz * dz
            sc = -(o[0] * dx + o[1] * dy + o[2] * dz) / a
            qx, qy, qz = o[0] + sc * dx, o[1] + sc * dy, o[2] + sc * dz
            disc = (np.float32(1.0) - (qx * qx + qy * qy + qz * qz)) / a
            s = sc - np.sqrt(np.maximum(disc, 0))
        hit = (disc >= 0) & (s > MIN_DEPTH)
        return np.where(hit, s, np.float32(np.inf)).astype(np.float32, copy=False)

    def surface(self, points: F32) -> Surface:
        Q = self.rotation.astype(np.float32)
        r = self.radii.astype(np.float32)
        local = (points - self.center.astype(np.float32)) @ Q  # metres, local axes
        unit = local / r
        n = (unit / r) @ Q.T
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        angle = np.arctan2(unit[:, 1], unit[:, 0])
        u = (angle + np.float32(np.pi)) * np.float32(self.u_period_m / (2 * np.pi))
        v = local[:, 2] + np.float32(self.v_offset_m)
        material = np.full(len(points), self.material, np.int32)
        return Surface(normals=n.astype(np.float32), u=u.astype(np.float32), v=v, material=material)
