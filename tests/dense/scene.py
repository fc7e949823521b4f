"""A tiny ray-cast renderer of textured rectangles: exact images and depth maps for tests.

Each rectangle is ``origin + s * u + t * v`` for s, t in [0, 1] with a texture image mapped
onto it. Every pixel's ray is intersected with every rectangle (vectorised); the nearest hit
gives the depth and the colour (bilinear texture lookup with ``cv2.remap``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry.camera import Camera, Rig
from edgerecon.views import View


def noise_texture(size: int, seed: int, scales: Sequence[int] = (2, 6, 18)) -> NDArray[np.uint8]:
    """Multi-scale random texture (BGR uint8, size x size), textured at every pyramid level."""
    rng = np.random.default_rng(seed)
    acc = np.zeros((size, size, 3), np.float32)
    for s in scales:
        small = rng.random((max(2, size // s), max(2, size // s), 3)).astype(np.float32)
        acc += cv2.resize(small, (size, size), interpolation=cv2.INTER_CUBIC)
    acc -= acc.min()
    acc /= acc.max()
    return (40 + 190 * acc).astype(np.uint8)


@dataclass(frozen=True, eq=False)
class Rect:
    origin: NDArray[np.float64]
    u: NDArray[np.float64]
    v: NDArray[np.float64]
    texture: NDArray[np.uint8]

    @staticmethod
    def make(
        origin: Sequence[float], u: Sequence[float], v: Sequence[float], seed: int, px: int = 512
    ) -> Rect:
        return Rect(
            np.asarray(origin, float),
            np.asarray(u, float),
            np.asarray(v, float),
            noise_texture(px, seed),
        )


def box_scene(seed: int = 0) -> list[Rect]:
    """A textured floor (6 x 6 m, z = 0) with a 0.8 m cube on it."""
    s = seed * 10
    rects = [Rect.make((-3, -3, 0), (6, 0, 0), (0, 6, 0), s + 1, 1024)]
    c, h = 0.4, 0.8
    # Cube faces (outward orientation does not matter for rendering).
    rects += [
        Rect.make((-c, -c, h), (2 * c, 0, 0), (0, 2 * c, 0), s + 3),
        Rect.make((-c, -c, 0), (2 * c, 0, 0), (0, 0, h), s + 4),
        Rect.make((-c, c, 0), (2 * c, 0, 0), (0, 0, h), s + 5),
        Rect.make((-c, -c, 0), (0, 2 * c, 0), (0, 0, h), s + 6),
        Rect.make((c, -c, 0), (0, 2 * c, 0), (0, 0, h), s + 7),
    ]
    return rects


def _bilinear(
    tex: NDArray[np.uint8], x: NDArray[np.float64], y: NDArray[np.float64]
) -> NDArray[np.uint8]:
    th, tw = tex.shape[:2]
    x0 = np.clip(np.floor(x).astype(int), 0, tw - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, th - 2)
    fx = np.clip(x - x0, 0, 1)[:, None]
    fy = np.clip(y - y0, 0, 1)[:, None]
    t = tex.astype(np.float64)
    c = (
        t[y0, x0] * (1 - fx) * (1 - fy)
        + t[y0, x0 + 1] * fx * (1 - fy)
        + t[y0 + 1, x0] * (1 - fx) * fy
        + t[y0 + 1, x0 + 1] * fx * fy
    )
    return np.clip(np.rint(c), 0, 255).astype(np.uint8)


def render(camera: Camera, rects: Sequence[Rect]) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
    """(BGR image, depth map) of ``rects`` seen by an undistorted ``camera`` (black, depth 0
    where nothing is hit)."""
    w, h = camera.size
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays_c = camera.pixel_rays(np.stack([u.ravel(), v.ravel()], axis=1))  # z = 1
    dirs = rays_c @ camera.R  # world directions (not unit; depth = parameter)
    C = camera.center
    best = np.full(len(dirs), np.inf)
    image = np.zeros((len(dirs), 3), np.uint8)
    for rect in rects:
        n = np.cross(rect.u, rect.v)
        denom = dirs @ n
        # Rays parallel to the plane meet it nowhere (inf / nan): never a hit.
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = ((rect.origin - C) @ n) / denom
            P = C + dirs * lam[:, None]
            rel = P - rect.origin
            # Solve rel = s u + t v in the least-squares sense (u, v orthogonal here).
            s = rel @ rect.u / (rect.u @ rect.u)
            t = rel @ rect.v / (rect.v @ rect.v)
            hit = (lam > 1e-6) & (s >= 0) & (s <= 1) & (t >= 0) & (t <= 1) & (lam < best)
        if not hit.any():
            continue
        th, tw = rect.texture.shape[:2]
        col = _bilinear(rect.texture, s[hit] * (tw - 1), t[hit] * (th - 1))
        image[hit] = col
        best[hit] = lam[hit]
    depth = np.where(np.isfinite(best), best, 0.0).astype(np.float32).reshape(h, w)
    return image.reshape(h, w, 3), depth


def render_views(
    rig: Rig, rects: Sequence[Rect], masks: Sequence[NDArray[np.bool_] | None] | None = None
):
    """Views of every camera of ``rig`` plus the ground-truth depth maps."""
    views, depths = [], []
    for i, cam in enumerate(rig):
        image, depth = render(cam, rects)
        mask = None if masks is None else masks[i]
        views.append(View(camera_id=i, camera=cam, image=image, mask=mask))
        depths.append(depth)
    return views, depths
