"""Views: the undistorted, rescaled images of one task that the reconstruction stages consume.

Sparse and dense reconstruction never see distortion or the original resolution: they work on
``View`` objects whose camera is an ideal pinhole at the task's image scale r.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry.camera import Camera, Rig
from edgerecon.types import DataError, FrameSet, Image, Mask


@dataclass(frozen=True, kw_only=True, eq=False)
class View:
    """One camera's image of a task, ready for reconstruction."""

    camera_id: int
    """Index of the camera in the full rig (stable across camera subsets)."""
    camera: Camera
    """Undistorted pinhole camera at the working scale (``camera.size`` = image size)."""
    image: Image
    """(H, W, 3) BGR uint8, undistorted and resized."""
    mask: Mask | None = None
    """(H, W) bool region of interest (True = reconstruct here); None = whole image."""
    scale: float = 1.0
    """The task's image scale r: the image is r x the camera's frames (the dense stage picks
    its resolution level from the frames' size, ``DenseConfig.level_for``)."""
    source_size: tuple[int, int] | None = None
    """(w, h) of the camera's frames; None = the image size divided by ``scale``, rounded
    (``prepare_views`` sets it: at r = 0.955 a 1280-wide frame gives a 1222-wide view,
    and 1222 / 0.955 rounds to 1279, which would move the dense stage's level)."""

    def __post_init__(self) -> None:
        if not 0.0 < self.scale <= 1.0:
            raise ValueError(
                f"view {self.camera.name!r}: scale must be in (0, 1], got {self.scale}"
            )
        h, w = self.image.shape[:2]
        if (w, h) != self.camera.size:
            raise ValueError(
                f"view {self.camera.name!r}: image is {w}x{h}, camera expects "
                f"{self.camera.width}x{self.camera.height}"
            )
        if self.camera.has_distortion:
            raise ValueError(f"view {self.camera.name!r}: view cameras must be undistorted")
        if self.source_size is not None and (
            max(1, round(self.source_size[0] * self.scale)),
            max(1, round(self.source_size[1] * self.scale)),
        ) != (w, h):
            # Camera.scaled's rounding: the frames' size at the view's scale is the image's.
            raise ValueError(
                f"view {self.camera.name!r}: source_size {self.source_size} at scale "
                f"{self.scale} is not the image's {w}x{h}"
            )
        if self.mask is not None and self.mask.shape != (h, w):
            raise ValueError(f"view {self.camera.name!r}: mask shape {self.mask.shape} != {(h, w)}")

    @property
    def name(self) -> str:
        return self.camera.name

    @property
    def frame_size(self) -> tuple[int, int]:
        """(w, h) of the camera's frames (the view's size at r = 1)."""
        if self.source_size is not None:
            return self.source_size
        return (round(self.camera.width / self.scale), round(self.camera.height / self.scale))


def resize_mask(mask: Mask, size: tuple[int, int]) -> Mask:
    """Resize a boolean mask to ``size`` = (width, height) (nearest neighbour)."""
    if (mask.shape[1], mask.shape[0]) == size:
        return mask.astype(bool, copy=False)
    out = cv2.resize(mask.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST)
    return out.astype(bool)


def resize_mask_smooth(mask: Mask, size: tuple[int, int]) -> Mask:
    """Resize a mask to ``size`` = (width, height) with bilinear interpolation of the 0/1
    values and a 0.5 threshold: smoother silhouettes than nearest neighbour when upsampling."""
    mask = np.asarray(mask, dtype=bool)
    if (mask.shape[1], mask.shape[0]) == tuple(size):
        return mask
    if size[0] <= mask.shape[1]:
        return resize_mask(mask, size)
    up = cv2.resize(mask.astype(np.uint8) * 255, tuple(size), interpolation=cv2.INTER_LINEAR)
    return np.asarray(up > 127)


def mask_scale(mask: NDArray[np.generic], camera: Camera) -> float:
    """Size of a per-camera mask relative to the camera's frames (mask width / frame width).

    Masks and label images of a camera may be stored at any resolution with the frames'
    aspect ratio (the scene stage works at a reduced working resolution); anything else is a
    ``DataError`` naming the camera."""
    h, w = mask.shape[:2]
    s = w / camera.width
    if h <= 0 or w <= 0 or abs(h - s * camera.height) > max(1.0, 0.01 * h):
        raise DataError(
            f"camera {camera.name!r}: mask is {w}x{h}, which is not the {camera.width}x"
            f"{camera.height} frames' aspect ratio"
        )
    return s


def undistort_mask(camera: Camera, mask: Mask, scale: float) -> Mask:
    """Map a mask of a (possibly distorted) camera, at full or at a reduced resolution (see
    ``mask_scale``), to its undistorted view at ``scale``."""
    s = mask_scale(mask, camera)
    if not camera.has_distortion:
        return resize_mask(mask, camera.scaled(scale).size)
    mx, my = camera.undistort_maps(scale)
    if s != 1.0:
        # The maps address full-resolution pixels; pixel centres scale as (x + 0.5) s - 0.5.
        sy = mask.shape[0] / camera.height
        mx = (mx + np.float32(0.5)) * np.float32(s) - np.float32(0.5)
        my = (my + np.float32(0.5)) * np.float32(sy) - np.float32(0.5)
    out = cv2.remap(
        mask.astype(np.uint8) * 255,
        mx,
        my,
        interpolation=cv2.INTER_LINEAR if s < 1.0 else cv2.INTER_NEAREST,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )
    return out > 127


def prepare_views(
    frames: FrameSet,
    rig: Rig,
    scale: float = 1.0,
    camera_ids: Sequence[int] | None = None,
    masks: Sequence[Mask | None] | None = None,
) -> list[View]:
    """Undistort and rescale the frames of ``camera_ids`` (default: all with a frame).

    ``masks``, when given, holds one full-resolution mask (or None) per rig camera. Cameras
    without a frame are left out (the caller sees which in ``View.camera_id``).
    """
    if len(frames.images) != len(rig):
        raise DataError(
            f"frame set of time {frames.time_index} has {len(frames.images)} images for a rig of "
            f"{len(rig)} cameras"
        )
    if not 0.0 < scale <= 1.0:
        raise ValueError(f"scale must be in (0, 1], got {scale}")
    ids = list(range(len(rig))) if camera_ids is None else [rig.index(i) for i in camera_ids]
    views = []
    for i in ids:
        image = frames.images[i]
        if image is None:
            continue
        cam = rig[i]
        mask = None
        if masks is not None and masks[i] is not None:
            m = masks[i]
            if m.shape != (cam.height, cam.width):  # type: ignore[union-attr]
                raise DataError(
                    f"camera {cam.name!r}: mask is {m.shape[1]}x{m.shape[0]} but frames are "  # type: ignore[union-attr]
                    f"{cam.width}x{cam.height}"
                )
            mask = undistort_mask(cam, m, scale)  # type: ignore[arg-type]
        views.append(
            View(
                camera_id=i,
                camera=cam.scaled(scale).undistorted(),
                image=cam.prepare_image(image, scale),
                mask=mask,
                scale=scale,
                source_size=cam.size,
            )
        )
    return views


def with_masks(views: Sequence[View], rig: Rig, masks: Sequence[Mask | None]) -> list[View]:
    """The same views with per-rig-camera ``masks`` (full or reduced resolution, see
    ``mask_scale``) mapped onto them (a None mask keeps the whole view). Avoids undistorting
    the images again."""
    out = []
    for view in views:
        m = masks[view.camera_id]
        if m is None:
            out.append(dataclasses.replace(view, mask=None))
            continue
        cam = rig[view.camera_id]
        scale = view.camera.width / cam.width
        mask = undistort_mask(cam, m, scale)
        if mask.shape != (view.camera.height, view.camera.width):
            mask = resize_mask_smooth(mask, view.camera.size)
        out.append(dataclasses.replace(view, mask=mask))
    return out
