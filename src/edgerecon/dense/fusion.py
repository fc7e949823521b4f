"""Fusion of per-view depth maps into one coloured point cloud with normals.

* Normals come from the depth maps: tangents are finite differences of the back-projected
  pixels (skipping depth discontinuities), averaged over a small window by normalised
  convolution; the normal is their cross product, turned towards the camera. Pixels without
  usable neighbours get the direction towards the camera.
* De-duplication: points of all views are binned in a voxel grid fixed in the world (corners
  at multiples of the voxel edge, whatever the points' box); each occupied voxel becomes
  one point with the mean position, colour and normal of its members and the largest number
  of views that supported any of them.
* Inferred points (``ViewPoints.inferred``: ground-plane completion) never move a measured
  one: in a voxel that holds a measured point the inferred members are left out, and a
  fused point is flagged inferred (``PointCloud.inferred``) only when all its members were.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.dense import kernels
from edgerecon.geometry.camera import Camera
from edgerecon.types import INFERRED, DepthMap, Image, PointCloud

#: Neighbouring depths that differ by more than this share are a discontinuity, not a slope.
_MAX_REL_STEP = 0.05
#: Pixel distance of the finite differences that give point normals.
NORMAL_STRIDE_PX = 2


def camera_points(camera: Camera, depth: DepthMap) -> NDArray[np.float32]:
    """(H, W, 3) camera-frame points of every pixel (depth 0 -> the origin)."""
    h, w = depth.shape
    Kinv = np.linalg.inv(camera.K).astype(np.float32)
    u = np.arange(w, dtype=np.float32)[None, :]
    v = np.arange(h, dtype=np.float32)[:, None]
    x = (Kinv[0, 0] * u + Kinv[0, 1] * v + Kinv[0, 2]) * depth
    y = (Kinv[1, 1] * v + Kinv[1, 2]) * depth
    return np.stack([x, y, depth.astype(np.float32)], axis=-1)


def depth_normals(camera: Camera, depth: DepthMap, radius: int = 2) -> NDArray[np.float32]:
    """(H, W, 3) unit normals in the camera frame, facing the camera (n . X < 0); zero where
    the depth is 0."""
    X = camera_points(camera, depth)
    valid = depth > 0

    def tangent(axis: int) -> NDArray[np.float32]:
        """Mean finite difference along ``axis`` around each pixel, window-averaged."""
        d = np.diff(X, axis=axis)
        a = np.take(depth, range(depth.shape[axis] - 1), axis=axis)
        b = np.take(depth, range(1, depth.shape[axis]), axis=axis)
        ok = (a > 0) & (b > 0) & (np.abs(a - b) <= _MAX_REL_STEP * np.minimum(a, b))
        d = d * ok[..., None]
        before = [(1, 0), (0, 0)] if axis == 0 else [(0, 0), (1, 0)]
        after = [(0, 1), (0, 0)] if axis == 0 else [(0, 0), (0, 1)]
        num = np.pad(d, [*before, (0, 0)]) + np.pad(d, [*after, (0, 0)])
        okf = ok.astype(np.float32)
        den = np.pad(okf, before) + np.pad(okf, after)
        k = (2 * radius + 1, 2 * radius + 1)
        num = cv2.boxFilter(num, -1, k, normalize=False)
        den = cv2.boxFilter(den, -1, k, normalize=False)[..., None]
        return np.where(den > 0, num / np.maximum(den, 1e-12), 0.0).astype(np.float32)

    tu = tangent(1)
    tv = tangent(0)
    n = np.cross(tu, tv)
    norm = np.linalg.norm(n, axis=2, keepdims=True)
    good = norm[..., 0] > 1e-12
    n = np.where(good[..., None], n / np.maximum(norm, 1e-30), 0.0)
    # Face the camera: n . X < 0.
    flip = np.einsum("ijk,ijk->ij", n, X) > 0
    n[flip] *= -1.0
    # No usable tangents: point the normal at the camera.
    lost = valid & ~good
    if lost.any():
        Xl = X[lost]
        n[lost] = -Xl / np.linalg.norm(Xl, axis=1, keepdims=True)
    n[~valid] = 0.0
    return n.astype(np.float32)


@dataclass(frozen=True, eq=False)
class ViewPoints:
    """The points one view contributes to fusion."""

    camera_id: int
    points3D: NDArray[np.float64]
    colors: NDArray[np.uint8]
    """(N, 3) RGB."""
    normals: NDArray[np.float32]
    """(N, 3) world unit normals."""
    num_views: NDArray[np.int16]
    """(N,) supporting views including this one."""
    score: NDArray[np.float32]
    """(N,) matching score (aggregated NCC)."""
    inferred: bool = False
    """All the points are inferred (not measured by stereo), e.g. ground-plane completion."""

    def select(self, keep: NDArray[np.bool_]) -> ViewPoints:
        """The points at ``keep`` (same view, same flag)."""
        return ViewPoints(
            camera_id=self.camera_id,
            points3D=self.points3D[keep],
            colors=self.colors[keep],
            normals=self.normals[keep],
            num_views=self.num_views[keep],
            score=self.score[keep],
            inferred=self.inferred,
        )


def view_points(
    camera_id: int,
    camera: Camera,
    depth: DepthMap,
    image: Image,
    keep: NDArray[np.bool_],
    support: NDArray[np.int16],
    score: NDArray[np.float32],
) -> ViewPoints:
    """Points, colours, world normals of the pixels ``keep`` of a depth map."""
    pts, normals, idx = kernels.view_points(
        np.ascontiguousarray(depth, dtype=np.float32),
        np.ascontiguousarray(keep),
        np.linalg.inv(camera.K).astype(np.float64),
        camera.R,
        camera.t,
        NORMAL_STRIDE_PX,
        _MAX_REL_STEP,
    )
    bgr = image.reshape(-1, 3)[idx]
    return ViewPoints(
        camera_id=camera_id,
        points3D=pts,
        colors=np.ascontiguousarray(bgr[:, ::-1]),
        normals=normals,
        num_views=(support.ravel()[idx] + 1).astype(np.int16),
        score=score.ravel()[idx].astype(np.float32),
    )


def voxel_merge(parts: Sequence[ViewPoints], voxel: float) -> PointCloud:
    """One point per occupied voxel of edge ``voxel``: mean position, colour and normal,
    the largest ``num_views``, the mean score (``confidence``)."""
    parts = [p for p in parts if len(p.points3D)]
    if not parts:
        return PointCloud(
            points3D=np.zeros((0, 3)),
            colors=np.zeros((0, 3), np.uint8),
            normals=np.zeros((0, 3), np.float32),
            confidence=np.zeros(0, np.float32),
            attributes={"num_views": np.zeros(0, np.int32), INFERRED: np.zeros(0, np.uint8)},
        )
    X = np.concatenate([p.points3D for p in parts])
    C = np.concatenate([p.colors for p in parts])
    N = np.concatenate([p.normals for p in parts])
    V = np.concatenate([p.num_views for p in parts]).astype(np.int32)
    S = np.concatenate([p.score for p in parts]).astype(np.float32)
    inferred = np.concatenate([np.full(len(p.points3D), p.inferred, bool) for p in parts])
    flat = kernels.voxel_keys(X, float(voxel))
    order = np.argsort(flat)
    fs = flat[order]
    starts = np.concatenate([[0], np.nonzero(np.diff(fs))[0] + 1]).astype(np.int64)
    if inferred.any() and not inferred.all():
        # Inferred points in a voxel that holds a measured point are left out (one sort:
        # a voxel's members are contiguous in ``order``).
        measured = ~inferred[order]
        has_measured = np.maximum.reduceat(measured, starts)
        voxel_of = np.repeat(np.arange(len(starts)), np.diff(np.append(starts, len(order))))
        keep = measured | ~has_measured[voxel_of]
        order, fs = order[keep], fs[keep]
        starts = np.concatenate([[0], np.nonzero(np.diff(fs))[0] + 1]).astype(np.int64)
    pts, cols, nrm, views, conf = kernels.merge_sorted(order, starts, X, C, N, V, S)
    # A voxel's members are all measured or all inferred (see above): its first member says.
    flag = inferred[order[starts]].astype(np.uint8)
    return PointCloud(
        points3D=pts,
        colors=cols,
        normals=nrm,
        confidence=conf,
        attributes={"num_views": views, INFERRED: flag},
    )
