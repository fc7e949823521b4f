"""Is a frame usable at all? Black (lights out, lens cap), saturated (blinded) and textureless
(a uniform wall, a covered lens) frames carry nothing to reconstruct, and the scene stage
would take all of them for foreground (a lit background model sees every pixel change), so
the hull fills the room and the task costs many times the usual. They are found here, on a
subsample of the frame (~1 ms per camera), before any stage runs.
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.types import FrameSet, Image

#: Values of :func:`frame_defect`.
DEFECTS = ("black", "saturated", "textureless")


@dataclass(frozen=True, kw_only=True)
class FrameCheckConfig:
    """Thresholds of :func:`frame_defect` on 8-bit luminance."""

    black_max_level: float = 16.0
    """A frame whose 99th luminance percentile is below this is black (0-255)."""
    saturated_min_level: float = 240.0
    """A frame whose 1st luminance percentile is above this is saturated (0-255)."""
    textureless_max_std: float = 3.0
    """A frame whose luminance standard deviation is below this is textureless (0-255; sensor
    noise alone is ~1-2, real scenes measured 12-60 on the synthetic and real datasets)."""
    sample_px: int = 160
    """The check reads about this many pixels along the longer side (a strided subsample)."""
    frozen_after_s: float = 2.0
    """A camera whose frames have not changed bit for bit (on that subsample) over this many
    seconds of the stream while another camera's did is *frozen*: a stuck camera, or a
    stream or decoder repeating its last frame (:class:`FrozenCameras`); 0 = no check.
    Sensor noise changes a working camera's every frame."""

    def __post_init__(self) -> None:
        if not 0 <= self.black_max_level < self.saturated_min_level <= 255:
            raise ValueError(
                "FrameCheckConfig: need 0 <= black_max_level < saturated_min_level <= 255, got "
                f"{self.black_max_level}, {self.saturated_min_level}"
            )
        if self.textureless_max_std < 0:
            raise ValueError(
                f"FrameCheckConfig.textureless_max_std must be >= 0, got {self.textureless_max_std}"
            )
        if self.sample_px < 8:
            raise ValueError(f"FrameCheckConfig.sample_px must be >= 8, got {self.sample_px}")
        if not self.frozen_after_s >= 0:
            raise ValueError(
                f"FrameCheckConfig.frozen_after_s must be >= 0, got {self.frozen_after_s}"
            )


def local_contrast(
    image: NDArray[np.floating] | NDArray[np.uint8], size: int
) -> NDArray[np.float32]:
    """Grey-level standard deviation in a ``size`` x ``size`` box around each pixel (the
    photo check's texture, the online estimate's textured pixels)."""
    im = np.asarray(image, np.float32)
    # (The channels' mean as NumPy's mean over the last axis computes it, without its
    # strided reduction: 3.4 -> 0.2 ms at 480x270.)
    grey = ((im[..., 0] + im[..., 1]) + im[..., 2]) / np.float32(3) if im.ndim == 3 else im
    m1 = cv2.blur(grey, (size, size))
    m2 = cv2.blur(grey * grey, (size, size))
    return np.sqrt(np.maximum(m2 - m1 * m1, 0.0)).astype(np.float32)


def _sample(image: Image, config: FrameCheckConfig) -> Image:
    """The strided subsample the checks read (about ``sample_px`` along the longer side)."""
    h, w = image.shape[:2]
    stride = max(1, max(h, w) // config.sample_px)
    return image[::stride, ::stride]


def frame_defect(image: Image, config: FrameCheckConfig | None = None) -> str | None:
    """``"black"``, ``"saturated"``, ``"textureless"`` or None (usable) for one BGR frame."""
    config = config or FrameCheckConfig()
    sample = _sample(image, config)
    gray = cv2.cvtColor(sample, cv2.COLOR_BGR2GRAY) if sample.ndim == 3 else sample
    p1, p99 = np.percentile(gray, (1, 99))
    if p99 < config.black_max_level:
        return "black"
    if p1 > config.saturated_min_level:
        return "saturated"
    if float(gray.std()) < config.textureless_max_std:
        return "textureless"
    return None


def frame_defects(
    frames: FrameSet, config: FrameCheckConfig | None = None
) -> tuple[str | None, ...]:
    """Per camera of ``frames``: its defect, or None (usable, or no frame)."""
    return tuple(None if im is None else frame_defect(im, config) for im in frames.images)


def without_defective(frames: FrameSet, defects: Sequence[str | None]) -> FrameSet:
    """``frames`` with the defective cameras' images dropped (as a camera without a frame)."""
    if not any(defects):
        return frames
    images = tuple(None if d else im for im, d in zip(frames.images, defects, strict=True))
    return dataclasses.replace(frames, images=images)


class FrozenCameras:
    """Which cameras' frames stopped changing while the others' went on.

    A camera that hangs, or a stream or decoder that repeats its last frame, keeps delivering
    an image: nothing else finds it, and the tasks reconstruct that camera's silhouette and
    colours of the moment it froze. :meth:`update`, called with each task's frames (in time
    order), compares a hash of each camera's check subsample with its previous one: a camera
    whose frame has been the same bit for bit over ``frozen_after_s`` seconds of the stream
    while another camera's changed in that time is frozen, until its frame changes. A scene
    where nothing changes in any camera (noise-free frames of a still scene, a paused
    stream) freezes nobody; a camera without a frame in an update (stalled, unusable) keeps
    its state. About 10 microseconds per camera.

    The tasks keep a frozen camera: on a 4-camera rig 90 degrees apart its stale view still
    helps the hull and the depths more than three cameras alone (hd4 at 1080p, one camera
    frozen for the last 2 s of 3.6, the tasks after it froze: foreground F at 0.5 % 0.357 ->
    0.276 with it kept, 0.143 with it left out; docs/BENCHMARKS.md).
    """

    def __init__(self, config: FrameCheckConfig | None = None, *, fps: float) -> None:
        self.config = config or FrameCheckConfig()
        self.fps = fps
        """The stream's rate: a frame set without a timestamp is at ``time_index / fps``."""
        self._hash: dict[int, bytes] = {}
        self._since: dict[int, float] = {}
        """Per camera: the stream time its current frame was first seen ..."""
        self._since_index: dict[int, int] = {}
        """... and that frame's time index."""
        self._frozen: set[int] = set()

    @property
    def frozen(self) -> frozenset[int]:
        """Indices of the cameras frozen as of the last update."""
        return frozenset(self._frozen)

    def since(self, camera: int) -> int | None:
        """The time index of the first update that gave ``camera``'s current frame (None:
        none seen yet)."""
        return self._since_index.get(camera)

    def update(self, frames: FrameSet) -> tuple[list[int], list[int]]:
        """Take the next frames; return the cameras that froze and those whose frames
        changed again since the last update (indices, ascending)."""
        if self.config.frozen_after_s <= 0:
            return [], []
        seconds = frames.timestamp_s
        if seconds is None:
            seconds = frames.time_index / self.fps
        absent = set()
        for i, image in enumerate(frames.images):
            if image is None:  # no frame (stalled, unusable): not judged this time
                absent.add(i)
                continue
            sample = np.ascontiguousarray(_sample(image, self.config))
            digest = hashlib.blake2b(sample.data, digest_size=16).digest()
            if self._hash.get(i) != digest:
                self._hash[i] = digest
                self._since[i] = seconds
                self._since_index[i] = frames.time_index
        now_frozen = {
            i
            for i, since in self._since.items()
            if i not in absent
            and seconds - since >= self.config.frozen_after_s
            and any(other > since for j, other in self._since.items() if j != i)
        } | (self._frozen & absent)
        froze = sorted(now_frozen - self._frozen)
        thawed = sorted(self._frozen - now_frozen)
        self._frozen = now_frozen
        return froze, thawed
