"""Small synthetic images and rigs with exact ground truth for the scene tests."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry import Camera, Rig

RNG_SEED = 7


def textured_background(h: int = 120, w: int = 160, seed: int = RNG_SEED) -> NDArray[np.uint8]:
    """A smooth random colour texture (what a room looks like to a background model)."""
    rng = np.random.default_rng(seed)
    small = rng.integers(40, 215, size=(h // 8 + 1, w // 8 + 1, 3)).astype(np.uint8)
    return np.ascontiguousarray(cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC))


def noisy(image: NDArray[np.uint8], sigma: float, rng: np.random.Generator) -> NDArray[np.uint8]:
    noise = rng.normal(0.0, sigma, image.shape)
    return np.clip(image.astype(np.float64) + noise, 0, 255).astype(np.uint8)


def square_mask(h: int, w: int, x: int, y: int, size: int) -> NDArray[np.bool_]:
    m = np.zeros((h, w), bool)
    m[max(0, y) : max(0, y + size), max(0, x) : max(0, x + size)] = True
    return m


def paint(
    image: NDArray[np.uint8], mask: NDArray[np.bool_], color: tuple[int, int, int]
) -> NDArray[np.uint8]:
    out = image.copy()
    out[mask] = color
    return out


def box_corners(lo: NDArray[np.float64], hi: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    )


def box_silhouette(
    cam: Camera, lo: NDArray[np.float64], hi: NDArray[np.float64]
) -> NDArray[np.bool_]:
    """Exact silhouette of an axis-aligned box in an undistorted camera (convex polygon)."""
    uv, depth = cam.project(box_corners(lo, hi))
    assert np.all(depth > 0)
    hull = cv2.convexHull(uv.astype(np.float32)).reshape(-1, 2)
    m = np.zeros((cam.height, cam.width), np.uint8)
    # fillPoly with sub-pixel precision (shift=4) so the silhouette is exact to 1/16 px.
    cv2.fillPoly(m, [np.rint(hull * 16).astype(np.int32)], 1, lineType=cv2.LINE_8, shift=4)
    return m.astype(bool)


def box_surface_points(
    lo: NDArray[np.float64], hi: NDArray[np.float64], n: int = 20
) -> NDArray[np.float64]:
    """Points on the six faces of a box (an n x n grid per face)."""
    pts = []
    g = np.linspace(0.0, 1.0, n)
    a, b = np.meshgrid(g, g, indexing="ij")
    a, b = a.ravel(), b.ravel()
    for axis in range(3):
        u, v = [i for i in range(3) if i != axis]
        for side in (lo[axis], hi[axis]):
            p = np.zeros((len(a), 3))
            p[:, axis] = side
            p[:, u] = lo[u] + a * (hi[u] - lo[u])
            p[:, v] = lo[v] + b * (hi[v] - lo[v])
            pts.append(p)
    return np.concatenate(pts)


def ring_with_top(num_cameras: int = 6, width: int = 320, height: int = 240) -> Rig:
    """Ring cameras around the origin (metres, z up) looking at (0, 0, 1), plus variety in
    height so that the box's top and bottom are constrained."""
    from edgerecon.geometry import look_at

    cams = []
    f = 0.8 * width
    for i in range(num_cameras):
        a = 2 * np.pi * i / num_cameras
        z = 2.5 if i % 2 == 0 else 0.6
        R, t = look_at((4.0 * np.cos(a), 4.0 * np.sin(a), z), (0.0, 0.0, 1.0))
        K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]])
        cams.append(Camera(name=f"cam{i}", width=width, height=height, K=K, R=R, t=t))
    return Rig(cameras=tuple(cams), unit="m")
