"""Per-camera background model: robust per-pixel Gaussian with shadow and gain handling.

Why not OpenCV's MOG2/KNN: their update cannot be switched off per pixel, so an actor who
stands still is absorbed into the background after ``history`` frames, and their state is not
serialisable. This model (in the spirit of Horprasert et al.'s brightness/chromaticity
distortion model) keeps, per pixel of a working-resolution image:

* a background colour ``mean`` and a noise variance per channel, learned robustly (median and
  MAD) from a background-only clip or from the first frames of the stream (where the person
  model's masks are given, over the frames that show each pixel free of people);
* a per-frame global gain per channel (robust median ratio over background pixels), so that a
  global illumination change or an exposure drift is not flagged;
* a shadow test: a pixel darker than the background by a bounded factor with the same
  chromaticity is a shadow, not foreground;
* a selective update: only pixels classified as background (away from the foreground by a
  guard band) learn; a pixel that stays foreground for ``absorb_after_frames`` updates is
  absorbed slowly (a moved piece of furniture), long after an actor standing still for a few
  seconds would have been — a stopped actor stays foreground (the *hold*);
* ghost repair: when something that was part of the learned background leaves (a person who
  was present while the model was bootstrapped from the stream), the background it uncovers
  differs from the model and shows up as a foreground blob — a *ghost*. A real object has an
  image edge along its outline (object against background); a ghost has the edge in the
  *model* (the departed object's outline) and none in the frame. Blobs whose outline is much
  stronger in the model than in the frame are learned at once.

Segmentation and update are separate: ``segment`` classifies a frame and never changes the
model, ``update`` learns from one frame (reusing a segmentation of it). Everything works at a
*working resolution* of at most ``working_pixels`` pixels (masks are returned there: consumers
map them onto their views, see ``edgerecon.views.mask_scale``), so the cost per frame does not
grow with the sensor's megapixels.

The state is a few NumPy arrays (``BackgroundState``): it pickles and travels between nodes.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.scene.masks import MaskConfig, clean_mask, disk
from edgerecon.types import DataError, Image, Mask

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class BackgroundConfig:
    """Parameters of the per-camera background model."""

    working_pixels: int = 130_000
    """Frames with more pixels than this are downscaled (aspect kept) to about this many
    pixels for modelling (480x270 for 16:9); masks are produced at that working resolution."""
    threshold_sigma: float = 4.0
    """A pixel is foreground when its colour differs from the gain-compensated background by
    more than this many noise standard deviations (Mahalanobis norm over the 3 channels)."""
    min_noise_std: float = 3.0
    """Floor of the per-channel noise standard deviation (grey levels): covers compression
    noise that a short learning clip underestimates."""
    max_noise_ratio: float = 2.0
    """The per-pixel noise learned from a clip is capped at this multiple of the camera's
    median noise (per channel): without an empty clip, the pixels actors crossed during the
    learning frames would otherwise become insensitive (hd4 at 640x360, t = 100: the recall
    of an actor who stopped where they had walked rose from 0.45 / 0.26 to 0.77 / 0.91 in the
    two cameras that saw them cross); 0 = no cap."""
    jitter_px: float = 1.0
    """Expected misregistration between the model and a frame (pixels at the working
    resolution: camera vibration, video compression): the noise of pixels on strong image
    edges is raised by ``jitter_px`` times the local gradient so that edges are not flagged."""
    min_abs_diff: float = 12.0
    """A pixel is only foreground when its colour also differs by at least this much (grey
    levels, Euclidean over BGR) from the compensated background."""
    texture_window_px: int = 7
    """Side of the window (working pixels, odd) of the texture cue: where the background is
    textured, a window whose normalised cross-correlation with the background falls below
    ``texture_max_ncc`` is foreground even when its colour is close (grey trousers on a grey
    stone floor); shadows and illumination changes keep the texture. 0 = colour only."""
    texture_min_std: float = 8.0
    """The texture cue applies where the background's grey-level standard deviation in the
    window exceeds this (grey levels): flat backgrounds have no texture to compare."""
    texture_max_ncc: float = 0.4
    """Windows correlating less than this with the background are foreground."""
    shadow_min_brightness: float = 0.45
    """Shadows darken the background by at most this factor (brightness ratio >= it)."""
    shadow_max_brightness: float = 1.5
    """Brightness ratios up to this are tested for shadows/highlights (1 = shadows only)."""
    shadow_max_chroma: float = 0.1
    """Largest chromaticity distortion of a shadow, relative to its brightness."""
    learning_rate: float = 0.05
    """Rate at which background pixels learn the frame of each update (0 = frozen model);
    the stream schedule updates every ``ForegroundConfig.update_interval_s`` (10 s time
    constant at the defaults)."""
    update_guard_px: int = 4
    """Foreground is dilated by this many working pixels before the selective update, so that
    blurred silhouette edges are not learned into the background."""
    absorb_after_frames: int = 120
    """A pixel that is foreground in this many consecutive updates starts to be learned
    (a static change of the scene); 0 = never absorb. 120 updates = 60 s at the default
    update interval."""
    ghost_edge_ratio: float = 2.0
    """A foreground blob is a ghost (uncovered background, see the module docstring) when the
    model's mean gradient along its outline exceeds the frame's by this factor; 0 = no ghost
    repair."""
    ghost_min_edge: float = 10.0
    """... and the model's mean gradient along the outline (strongest within a pixel) is at
    least this (grey levels per pixel): a blob on a flat background has no outline to judge."""
    ghost_min_outline_px: int = 12
    """Blobs with a shorter outline (working pixels) are never judged ghosts."""
    ghost_min_matches: int = 2
    """A foreground pixel whose colour matches (within ``threshold_sigma``) at least this many
    of the frames the model was learned from is background seen then, uncovered now: a ghost
    pixel, learned at once (it catches ghosts fused to an actor, which the outline test cannot
    judge); 0 = off."""
    max_learning_frames: int = 60
    """At most this many frames (evenly spaced) of a learning clip enter the median."""
    min_free_frames: int = 3
    """Learning from the stream with the person model's masks (``BackgroundModel.learn``'s
    ``people``): a pixel's colour is the median of the frames that show it free of people
    where at least this many do, else of all of them. Fewer trust the network's misses: where
    people cover a pixel in every learning frame, a person the network misses in the last
    two is learned as the background there (hd4, 8 frames: 2 lost more of an arriving
    actor than they gained)."""
    people_margin_px: int = 0
    """The person model's masks grown (> 0) or shrunk (< 0) by this (working pixels) before
    they leave frames out of a pixel's median (hd4 / hd4p masks: 0 better than 3 or -3)."""
    min_gain: float = 0.4
    """Smallest per-channel global gain accepted (an estimate below it is clamped)."""
    max_gain: float = 2.5
    """Largest per-channel global gain accepted."""
    mask: MaskConfig = field(default_factory=MaskConfig)
    """Cleaning of the raw detections, in working-resolution pixels."""

    def __post_init__(self) -> None:
        if self.working_pixels < 1024:
            raise ValueError(
                f"BackgroundConfig.working_pixels must be >= 1024, got {self.working_pixels}"
            )
        if self.min_free_frames < 1:
            raise ValueError(
                f"BackgroundConfig.min_free_frames must be >= 1, got {self.min_free_frames}"
            )
        for name in ("ghost_edge_ratio", "ghost_min_edge", "ghost_min_outline_px"):
            if getattr(self, name) < 0:
                raise ValueError(f"BackgroundConfig.{name} must be >= 0, got {getattr(self, name)}")
        for name in ("threshold_sigma", "min_noise_std", "shadow_max_chroma", "max_gain"):
            if not getattr(self, name) > 0:
                raise ValueError(f"BackgroundConfig.{name} must be > 0, got {getattr(self, name)}")
        if self.texture_window_px < 0 or (
            self.texture_window_px > 0 and self.texture_window_px % 2 == 0
        ):
            raise ValueError(
                "BackgroundConfig.texture_window_px must be 0 or an odd number of pixels, got "
                f"{self.texture_window_px}"
            )
        if not -1.0 <= self.texture_max_ncc <= 1.0:
            raise ValueError(
                f"BackgroundConfig.texture_max_ncc must be in [-1, 1], got {self.texture_max_ncc}"
            )
        if self.jitter_px < 0:
            raise ValueError(f"BackgroundConfig.jitter_px must be >= 0, got {self.jitter_px}")
        if self.min_abs_diff < 0:
            raise ValueError(f"BackgroundConfig.min_abs_diff must be >= 0, got {self.min_abs_diff}")
        if not 0.0 < self.shadow_min_brightness <= 1.0:
            raise ValueError(
                "BackgroundConfig.shadow_min_brightness must be in (0, 1], got "
                f"{self.shadow_min_brightness}"
            )
        if self.shadow_max_brightness < self.shadow_min_brightness:
            raise ValueError(
                "BackgroundConfig.shadow_max_brightness must be >= shadow_min_brightness, got "
                f"{self.shadow_max_brightness}"
            )
        if not 0.0 <= self.learning_rate <= 1.0:
            raise ValueError(
                f"BackgroundConfig.learning_rate must be in [0, 1], got {self.learning_rate}"
            )
        for name in ("update_guard_px", "absorb_after_frames"):
            if getattr(self, name) < 0:
                raise ValueError(f"BackgroundConfig.{name} must be >= 0, got {getattr(self, name)}")
        if self.max_learning_frames < 1:
            raise ValueError(
                f"BackgroundConfig.max_learning_frames must be >= 1, got {self.max_learning_frames}"
            )
        if not 0.0 < self.min_gain <= 1.0 <= self.max_gain:
            raise ValueError(
                f"BackgroundConfig gains must satisfy 0 < min_gain <= 1 <= max_gain, got "
                f"{self.min_gain}, {self.max_gain}"
            )


@dataclass(frozen=True, kw_only=True, eq=False)
class BackgroundState:
    """The serialisable state of one camera's background model (working resolution)."""

    camera: str
    """Camera name (for messages)."""
    frame_size: tuple[int, int]
    """(width, height) of the camera's frames."""
    mean: NDArray[np.float32]
    """(h, w, 3) background colour, BGR, at the working resolution."""
    var: NDArray[np.float32]
    """(h, w, 3) per-channel noise variance (grey levels squared)."""
    fg_age: NDArray[np.uint16]
    """(h, w) consecutive frames each pixel has been foreground."""
    last_foreground: NDArray[np.bool_]
    """(h, w) cleaned foreground of the last frame (excluded from the gain estimate)."""
    num_frames: int = 0
    """Frames segmented since the model was learned."""
    version: int = 0
    """Incremented each time the model is (re)learned from a clip."""
    last_image: NDArray[np.uint8] | None = None
    """(h, w, 3) the last update's frame at the model's exposure (working resolution): what
    stayed the same since then is still (None before the first update)."""
    seen: NDArray[np.uint8] | None = None
    """(n, h, w, 3) the frames the model was learned from (working resolution; read only):
    what each pixel looked like then, for the ghost test (None: fewer than 3 frames)."""
    unsettled: NDArray[np.bool_] | None = None
    """(h, w) pixels whose learning frames disagree (``BackgroundModel.unsettled``; read
    only), computed when the model learns."""
    seen_people: NDArray[np.bool_] | None = None
    """(n, h, w) where the person model saw a person in each of ``seen`` (read only; None:
    no person known): those frames never count as the background seen there."""


@dataclass(frozen=True, kw_only=True, eq=False)
class Segmentation:
    """Result of segmenting one frame (all at the model's working resolution)."""

    foreground: Mask
    """(h, w) clean foreground mask at the working resolution."""
    raw: Mask
    """(h, w) raw detections at the working resolution (before cleaning)."""
    shadow: Mask
    """(h, w) pixels explained as shadows (not foreground), working resolution."""
    gain: NDArray[np.float64]
    """(3,) per-channel global gain of the frame relative to the model (B, G, R)."""
    image: NDArray[np.float32] | None = field(default=None, repr=False)
    """The frame at the working resolution (float32 BGR), reused by ``update``; dropped
    (``slim``) before a segmentation travels to another node."""

    def slim(self) -> Segmentation:
        """The same segmentation without its working image."""
        return dataclasses.replace(self, image=None)


def _covered(
    people: Sequence[Mask | None], size: tuple[int, int], config: BackgroundConfig
) -> NDArray[np.bool_] | None:
    """(n, h, w) the learning frames' person pixels at the working ``size``, grown
    or shrunk by ``people_margin_px``; None when no frame has any."""
    if not any(m is not None and m.any() for m in people):
        return None
    margin = config.people_margin_px
    grow = disk(abs(margin)) if margin else None
    out = np.zeros((len(people), size[1], size[0]), bool)
    for i, m in enumerate(people):
        if m is None or not m.any():
            continue
        small = cv2.resize(m.view(np.uint8), size, interpolation=cv2.INTER_NEAREST)
        if grow is not None:
            small = cv2.dilate(small, grow) if margin > 0 else cv2.erode(small, grow)
        out[i] = small.view(bool)
    return out


def _free_median(
    stack: NDArray[np.uint8], covered: NDArray[np.bool_], min_free: int
) -> NDArray[np.float32]:
    """Per pixel and channel, the median of ``stack`` (n, h, w, 3) over the frames where
    ``covered`` (n, h, w) is False, where at least ``min_free`` are; elsewhere over all."""
    free = ~covered
    k = free.sum(axis=0)
    vals = stack.astype(np.uint16)
    vals[covered] = 256  # sorted after every colour
    vals.sort(axis=0)
    kk = np.maximum(k, 1)[None, :, :, None]
    lo = np.take_along_axis(vals, (kk - 1) // 2, axis=0)[0].astype(np.float32)
    hi = np.take_along_axis(vals, kk // 2, axis=0)[0].astype(np.float32)
    out = np.asarray(0.5 * (lo + hi), np.float32)
    few = k < min_free
    if few.any():
        out[few] = np.median(stack[:, few], axis=0)
    return out


def _unsettled(
    stack: NDArray[np.uint8], median: NDArray[np.floating[Any]], config: BackgroundConfig
) -> Mask:
    """(h, w) pixels where some learning frame of ``stack`` differs from their median by
    more than twice ``min_abs_diff`` in a channel, dilated by ``update_guard_px``."""
    dev = np.zeros(stack.shape[1:3], np.float32)
    for frame in stack:  # frame by frame: no (n, h, w, 3) float copy
        np.maximum(dev, np.abs(frame.astype(np.float32) - median).max(axis=2), out=dev)
    moved: Any = (dev > 2.0 * config.min_abs_diff).view(np.uint8)
    if config.update_guard_px > 0:
        moved = cv2.dilate(moved, disk(config.update_guard_px))
    return np.asarray(moved, bool)


def working_size(frame_size: tuple[int, int], max_pixels: int) -> tuple[int, int]:
    """(width, height) at which a camera with ``frame_size`` is modelled: the frame itself
    when it has at most ``max_pixels`` pixels, else the frame reduced by an integer factor
    when that keeps >= 70 % of ``max_pixels``, else scaled (aspect kept, rounded as
    ``Camera.scaled``) to about ``max_pixels``."""
    w, h = frame_size
    if w * h <= max_pixels:
        return (w, h)
    s = float(np.sqrt(max_pixels / (w * h)))
    # An exact integer reduction when one is close (1920x1080 -> 480x270): the frames then
    # take OpenCV's fast area-averaging path, and nothing is interpolated.
    k = int(np.ceil(1.0 / s))
    if w % k == 0 and h % k == 0 and (w // k) * (h // k) >= 0.7 * max_pixels:
        return (w // k, h // k)
    return (max(1, round(w * s)), max(1, round(h * s)))


@dataclass(frozen=True, kw_only=True)
class UpdateStats:
    """What one update of a background model did."""

    learned_px: int
    """Working pixels that learned the frame (background, or absorbed)."""
    ghost_px: int
    """Working pixels of ghosts learned at once."""
    ghosts: int
    """Ghost blobs found."""


def downscale(frame: Image, size: tuple[int, int]) -> Image:
    """``frame`` reduced to ``size`` = (width, height): pixel-area averaging, by an integer
    factor first (OpenCV's fast path: a non-integer area resize of a 1080p frame costs ~4x
    more), then bilinear for the remaining factor (< 2)."""
    h, w = frame.shape[:2]
    if (w, h) == size:
        return frame
    k = min(w // size[0], h // size[1])
    while k >= 2 and (w % k or h % k):
        k -= 1
    if k >= 2:
        reduced = np.asarray(
            cv2.resize(frame, (w // k, h // k), interpolation=cv2.INTER_AREA), np.uint8
        )
        if (w // k, h // k) == size:
            return reduced
        return np.asarray(cv2.resize(reduced, size, interpolation=cv2.INTER_LINEAR), np.uint8)
    return np.asarray(cv2.resize(frame, size, interpolation=cv2.INTER_AREA), np.uint8)


def _to_working(frame: Image, size: tuple[int, int]) -> NDArray[np.float32]:
    return downscale(frame, size).astype(np.float32)


#: BGR -> grey weights (ITU-R BT.601) for cv2.transform.
_GREY = np.array([[0.114, 0.587, 0.299]], np.float32)


def _gradient_magnitude(grey: NDArray[np.float32]) -> NDArray[np.float32]:
    """|grad| of a grey image in grey levels per pixel (3x3 Sobel)."""
    gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    return np.asarray(cv2.magnitude(gx, gy), np.float32)


class BackgroundModel:
    """Background model of one camera. Not thread-safe; one instance per camera."""

    def __init__(self, state: BackgroundState, config: BackgroundConfig | None = None) -> None:
        self.config = config or BackgroundConfig()
        self._state = state
        self._stats: (
            tuple[
                NDArray[np.float32], NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]
            ]
            | None
        ) = None

    # ------------------------------------------------------------------ construction
    @classmethod
    def learn(
        cls,
        frames: Iterable[Image],
        config: BackgroundConfig | None = None,
        *,
        camera: str = "",
        version: int = 0,
        people: Sequence[Mask | None] | None = None,
    ) -> BackgroundModel:
        """Learn the model from frames of the empty scene (or the first frames of the stream:
        the per-pixel median ignores actors that move through less than half of them).

        ``people``: per frame, the pixels a person covers (the person model's masks, any
        size; None: none known): a pixel's median is then over the frames that show it free
        of people, where at least ``min_free_frames`` do (an actor who walks along a
        camera's line of sight covers the same pixels in most of the first second's frames,
        and the plain median there is a smear of their colours).

        Raises ``DataError`` when no frame is given or the frames differ in size.
        """
        config = config or BackgroundConfig()
        frames = list(frames)
        if people is not None and len(people) != len(frames):
            raise ValueError(f"{len(people)} person masks for {len(frames)} frames")
        if not frames:
            raise DataError(f"camera {camera!r}: no frames to learn the background from")
        size = (frames[0].shape[1], frames[0].shape[0])
        for f in frames:
            if f.ndim != 3 or f.shape[2] != 3:
                raise DataError(f"camera {camera!r}: background frames must be BGR (H, W, 3)")
            if (f.shape[1], f.shape[0]) != size:
                raise DataError(
                    f"camera {camera!r}: background frames differ in size "
                    f"({f.shape[1]}x{f.shape[0]} vs {size[0]}x{size[1]})"
                )
        if len(frames) > config.max_learning_frames:
            idx = np.linspace(0, len(frames) - 1, config.max_learning_frames).round().astype(int)
            frames = [frames[i] for i in idx]
            people = None if people is None else [people[i] for i in idx]
        wsize = working_size(size, config.working_pixels)
        stack = np.stack([downscale(f, wsize) for f in frames])
        covered = None if people is None else _covered(people, wsize, config)
        if covered is None:
            mean = np.median(stack, axis=0).astype(np.float32)
        else:
            mean = _free_median(stack, covered, config.min_free_frames)
        if len(frames) >= 3:
            if covered is None:
                mad = np.median(np.abs(stack.astype(np.float32) - mean), axis=0)
            else:
                dev = np.abs(stack.astype(np.float32) - mean)
                mad = _free_median(
                    np.minimum(dev, 255.0).astype(np.uint8), covered, config.min_free_frames
                )
            std = (1.4826 * mad).astype(np.float32)
        else:
            std = np.zeros_like(mean)
        np.maximum(std, config.min_noise_std, out=std)
        if config.max_noise_ratio > 0:
            # A pixel an actor crossed in several learning frames gets a large MAD and would
            # never see that actor again when they stop there: cap it (edges keep their own
            # allowance through jitter_px).
            cap = config.max_noise_ratio * np.median(std, axis=(0, 1))
            np.minimum(std, np.maximum(cap, config.min_noise_std).astype(np.float32), out=std)
        var = std * std
        h, w = mean.shape[:2]
        seen = stack if len(frames) >= 3 else None
        unsettled = np.zeros((h, w), bool) if seen is None else _unsettled(stack, mean, config)
        state = BackgroundState(
            camera=camera,
            frame_size=size,
            mean=mean,
            var=var,
            fg_age=np.zeros((h, w), np.uint16),
            last_foreground=np.zeros((h, w), bool),
            num_frames=0,
            version=version,
            seen=seen,
            unsettled=unsettled,
            seen_people=None if seen is None else covered,
        )
        logger.debug(
            "camera %s: background learned from %d frames at %s", camera, len(frames), wsize
        )
        return cls(state, config)

    @classmethod
    def from_state(
        cls, state: BackgroundState, config: BackgroundConfig | None = None
    ) -> BackgroundModel:
        """Re-create a model from its state (e.g. after it crossed to another node)."""
        return cls(
            dataclasses.replace(
                state,
                mean=state.mean.copy(),
                var=state.var.copy(),
                fg_age=state.fg_age.copy(),
                last_foreground=state.last_foreground.copy(),
                last_image=None if state.last_image is None else state.last_image.copy(),
            ),
            config,
        )

    # ------------------------------------------------------------------ state
    @property
    def state(self) -> BackgroundState:
        """A snapshot of the current state (copies: later updates do not change it)."""
        s = self._state
        return dataclasses.replace(
            s,
            mean=s.mean.copy(),
            var=s.var.copy(),
            fg_age=s.fg_age.copy(),
            last_foreground=s.last_foreground.copy(),
            last_image=None if s.last_image is None else s.last_image.copy(),
        )

    @property
    def camera(self) -> str:
        return self._state.camera

    @property
    def frame_size(self) -> tuple[int, int]:
        return self._state.frame_size

    @property
    def working_size(self) -> tuple[int, int]:
        h, w = self._state.mean.shape[:2]
        return (w, h)

    @property
    def num_frames(self) -> int:
        return self._state.num_frames

    @property
    def version(self) -> int:
        return self._state.version

    @property
    def unsettled(self) -> Mask:
        """(h, w) working-resolution pixels whose learning frames disagree (something moved
        through them while the model was learned from the stream): there the model may hold
        part of an actor, whom it then cannot see while they stand still. Dilated by
        ``update_guard_px``; all False for a model learned from fewer than 3 frames or from
        an empty-scene clip (and for a state without the map)."""
        known = getattr(self._state, "unsettled", None)
        if known is None:
            return np.zeros(self._state.mean.shape[:2], bool)
        return np.asarray(known, bool)

    def background_image(self, *, working: bool = False) -> Image:
        """The background colour as a BGR image at the frame (or the working) resolution."""
        img = np.clip(np.rint(self._state.mean), 0, 255).astype(np.uint8)
        if not working and self.working_size != self.frame_size:
            img = np.asarray(
                cv2.resize(img, self.frame_size, interpolation=cv2.INTER_LINEAR), np.uint8
            )
        return img

    # ------------------------------------------------------------------ segmentation
    def _check_frame(self, frame: Image) -> None:
        if frame.ndim != 3 or frame.shape[2] != 3:
            raise DataError(f"camera {self.camera!r}: frames must be BGR (H, W, 3)")
        if (frame.shape[1], frame.shape[0]) not in (self.frame_size, self.working_size):
            raise DataError(
                f"camera {self.camera!r}: frame is {frame.shape[1]}x{frame.shape[0]} but the "
                f"background model was learned at {self.frame_size[0]}x{self.frame_size[1]}"
            )

    def estimate_gain(self, image: NDArray[np.float32]) -> NDArray[np.float64]:
        """(3,) per-channel gain of a working-resolution image relative to the background:
        the median ratio over well-exposed pixels that were background in the last frame."""
        s = self._state
        step = 4
        img = image[::step, ::step].reshape(-1, 3)
        mean = s.mean[::step, ::step].reshape(-1, 3)
        ok = ~s.last_foreground[::step, ::step].reshape(-1)
        ok &= np.all((mean > 20) & (mean < 235) & (img < 250), axis=1)
        if np.count_nonzero(ok) < 100:
            return np.ones(3)
        ratio = img[ok] / mean[ok]
        gain = np.median(ratio, axis=0).astype(np.float64)
        return np.clip(gain, self.config.min_gain, self.config.max_gain)

    def _background_stats(
        self,
    ) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
        """From the current background: the per-channel noise variance with the edge-jitter
        term, the grey background, its window mean and its window standard deviation.

        Derived from the state alone (so a model re-created from its state behaves exactly
        like the original) and kept until the next update: segmenting never changes it."""
        if self._stats is None:
            self._stats = self._compute_background_stats()
        return self._stats

    def _compute_background_stats(
        self,
    ) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.float32], NDArray[np.float32]]:
        cfg = self.config
        s = self._state
        grey = np.asarray(cv2.transform(s.mean, _GREY), np.float32)
        noise = s.var
        if cfg.jitter_px > 0:
            gx = np.asarray(cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3, scale=0.125), np.float32)
            gy = np.asarray(cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3, scale=0.125), np.float32)
            edge = np.float32(cfg.jitter_px**2) * (gx * gx + gy * gy)
            noise = s.var + edge[..., None]
        if cfg.texture_window_px <= 0:
            return noise, grey, grey, np.zeros_like(grey)
        k = (cfg.texture_window_px,) * 2
        mean = np.asarray(cv2.boxFilter(grey, -1, k), np.float32)
        var = np.asarray(cv2.boxFilter(grey * grey, -1, k), np.float32) - mean * mean
        std = np.sqrt(np.maximum(var, 0)).astype(np.float32)
        return noise, grey, mean, std

    def _texture_changed(
        self,
        image: NDArray[np.float32],
        grey_b: NDArray[np.float32],
        mean_b: NDArray[np.float32],
        std_b: NDArray[np.float32],
    ) -> Mask:
        """Pixels whose window has lost the background's texture (low normalised
        cross-correlation where the background is textured)."""
        cfg = self.config
        k = (cfg.texture_window_px,) * 2
        grey = np.asarray(cv2.transform(image, _GREY), np.float32)
        # Undo local brightness changes first (an edge-preserving median of the frame /
        # background ratio): a window across a shadow's edge then still matches.
        ratio = grey / np.maximum(grey_b, np.float32(1.0))
        ratio = np.asarray(cv2.medianBlur(np.clip(ratio, 0.05, 4.0), 5), np.float32)
        grey = np.asarray(grey / ratio, np.float32)
        mean = np.asarray(cv2.boxFilter(grey, -1, k), np.float32)
        var = np.asarray(cv2.boxFilter(grey * grey, -1, k), np.float32) - mean * mean
        cov = np.asarray(cv2.boxFilter(grey * grey_b, -1, k), np.float32) - mean * mean_b
        # Noise floor on the frame's deviation: a flat patch over texture correlates ~0.
        std = np.sqrt(np.maximum(var, np.float32(cfg.min_noise_std**2)))
        ncc = cov / (std * np.maximum(std_b, np.float32(1e-3)))
        return (std_b > np.float32(cfg.texture_min_std)) & (ncc < np.float32(cfg.texture_max_ncc))

    def classify(self, image: NDArray[np.float32]) -> tuple[Mask, Mask, NDArray[np.float64]]:
        """Raw foreground and shadow masks of a working-resolution float32 BGR image, and the
        frame's gain."""
        cfg = self.config
        s = self._state
        gain = self.estimate_gain(image)
        g = gain.astype(np.float32)
        ones = np.ones((1, 3), np.float32)
        noise, grey_b, mean_b, std_b = self._background_stats()
        diff = image - s.mean * g
        d2 = diff * diff
        abs2 = cv2.transform(d2, ones)
        # Mahalanobis distance with the variance scaled by the gain (noise scales with it).
        maha2 = cv2.transform(d2 / noise, (1.0 / (g * g)).reshape(1, 3))
        # The absolute floor is in the background's units, so it scales with the exposure
        # too: at 45 % light an actor's contrast with the floor is 45 % of what it was.
        floor = cfg.min_abs_diff * float(np.mean(g))
        changed = (maha2 > np.float32(cfg.threshold_sigma**2)) & (abs2 > np.float32(floor**2))
        # Brightness distortion alpha (I ~ alpha * mu, mu the compensated background) and
        # chromaticity distortion |I - alpha mu| / (alpha |mu|): a shadow is a darker copy of
        # the background colour. |I - alpha mu|^2 = |I|^2 - (I.mu)^2 / |mu|^2.
        mm = cv2.transform(s.mean * s.mean, (g * g).reshape(1, 3)) + np.float32(1e-3)
        im = cv2.transform(image * s.mean, g.reshape(1, 3))
        ii = cv2.transform(image * image, ones)
        alpha = im / mm
        resid2 = np.maximum(ii - im * alpha, 0)
        chroma2 = resid2 / (mm * np.maximum(alpha * alpha, np.float32(1e-6)))
        shadow = (
            changed
            & (alpha >= np.float32(cfg.shadow_min_brightness))
            & (alpha <= np.float32(cfg.shadow_max_brightness))
            & (chroma2 <= np.float32(cfg.shadow_max_chroma**2))
        )
        if cfg.texture_window_px > 0:
            # A shadow keeps the texture; a camouflaged object does not. The pixel itself must
            # differ a little too (half the threshold), or windows straddling an object's
            # outline would grow it by half a window.
            texture = self._texture_changed(image, grey_b, mean_b, std_b) & (
                maha2 > np.float32((0.5 * cfg.threshold_sigma) ** 2)
            )
            shadow &= ~texture
            changed |= texture
        return changed & ~shadow, shadow, gain

    def working_image(self, frame: Image) -> NDArray[np.float32]:
        """``frame`` (full resolution, or already reduced to the working size: e.g. by
        ``downscale`` before it travelled to another node) as the float32 working image."""
        self._check_frame(frame)
        return _to_working(frame, self.working_size)

    def segment(self, frame: Image, *, image: NDArray[np.float32] | None = None) -> Segmentation:
        """Foreground of a full-resolution BGR frame, at the working resolution. Never changes
        the model (see ``update``). ``image``: the frame's ``working_image`` when the caller
        has it already.

        Raises ``DataError`` when the frame's size differs from the model's.
        """
        if image is None:
            image = self.working_image(frame)
        raw, shadow, gain = self.classify(image)
        clean = clean_mask(raw, self.config.mask)
        return Segmentation(foreground=clean, raw=raw, shadow=shadow, gain=gain, image=image)

    def update(
        self,
        frame: Image,
        segmentation: Segmentation | None = None,
        *,
        image: NDArray[np.float32] | None = None,
    ) -> UpdateStats:
        """Learn from one frame: ghost repair, then the selective update. ``segmentation``:
        this frame's ``segment`` result when the caller has it (it is not computed twice)."""
        if image is None:
            image = (
                segmentation.image
                if segmentation is not None and segmentation.image is not None
                else self.working_image(frame)
            )
        seg = segmentation if segmentation is not None else self.segment(frame, image=image)
        foreground = seg.foreground
        ghost = np.zeros_like(foreground)
        num_ghosts = 0
        target = np.asarray(image / seg.gain.astype(np.float32), np.float32)
        if self.config.ghost_edge_ratio > 0 and foreground.any():
            ghost, num_ghosts = self._ghosts(image, foreground, seg.gain)
        if self.config.ghost_min_matches > 0 and self._state.seen is not None:
            # Only pixels foreground at the last update too, and still since then: a ghost is
            # uncovered background, it does not move; an actor walking over a place whose
            # learning frames showed look-alike colours (another actor crossing) does.
            steady = foreground & ~ghost & (self._state.fg_age > 0) & self._still(target)
            seen_before = self._seen_before(target, steady)
            if seen_before.any():
                ghost = ghost | seen_before
                num_ghosts += 1
        if ghost.any():
            self._state.mean[ghost] = target[ghost]
            foreground = foreground & ~ghost
        learned = self._update(image, foreground, seg.gain)
        self._state = dataclasses.replace(
            self._state, last_image=np.clip(np.rint(target), 0, 255).astype(np.uint8)
        )
        self._stats = None  # the background changed
        return UpdateStats(
            learned_px=learned, ghost_px=int(np.count_nonzero(ghost)), ghosts=num_ghosts
        )

    def apply(self, frame: Image, *, update: bool = True) -> Mask:
        """The clean working-resolution foreground of ``frame``; the model then learns from
        the frame unless ``update=False`` (segment + update in one call)."""
        image = self.working_image(frame)
        seg = self.segment(frame, image=image)
        if update:
            self.update(frame, seg, image=image)
        return seg.foreground

    def _still(self, target: NDArray[np.float32]) -> Mask:
        """Pixels whose colour (at the model's exposure) did not change since the last
        update (within ``threshold_sigma`` of the noise, or ``min_abs_diff``)."""
        s = self._state
        if s.last_image is None:
            return np.zeros(target.shape[:2], bool)
        d = target - s.last_image.astype(np.float32)
        d2 = d * d
        return np.asarray(
            (
                cv2.transform(d2 / s.var, np.ones((1, 3), np.float32))
                <= self.config.threshold_sigma**2
            )
            | (cv2.transform(d2, np.ones((1, 3), np.float32)) <= self.config.min_abs_diff**2),
            bool,
        )

    def _seen_before(self, target: NDArray[np.float32], foreground: Mask) -> Mask:
        """Foreground pixels whose colour (at the model's exposure) matches at least
        ``ghost_min_matches`` of the learning frames (see ``ghost_min_matches``)."""
        cfg = self.config
        s = self._state
        assert s.seen is not None
        ys, xs = np.nonzero(foreground)
        if not len(ys):
            return np.zeros_like(foreground)
        cand = target[ys, xs]  # (m, 3)
        diff = s.seen[:, ys, xs].astype(np.float32) - cand  # (n, m, 3)
        d2 = diff * diff
        maha2 = (d2 / s.var[ys, xs]).sum(axis=2)
        close = (maha2 <= np.float32(cfg.threshold_sigma**2)) | (
            d2.sum(axis=2) <= np.float32(cfg.min_abs_diff**2)
        )
        if s.seen_people is not None:
            # A frame that showed a person here showed no background: a person back where
            # they stood while the model learned is no ghost.
            close &= ~s.seen_people[:, ys, xs]
        hit = np.zeros_like(foreground)
        hit[ys, xs] = np.count_nonzero(close, axis=0) >= cfg.ghost_min_matches
        # Isolated matches inside an actor are chance: only regions count.
        return np.asarray(
            cv2.morphologyEx(hit.view(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)), bool
        )

    def _ghosts(
        self, image: NDArray[np.float32], foreground: Mask, gain: NDArray[np.float64]
    ) -> tuple[Mask, int]:
        """Foreground blobs that are uncovered background (see the module docstring)."""
        cfg = self.config
        # Grey of the frame at the model's exposure: channel c divided by its gain.
        grey_f = np.asarray(
            cv2.transform(image, _GREY / gain.astype(np.float32)[None, :]), np.float32
        )
        grey_b = np.asarray(cv2.transform(self._state.mean, _GREY), np.float32)
        n, cc = cv2.connectedComponents(foreground.view(np.uint8), connectivity=8)
        u8 = foreground.view(np.uint8)
        outline = foreground & ~cv2.erode(u8, np.ones((3, 3), np.uint8)).astype(bool)
        ys, xs = np.nonzero(outline)
        owner = cc[ys, xs]
        # The strongest gradient within a pixel of the outline: the blob's outline lies within
        # a pixel of the edge that made it, on either side.
        k3 = np.ones((3, 3), np.uint8)
        grad_f = cv2.dilate(_gradient_magnitude(grey_f), k3)[ys, xs]
        grad_b = cv2.dilate(_gradient_magnitude(grey_b), k3)[ys, xs]
        count = np.bincount(owner, minlength=n).astype(np.float64)
        mean_f = np.bincount(owner, grad_f, minlength=n) / np.maximum(count, 1)
        mean_b = np.bincount(owner, grad_b, minlength=n) / np.maximum(count, 1)
        is_ghost = (
            (count >= cfg.ghost_min_outline_px)
            & (mean_b >= cfg.ghost_min_edge)
            & (mean_b > cfg.ghost_edge_ratio * mean_f)
        )
        is_ghost[0] = False
        if not is_ghost.any():
            return np.zeros_like(foreground), 0
        return is_ghost[cc], int(np.count_nonzero(is_ghost))

    def _update(
        self, image: NDArray[np.float32], foreground: Mask, gain: NDArray[np.float64]
    ) -> int:
        cfg = self.config
        s = self._state
        age = s.fg_age
        np.add(age, 1, out=age, where=foreground & (age < np.iinfo(np.uint16).max))
        age[~foreground] = 0
        guard = foreground
        if cfg.update_guard_px > 0 and foreground.any():
            guard = cv2.dilate(foreground.view(np.uint8), disk(cfg.update_guard_px)).astype(bool)
        learn = ~guard
        if cfg.absorb_after_frames > 0:
            learn |= age >= cfg.absorb_after_frames
        if cfg.learning_rate > 0 and learn.any():
            # Learn the frame at the model's reference exposure (divide by the frame's gain).
            target = np.asarray(image / gain.astype(np.float32), np.float32)
            m8 = learn.view(np.uint8)
            diff = np.asarray(target - s.mean, np.float32)
            cv2.accumulateWeighted(diff * diff, s.var, cfg.learning_rate, mask=m8)
            np.maximum(s.var, np.float32(cfg.min_noise_std**2), out=s.var)
            cv2.accumulateWeighted(target, s.mean, cfg.learning_rate, mask=m8)
        s.last_foreground[...] = foreground
        object.__setattr__(s, "num_frames", s.num_frames + 1)
        return int(np.count_nonzero(learn)) if cfg.learning_rate > 0 else 0


def learn_backgrounds(
    clips: Iterable[Iterable[Image]],
    config: BackgroundConfig | None = None,
    *,
    camera_names: Iterable[str] | None = None,
) -> list[BackgroundModel]:
    """One background model per camera from per-camera background clips."""
    names = list(camera_names) if camera_names is not None else None
    models = []
    for i, clip in enumerate(clips):
        name = names[i] if names is not None else f"cam{i}"
        models.append(BackgroundModel.learn(clip, config, camera=name))
    return models
