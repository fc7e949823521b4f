"""Synthetic scenes with exact ground truth for the sparse tests: textured planes (a floor and
a box) rendered into a ring of pinhole cameras with ``cv2.warpPerspective``."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry import Camera, Rig
from edgerecon.views import View
from tests.conftest import ring_rig

TEXTURE_PX = 768


def texture(seed: int, size: int = TEXTURE_PX) -> NDArray[np.uint8]:
    """A colourful multi-scale noise texture (blobs and corners SIFT can find)."""
    rng = np.random.default_rng(seed)
    out = np.zeros((size, size, 3), np.float32)
    for sigma, weight in ((2.0, 0.5), (5.0, 1.0), (12.0, 1.0)):
        noise = rng.standard_normal((size, size, 3)).astype(np.float32)
        noise = cv2.GaussianBlur(noise, (0, 0), sigma)
        out += weight * noise / noise.std()
    out = (out - out.min()) / (out.max() - out.min()) * 255
    return out.astype(np.uint8)


@dataclass(frozen=True)
class Plane:
    """The rectangle ``origin + a * u + b * v`` for a, b in [0, 1]."""

    origin: NDArray[np.float64]
    u: NDArray[np.float64]
    v: NDArray[np.float64]
    texture: NDArray[np.uint8]

    @property
    def normal(self) -> NDArray[np.float64]:
        n = np.cross(self.u, self.v)
        return n / np.linalg.norm(n)

    @property
    def centre(self) -> NDArray[np.float64]:
        return self.origin + 0.5 * (self.u + self.v)

    def distance(self, points: NDArray[np.float64]) -> NDArray[np.float64]:
        """Distance of points to the rectangle (exact)."""
        d = points - self.origin
        a = np.clip(d @ self.u / (self.u @ self.u), 0, 1)
        b = np.clip(d @ self.v / (self.v @ self.v), 0, 1)
        closest = self.origin + a[:, None] * self.u + b[:, None] * self.v
        return np.linalg.norm(points - closest, axis=1)


def box_scene(seed: int = 0) -> list[Plane]:
    """A 4 m x 4 m textured floor (z = 0) and a 1 m textured cube standing on it (z up)."""
    e = np.eye(3)
    planes = [Plane(np.array([-2.0, -2.0, 0.0]), 4 * e[0], 4 * e[1], texture(seed))]
    c = np.array([-0.5, -0.5, 0.0])
    faces = [
        (c, e[0], e[2]),  # y = -0.5, normal -y
        (c + e[0], e[1], e[2]),  # x = 0.5, normal +x
        (c + e[0] + e[1], -e[0], e[2]),  # y = 0.5, normal +y
        (c + e[1], -e[1], e[2]),  # x = -0.5, normal -x
        (c + e[2], e[0], e[1]),  # top, normal +z
    ]
    for k, (o, u, v) in enumerate(faces):
        planes.append(
            Plane(o.astype(float), u.astype(float), v.astype(float), texture(seed + k + 1))
        )
    return planes


def render(camera: Camera, planes: list[Plane]) -> NDArray[np.uint8]:
    """Image of the planes (floor first, then the faces that face the camera)."""
    image = np.full((camera.height, camera.width, 3), 40, np.uint8)
    for k, p in enumerate(planes):
        if k > 0 and p.normal @ (camera.center - p.centre) <= 0:
            continue  # back face of the convex box
        ts = p.texture.shape[0] - 1
        M = np.column_stack(
            [camera.R @ p.u / ts, camera.R @ p.v / ts, camera.R @ p.origin + camera.t]
        )
        H = camera.K @ M
        warped = cv2.warpPerspective(p.texture, H, camera.size, flags=cv2.INTER_LINEAR)
        cover = cv2.warpPerspective(
            np.full(p.texture.shape[:2], 255, np.uint8), H, camera.size, flags=cv2.INTER_NEAREST
        )
        image[cover > 0] = warped[cover > 0]
    return image


def scene_distance(planes: list[Plane], points: NDArray[np.float64]) -> NDArray[np.float64]:
    """Distance of each point to the nearest scene surface."""
    return np.min([p.distance(points) for p in planes], axis=0)


def box_views(
    num_cameras: int = 6, seed: int = 0, **rig_kwargs: float
) -> tuple[Rig, list[View], list[Plane]]:
    """A ring rig around the box scene and its rendered views (cached: rendering is the slow
    part of the tests; the returned lists are fresh copies)."""
    rig, views, planes = _box_views(num_cameras, seed, tuple(sorted(rig_kwargs.items())))
    return rig, list(views), list(planes)


@functools.lru_cache(maxsize=16)
def _box_views(
    num_cameras: int, seed: int, rig_kwargs: tuple[tuple[str, float], ...]
) -> tuple[Rig, tuple[View, ...], tuple[Plane, ...]]:
    rig = ring_rig(num_cameras, **dict(rig_kwargs))  # type: ignore[arg-type]
    planes = box_scene(seed)
    views = tuple(View(camera_id=i, camera=c, image=render(c, planes)) for i, c in enumerate(rig))
    return rig, views, tuple(planes)
