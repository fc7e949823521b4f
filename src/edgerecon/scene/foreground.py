"""Foreground of a whole rig per timestamp: background models, masks, hull, objects.

``RigForeground`` holds one ``BackgroundModel`` per rig camera (the only state of the scene
stage) and turns each ``FrameSet`` into a ``ForegroundResult``:

1. per camera, the background model's clean foreground mask (the model learns from the frame);
2. optionally, the visual hull of all masks, and masks made consistent with it (foreground
   that no 3D object explains, such as a change only one camera sees, is dropped);
3. per camera, the objects (k-means with automatic k) of the final mask.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry.camera import Camera, Rig
from edgerecon.progress import track
from edgerecon.scene.background import BackgroundConfig, BackgroundModel, BackgroundState
from edgerecon.scene.hull import HullConfig, VisualHull, hull_consistent_masks, visual_hull
from edgerecon.scene.objects import ObjectConfig, ObjectSegmentation, find_objects
from edgerecon.types import DataError, DepthMap, FrameSet, Image, Mask, StageTimings
from edgerecon.views import resize_mask

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class ForegroundConfig:
    """Parameters of the per-timestamp foreground stage."""

    background: BackgroundConfig = field(default_factory=BackgroundConfig)
    """Per-camera background model."""
    objects: ObjectConfig = field(default_factory=ObjectConfig)
    """Object clustering in each image."""
    hull: HullConfig = field(default_factory=lambda: HullConfig(max_missing=0))
    """Visual hull used for the cross-camera consistency of the masks."""
    hull_max_width: int = 960
    """The hull is carved from masks downscaled to at most this width (pixels)."""
    hull_consistency: bool = True
    """Remove the foreground that the visual hull of all masks does not explain: a detection
    that the other cameras seeing the same space contradict, or that fewer than
    ``hull.min_views`` cameras see (it could not be reconstructed anyway)."""

    def __post_init__(self) -> None:
        if self.hull_max_width < 16:
            raise ValueError(
                f"ForegroundConfig.hull_max_width must be >= 16, got {self.hull_max_width}"
            )
        for name, cls in (
            ("background", BackgroundConfig),
            ("objects", ObjectConfig),
            ("hull", HullConfig),
        ):
            if not isinstance(getattr(self, name), cls):
                raise ValueError(f"ForegroundConfig.{name} must be a {cls.__name__}")


@dataclass(frozen=True, kw_only=True, eq=False)
class ForegroundResult:
    """Foreground of one timestamp, per rig camera (None for a camera without a frame)."""

    time_index: int
    """The frame set's time index."""
    masks: tuple[Mask | None, ...]
    """(H, W) final foreground per camera, full resolution."""
    model_masks: tuple[Mask | None, ...]
    """(H, W) background-model masks before the hull consistency step."""
    objects: tuple[ObjectSegmentation | None, ...]
    """Objects per camera (labels image, per-object boxes and ROIs)."""
    hull: VisualHull | None
    """Visual hull of the model masks (None when it was not computed)."""
    timings: StageTimings
    """Seconds per step."""

    def label_images(self) -> list[NDArray[np.int32] | None]:
        """Per camera, the object-id image (0 = background), e.g. for ``split_sparse``."""
        return [None if o is None else o.labels for o in self.objects]

    def areas(self) -> list[float | None]:
        """Per camera, the share of the image that is foreground."""
        return [None if m is None else float(np.count_nonzero(m)) / m.size for m in self.masks]

    def num_objects(self) -> list[int | None]:
        return [None if o is None else o.num_objects for o in self.objects]


class RigForeground:
    """Background models of all cameras of a rig, and the per-timestamp foreground stage."""

    def __init__(
        self, rig: Rig, models: Sequence[BackgroundModel], config: ForegroundConfig | None = None
    ) -> None:
        if len(models) != len(rig):
            raise DataError(f"{len(models)} background models for a rig of {len(rig)} cameras")
        for cam, model in zip(rig, models, strict=True):
            if model.frame_size != cam.size:
                raise DataError(
                    f"camera {cam.name!r}: background model is {model.frame_size[0]}x"
                    f"{model.frame_size[1]} but the camera is {cam.width}x{cam.height}"
                )
        self.rig = rig
        self.config = config or ForegroundConfig()
        self.models = list(models)
        self.occluders: list[DepthMap | None] | None = None

    @classmethod
    def learn(
        cls,
        rig: Rig,
        clips: Sequence[Iterable[Image]],
        config: ForegroundConfig | None = None,
    ) -> RigForeground:
        """Learn every camera's model from its background-only clip (or first frames)."""
        config = config or ForegroundConfig()
        if len(clips) != len(rig):
            raise DataError(f"{len(clips)} background clips for a rig of {len(rig)} cameras")
        models = [
            BackgroundModel.learn(clip, config.background, camera=cam.name)
            for cam, clip in zip(rig, clips, strict=True)
        ]
        return cls(rig, models, config)

    @classmethod
    def learn_from_framesets(
        cls, rig: Rig, framesets: Iterable[FrameSet], config: ForegroundConfig | None = None
    ) -> RigForeground:
        """Learn from synchronized frame sets (a background clip, or frames of the stream: the
        per-pixel median ignores actors that cover a pixel in fewer than half of them)."""
        per_cam: list[list[Image]] = [[] for _ in range(len(rig))]
        for fs in framesets:
            if len(fs.images) != len(rig):
                raise DataError(
                    f"frame set {fs.time_index} has {len(fs.images)} images for {len(rig)} cameras"
                )
            for i, im in enumerate(fs.images):
                if im is not None:
                    per_cam[i].append(im)
        for cam, frames in zip(rig, per_cam, strict=True):
            if not frames:
                raise DataError(f"camera {cam.name!r}: no frames to learn the background from")
        return cls.learn(rig, per_cam, config)

    @classmethod
    def from_states(
        cls, rig: Rig, states: Sequence[BackgroundState], config: ForegroundConfig | None = None
    ) -> RigForeground:
        config = config or ForegroundConfig()
        return cls(rig, [BackgroundModel.from_state(s, config.background) for s in states], config)

    def states(self) -> list[BackgroundState]:
        """Snapshots of the models' states (picklable; see ``from_states``)."""
        return [m.state for m in self.models]

    def warm_up(self, framesets: Iterable[FrameSet]) -> int:
        """Let the models learn from frames before the first task; returns frames used."""
        n = 0
        for fs in track(framesets, "warming up background models"):
            self._model_masks(fs, update=True)
            n += 1
        return n

    def _model_masks(self, frames: FrameSet, update: bool) -> list[Mask | None]:
        if len(frames.images) != len(self.rig):
            raise DataError(
                f"frame set {frames.time_index} has {len(frames.images)} images for "
                f"{len(self.rig)} cameras"
            )
        return [
            None if im is None else model.apply(im, update=update)
            for model, im in zip(self.models, frames.images, strict=True)
        ]

    def set_occluders(self, depth_maps: Sequence[DepthMap | None] | None) -> None:
        """Per camera, the depth map of the static scene (e.g. ``hull.depth_map`` of the
        background cloud): the visual hull then knows what each camera cannot see. None
        forgets them."""
        if depth_maps is not None and len(depth_maps) != len(self.rig):
            raise DataError(f"{len(depth_maps)} occluder depth maps for {len(self.rig)} cameras")
        self.occluders = None if depth_maps is None else list(depth_maps)

    def _hull_inputs(
        self, masks: Sequence[Mask | None]
    ) -> tuple[list[Camera], list[Mask | None], list[DepthMap | None] | None]:
        """Cameras, masks and occluder maps at most ``hull_max_width`` pixels wide."""
        width = self.config.hull_max_width
        cams: list[Camera] = []
        small: list[Mask | None] = []
        occ: list[DepthMap | None] = []
        for i, (cam, m) in enumerate(zip(self.rig, masks, strict=True)):
            c = cam.scaled(width / cam.width) if cam.width > width else cam
            cams.append(c)
            small.append(None if m is None else resize_mask(m, c.size))
            d = None if self.occluders is None else self.occluders[i]
            if d is not None and c is not cam:
                d = np.asarray(
                    cv2.resize(np.asarray(d, np.float32), c.size, interpolation=cv2.INTER_NEAREST),
                    np.float32,
                )
            occ.append(d)
        return cams, small, (None if self.occluders is None else occ)

    def segment(self, frames: FrameSet, *, update: bool = True) -> ForegroundResult:
        """The foreground of one timestamp (the models learn from it unless ``update=False``)."""
        timings = StageTimings()
        cfg = self.config
        with timings.stage("background_subtraction"):
            model_masks = self._model_masks(frames, update)
        hull = None
        masks: list[Mask | None] = list(model_masks)
        with_fg = sum(m is not None and bool(m.any()) for m in model_masks)
        if cfg.hull_consistency and with_fg >= 1:
            # The hull is carved from masks at <= hull_max_width (the background model's
            # resolution): the same geometry for a fraction of the pixel work.
            cams, small, occ = self._hull_inputs(model_masks)
            with timings.stage("visual_hull"):
                hull = visual_hull(cams, small, cfg.hull, occluders=occ)
            with timings.stage("hull_consistency"):
                consistent = hull_consistent_masks(
                    hull, cams, small, max_missing=cfg.hull.max_missing, occluders=occ
                )
                for i, (m, sm, cm) in enumerate(zip(model_masks, small, consistent, strict=True)):
                    if m is None or sm is None or cm is None:
                        continue
                    removed = sm & ~cm
                    if removed.any():
                        masks[i] = m & ~resize_mask(removed, (m.shape[1], m.shape[0]))
        with timings.stage("objects"):
            objects = tuple(None if m is None else find_objects(m, cfg.objects) for m in masks)
        return ForegroundResult(
            time_index=frames.time_index,
            masks=tuple(masks),
            model_masks=tuple(model_masks),
            objects=objects,
            hull=hull,
            timings=timings,
        )
