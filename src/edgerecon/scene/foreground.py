"""Foreground of a whole rig per timestamp: background models, masks, hull, objects.

``RigForeground`` holds one ``BackgroundModel`` per rig camera (the only state of the scene
stage) and turns each ``FrameSet`` into a ``ForegroundResult``:

1. per camera, the background model's clean foreground mask;
2. optionally, the visual hull of all masks, and masks made consistent with it (foreground
   that no 3D object explains, such as a change only one camera sees, is dropped), then
   their holes filled where all cameras but one agree on an object (4+ cameras);
3. per camera, the objects (k-means with automatic k) of the final mask.

Everything runs at the models' working resolution (``BackgroundConfig.working_pixels``): the
masks, object label images and the hull's cameras are at that size, so the stage costs the
same for a 640x480 and a 1920x1080 rig. Segmenting never changes the models; ``update``
teaches them one frame (see :mod:`edgerecon.scene.stream` for which frames of a stream do).
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import logging
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.dense.planes import Plane, plane_depth
from edgerecon.geometry.camera import Camera, Rig
from edgerecon.scene.background import (
    BackgroundConfig,
    BackgroundModel,
    BackgroundState,
    Segmentation,
    UpdateStats,
    downscale,
    working_size,
)
from edgerecon.scene.ghosts import (
    PhotoCheckConfig,
    StaticCheckConfig,
    photo_consistent_masks,
    static_consistent_masks,
)
from edgerecon.scene.hull import (
    HullConfig,
    VisualHull,
    depth_map,
    hull_consistent_masks,
    hull_explained_masks,
    hull_filled_masks,
    hull_rescued,
    phantom_explained_masks,
    silhouette_distances,
    tolerant_hull,
    visual_hull,
)
from edgerecon.scene.masks import guided_mask, labels_joining
from edgerecon.scene.objects import ObjectConfig, ObjectSegmentation, find_objects
from edgerecon.scene.people import PersonSegmenter, person_segmenter
from edgerecon.threads import thread_map
from edgerecon.types import (
    DataError,
    DepthMap,
    FrameSet,
    Image,
    Mask,
    Points3D,
    StageTimings,
)

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
    hull_consistency: bool = True
    """Remove the foreground that the visual hull of all masks does not explain: a detection
    that the other cameras seeing the same space contradict, or that fewer than
    ``hull.min_views`` cameras see (it could not be reconstructed anyway)."""
    hull_fill: bool = True
    """With 4 or more cameras, fill the holes of each mask where a tolerant hull (all
    cameras but one agree) puts an object seen by the exact hull, inside the mask's own
    outline (``hull.hull_filled_masks``): a still actor's parts that match the background
    model in one camera come back from the others (hd4: foreground recall of the moving and
    still actors 0.82 -> 0.94; see docs/BENCHMARKS.md)."""
    hull_rescue: bool = True
    """With 4 or more cameras, bring back an object that all cameras but one see and that the
    one carves away where its model is unsettled (``hull.hull_rescued``): an actor whom one
    camera's model learned while it stood there during the bootstrap."""
    photo_check: bool = True
    """Drop the mask pixels, among the models' unsettled ones, whose hull points the other
    cameras all see in other colours (``ghosts.photo_consistent_masks``): ghosts where an
    actor stood while a model learned, which two opposite cameras share and the hull
    therefore keeps. Needs only the frames of the moment and the hull, so every command gets
    the same masks for a time index (hd4, 20 tasks: moving-actor IoU 0.727 -> 0.814, hd4p
    0.695 -> 0.761; about 0.065 s per task; docs/BENCHMARKS.md)."""
    photo: PhotoCheckConfig = field(default_factory=PhotoCheckConfig)
    """Parameters of that check."""
    phantom_explained_px: int | None = 4
    """Last but one of the hull steps when set: drop the mask pixels, among the models'
    unsettled ones, that only a phantom explains (inside the silhouette of the objects the
    hull dropped as phantoms, outside its own silhouette grown by this many working pixels;
    ``hull.phantom_explained_masks``; not while fewer than ``photo.min_reference_px`` mask
    pixels are settled): ghosts two facing cameras share, whose cones meet in the phantom.
    Moving-actor IoU (`bench_scene.py --online`, 20 tasks 0:240:12): hd4p 0.767 -> 0.790,
    hd4 0.814 -> 0.815; 62:240:9: hd4p 0.787 -> 0.810; hd6 (0:100:5) 0.833 -> 0.836, hd8
    unchanged; caliscope_charuco 0-0.6 % of a camera's mask pixels over 27 tasks (an arm's
    ghost on the floor), utrecht4cam none; about 10-14 ms per task on hd4p
    (docs/BENCHMARKS.md). The dense foreground does not change: those pixels have no hull
    depth interval. None = off."""
    hull_explained_px: int | None = None
    """Last of the hull steps when set: drop the mask pixels, among the models' unsettled
    ones, that the final hull does not explain (outside its silhouette grown by this many
    working pixels; ``hull.hull_explained_masks``): ghosts two facing cameras share, which
    neither contradicts and the hull's objects (phantoms removed) do not hold. With 4, the
    moving-actor IoU over 20 tasks: hd4p 0.766 -> 0.781, hd4 0.814 -> 0.819, hd6 +0.006,
    hd8 -0.001; the dense foreground is the same (those pixels have no hull depth range).
    Off by default: on caliscope_charuco it drops 10-33 % of each task's mask pixels (the
    close person's parts that the hull does not hold), which nothing there can check, and
    at the stream's first frame an actor whom the models learned leaves the masks with it
    (docs/BENCHMARKS.md)."""
    refine_px: int | None = 16
    """Last step when set: each final mask's outline moved to where its frame's colours
    change (``masks.guided_mask``: the colour guided filter of the mask in windows of ``2
    refine_px + 1`` working pixels): the halo of background that a model holds beside a
    still actor (its pixels were within ``background.update_guard_px`` of the actor, so they
    never learned the floor), which two facing cameras share and nothing else removes, and
    the outline of the working resolution. Added pixels never make two objects of the
    masks before it (``find_objects``) one. Moving-actor IoU (``bench_scene.py --online``,
    20 tasks 0:240:12, two passes, ``refine_subsample`` 2): hd4 0.815 -> 0.879, hd4p 0.790
    -> 0.856 (docs/BENCHMARKS.md); a few ms per camera and pass. None or 0 = off."""
    refine_passes: int = 2
    """How many times the refinement runs, each on the last one's masks (the filter's own
    outline moves further toward the colour edge: hd4 / hd4p, 10 tasks, pooled moving IoU
    0.869 / 0.837 with one, 0.881 / 0.850 with two, 0.886 / 0.855 with three)."""
    refine_subsample: int = 2
    """The filter's coefficients are fitted on the working frame reduced by this factor
    (the fast guided filter; hd4 / hd4p, 10 tasks, pooled moving IoU 0.8806 / 0.8496 with
    1, 0.8800 / 0.8492 with 2, at half the cost)."""
    refine_eps: float = 1e-3
    """The filter's ridge (squared colour, channels in 0..1): colour differences well below
    its square root (8 grey levels) do not move an outline."""
    refine_min_push: float = 0.0
    """A pixel changes only where the colours move its filtered value more than this away
    from what the filter gives without colour (0: any push across 0.5)."""
    num_threads: int = 2
    """Cameras whose per-camera steps (background subtraction, outline refinement, objects)
    run at once, on threads (OpenCV and NumPy release the interpreter lock); 1 = one after
    the other."""
    static_check: bool = False
    """Drop the mask pixels that show the static scene as other cameras see it uncovered
    (``ghosts.static_consistent_masks``): ghosts where an actor stood while a model learned
    (hd4: moving-actor IoU 0.73 -> 0.77, docs/BENCHMARKS.md). The static scene is the
    stream's own (``scene.stream``: a frame set on the update schedule every
    ``static.every_s``, reconstructed outside its model masks at the working resolution), so
    every command gets the same masks for a time index. Off by default: on caliscope_charuco
    it also removes true foreground (2 % of one camera's mask at t = 100, a line through the
    person and the board before a white wall), and its static scenes cost 0.5-0.8 s of CPU
    per 2 s of stream."""
    static: StaticCheckConfig = field(default_factory=StaticCheckConfig)
    """Parameters of that check."""
    hull_fill_close_px: int = 15
    """The outline a filled pixel must lie in: the mask closed by a disc of this diameter
    (working pixels), holes filled."""
    update_interval_s: float = 0.5
    """Stream time between two updates of the background models: every frame whose time
    index is a multiple of ``round(fps x update_interval_s)`` teaches them (seconds)."""
    bootstrap_span_s: float = 1.0
    """Without a background clip, the models start from the per-pixel median of frames spread
    over the first this many seconds of the stream. Short on purpose: whatever is present
    then is learned, and the ghost repair learns the background it uncovers as soon as it
    moves; a long span would also learn an actor who stands still for most of it and then
    hold nothing (measured on the hd4 preset: see docs/BENCHMARKS.md)."""
    bootstrap_frames: int = 8
    """How many frames (evenly spread over ``bootstrap_span_s``) enter that median."""
    person_model: str = "auto"
    """A learned person segmentation added to the models' masks before the visual hull
    (``scene.people``): people the models learned as background (present and still from the
    first frame) come back where several cameras agree. ``"auto"``: the model fetched by
    ``edgerecon models fetch``, when it is there and the models learned from the stream
    (no clip of the empty scene: a clip's models see a still person already, and the
    model's mistakes would only add); ``"on"``: the fetched model whatever the models
    learned from (an error without it); ``"off"``: never; else the model file's path (as
    ``"on"``)."""
    person_threshold: float = 0.5
    """A pixel is a person's when the model's probability exceeds this."""
    person_covered_max: float = 0.75
    """A person (a connected region of the person model's mask) joins the mask only when the
    background models hold less than this share of it: the people they miss (still from the
    first frame) come in whole, while the outline of one they see already stays theirs
    (the network's input is 256x144: its outlines spill a few working pixels onto what
    touches a person)."""

    def __post_init__(self) -> None:
        for name in ("update_interval_s", "bootstrap_span_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"ForegroundConfig.{name} must be > 0, got {getattr(self, name)}")
        for name in ("phantom_explained_px", "hull_explained_px", "refine_px"):
            value = getattr(self, name)
            if value is not None and value < 0:
                raise ValueError(f"ForegroundConfig.{name} must be >= 0 or None, got {value}")
        for name in (
            "refine_subsample",
            "refine_passes",
            "hull_fill_close_px",
            "bootstrap_frames",
            "num_threads",
        ):
            value = getattr(self, name)
            if value < 1:
                raise ValueError(f"ForegroundConfig.{name} must be >= 1, got {value}")
        if not 0.0 < self.person_covered_max <= 1.0:
            raise ValueError(
                f"ForegroundConfig.person_covered_max must be in (0, 1], got "
                f"{self.person_covered_max}"
            )
        if not 0.0 < self.person_threshold < 1.0:
            raise ValueError(
                f"ForegroundConfig.person_threshold must be in (0, 1), got {self.person_threshold}"
            )
        if not self.refine_eps > 0:
            raise ValueError(f"ForegroundConfig.refine_eps must be > 0, got {self.refine_eps}")
        if not 0.0 <= self.refine_min_push < 0.5:
            raise ValueError(
                f"ForegroundConfig.refine_min_push must be in [0, 0.5), got {self.refine_min_push}"
            )
        for name, cls in (
            ("background", BackgroundConfig),
            ("objects", ObjectConfig),
            ("hull", HullConfig),
            ("static", StaticCheckConfig),
            ("photo", PhotoCheckConfig),
        ):
            if not isinstance(getattr(self, name), cls):
                raise ValueError(f"ForegroundConfig.{name} must be a {cls.__name__}")


#: Four points at alternate corners of a cube's inner half spread through each voxel (a
#: regular tetrahedron): the photo check compares the colours at points this fine.
_TETRAHEDRON = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], np.float64)


def _hull_samples(hull: VisualHull, max_points: int) -> tuple[Points3D, float, NDArray[np.int32]]:
    """Points spread through the hull's voxels, four per voxel, their spacing (half a voxel)
    and their objects: the tolerant hull's voxels are twice the exact ones, too coarse to
    compare colours at their centres (hd4, the check's first version: moving-actor IoU 0.790
    with the centres, 0.812 with these). Beyond ``max_points`` (``PhotoCheckConfig``) the
    voxels' centres, a voxel apart."""
    if len(_TETRAHEDRON) * hull.num_voxels > max_points:
        return np.asarray(hull.centers, np.float64), hull.voxel_size, np.asarray(hull.labels)
    offsets = _TETRAHEDRON * (0.25 * hull.voxel_size)
    points = (hull.centers[:, None, :] + offsets[None]).reshape(-1, 3)
    return points, 0.5 * hull.voxel_size, np.repeat(hull.labels, len(offsets))


@dataclass(frozen=True, kw_only=True, eq=False)
class ForegroundResult:
    """Foreground of one timestamp, per rig camera (None for a camera without a frame)."""

    time_index: int
    """The frame set's time index."""
    masks: tuple[Mask | None, ...]
    """(h, w) final foreground per camera at the working resolution (``cameras``)."""
    model_masks: tuple[Mask | None, ...]
    """(h, w) background-model masks before the hull consistency step."""
    objects: tuple[ObjectSegmentation | None, ...]
    """Objects per camera (labels image, per-object boxes and ROIs), working resolution."""
    hull: VisualHull | None
    """Visual hull of the model masks (None when it was not computed)."""
    checked_masks: tuple[Mask | None, ...] = ()
    """The masks after the hull and ghost steps, before ``refine_px``'s outline refinement
    (empty: the same as ``masks``)."""
    timings: StageTimings
    """Seconds per step."""
    cameras: tuple[Camera, ...] = ()
    """The rig's cameras at the masks' working resolution (distortion kept)."""
    segmentations: tuple[Segmentation | None, ...] = field(default=(), repr=False)
    """The background models' per-camera classifications (reused by ``update``)."""
    hull_config: HullConfig | None = None
    """The visual hull's parameters (``ForegroundConfig.hull``), for a caller that carves
    it again (``pipeline.occluded_hull``)."""

    def slim(self) -> ForegroundResult:
        """The same result without the per-camera classifications (and their working
        images): what another node needs of it."""
        return dataclasses.replace(self, segmentations=())

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
        self,
        rig: Rig,
        models: Sequence[BackgroundModel],
        config: ForegroundConfig | None = None,
        *,
        from_stream: bool = False,
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
        self.static_clouds: tuple[Points3D, ...] = ()
        """The static scene's clouds, oldest first (``set_static_clouds``)."""
        self.static_floors: tuple[Plane | None, ...] = ()
        """Per static cloud, the ground plane its reconstruction found (or None)."""
        self.static_depth: list[DepthMap | None] | None = None
        self.from_stream = from_stream
        """The models learned from the stream itself, not from a clip of the empty scene
        (``scene.stream``): ``person_model = "auto"`` then adds the person model's masks."""

    @classmethod
    def learn(
        cls,
        rig: Rig,
        clips: Sequence[Iterable[Image]],
        config: ForegroundConfig | None = None,
        *,
        from_stream: bool = False,
    ) -> RigForeground:
        """Learn every camera's model from its background-only clip, or from the stream's
        first frames (``from_stream``: their medians then leave out the pixels the person
        model, where ``person_model`` uses it, sees a person in; see
        ``BackgroundModel.learn``)."""
        config = config or ForegroundConfig()
        if len(clips) != len(rig):
            raise DataError(f"{len(clips)} background clips for a rig of {len(rig)} cameras")
        models = thread_map(
            lambda job: learn_model(job[1], config, camera=job[0].name, from_stream=from_stream),
            list(zip(rig, clips, strict=True)),
            config.num_threads,
        )
        return cls(rig, models, config, from_stream=from_stream)

    @classmethod
    def learn_from_framesets(
        cls,
        rig: Rig,
        framesets: Iterable[FrameSet],
        config: ForegroundConfig | None = None,
        *,
        from_stream: bool = False,
    ) -> RigForeground:
        """Learn from synchronized frame sets (a background clip, or frames of the stream:
        ``from_stream``; the per-pixel median ignores actors that cover a pixel in fewer than
        half of them, and the person model's people)."""
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
        return cls.learn(rig, per_cam, config, from_stream=from_stream)

    @classmethod
    def from_states(
        cls,
        rig: Rig,
        states: Sequence[BackgroundState],
        config: ForegroundConfig | None = None,
        *,
        from_stream: bool = False,
    ) -> RigForeground:
        config = config or ForegroundConfig()
        models = [BackgroundModel.from_state(s, config.background) for s in states]
        return cls(rig, models, config, from_stream=from_stream)

    @property
    def people(self) -> PersonSegmenter | None:
        """The person model ``segment`` uses (``ForegroundConfig.person_model``), or None."""
        return _people(self.config, self.from_stream)

    def copy(self) -> RigForeground:
        """An independent copy: the models' states copied; the static scene, the occluders
        and their depth maps (replaced, never changed in place) shared."""
        out = copy.copy(self)
        # (``state`` is a copy already.)
        out.models = [BackgroundModel(m.state, m.config) for m in self.models]
        return out

    def states(self) -> list[BackgroundState]:
        """Snapshots of the models' states (picklable; see ``from_states``)."""
        return [m.state for m in self.models]

    @property
    def working_cameras(self) -> tuple[Camera, ...]:
        """The rig's cameras at the models' working resolution (what the masks are at)."""
        return tuple(
            cam.resized(*model.working_size)
            for cam, model in zip(self.rig, self.models, strict=True)
        )

    def reduce(self, frames: FrameSet) -> FrameSet:
        """``frames`` at the models' working resolution: all that ``segment`` and ``update``
        need of them, a fraction of the bytes when frames travel to another node."""
        self._check(frames)
        return dataclasses.replace(
            frames,
            images=tuple(
                None if im is None else downscale(im, model.working_size)
                for model, im in zip(self.models, frames.images, strict=True)
            ),
        )

    def _check(self, frames: FrameSet) -> None:
        if len(frames.images) != len(self.rig):
            raise DataError(
                f"frame set {frames.time_index} has {len(frames.images)} images for "
                f"{len(self.rig)} cameras"
            )

    def set_occluders(self, depth_maps: Sequence[DepthMap | None] | None) -> None:
        """Per camera, the depth map of the static scene at any resolution (e.g.
        ``hull.depth_map`` of the background cloud): the visual hull then knows what each
        camera cannot see. None forgets them."""
        if depth_maps is not None and len(depth_maps) != len(self.rig):
            raise DataError(f"{len(depth_maps)} occluder depth maps for {len(self.rig)} cameras")
        if depth_maps is None:
            self.occluders = None
            return
        self.occluders = [
            None
            if d is None
            else np.asarray(
                cv2.resize(np.asarray(d, np.float32), c.size, interpolation=cv2.INTER_NEAREST),
                np.float32,
            )
            if (d.shape[1], d.shape[0]) != c.size
            else np.asarray(d, np.float32)
            for c, d in zip(self.working_cameras, depth_maps, strict=True)
        ]

    def set_static_clouds(
        self, clouds: Sequence[Points3D], floors: Sequence[Plane | None] = ()
    ) -> None:
        """The static scene from several clouds of it, oldest first (``scene.stream`` keeps
        the last ``static.keep`` it built): each camera's depth is the newest cloud's where a
        point of it lands, else the next newer one's (where an actor stood in one, another
        saw the floor); with ``floors`` (per cloud, the ground plane its reconstruction found,
        or None) and ``static.floor``, the newest plane's where no cloud has a point and the
        pixel's ray meets it (a ghost's floor that no camera saw uncovered when a cloud was
        built)."""
        if floors and len(floors) != len(clouds):
            raise DataError(f"{len(floors)} floor planes for {len(clouds)} static clouds")
        pairs = [
            (np.asarray(c, np.float64), floors[i] if floors else None)
            for i, c in enumerate(clouds)
            if c is not None and len(c)
        ]
        kept = tuple(c for c, _ in pairs)
        self.static_clouds = kept
        self.static_floors = tuple(f for _, f in pairs)
        floor = next((f for f in reversed(self.static_floors) if f is not None), None)
        use_floor = floor is not None and self.config.static.floor
        if not kept and not use_floor:
            self.static_depth = None
            return
        depth: list[DepthMap | None] = []
        for cam in self.working_cameras:
            d = depth_map(kept[-1], cam) if kept else np.full(cam.size[::-1], np.nan, np.float32)
            for older in kept[-2::-1]:
                hole = ~np.isfinite(d)
                if not hole.any():
                    break
                d = np.where(hole, depth_map(older, cam), d).astype(np.float32)
            if use_floor:
                assert floor is not None
                on_floor = plane_depth(cam, floor)
                d = np.where(~np.isfinite(d) & (on_floor > 0), on_floor, d).astype(np.float32)
            depth.append(d)
        self.static_depth = depth

    def model_segmentations(self, frames: FrameSet) -> tuple[Segmentation | None, ...]:
        """The background models' per-camera classifications of ``frames`` (what ``segment``
        starts from, and what ``update`` reuses)."""
        self._check(frames)
        return tuple(
            thread_map(
                lambda pair: None if pair[1] is None else pair[0].segment(pair[1]),
                list(zip(self.models, frames.images, strict=True)),
                self.config.num_threads,
            )
        )

    def segment(self, frames: FrameSet) -> ForegroundResult:
        """The foreground of one timestamp at the working resolution. The models do not
        change (``update`` teaches them)."""
        self._check(frames)
        timings = StageTimings()
        cfg = self.config
        cams = self.working_cameras
        with timings.stage("background_subtraction"):
            segs = self.model_segmentations(frames)
        model_masks = tuple(None if sg is None else sg.foreground for sg in segs)
        unsettled = [m.unsettled for m in self.models]
        people = self.people
        if people is not None:
            # The people the models miss join their masks; their pixels have no other
            # evidence, so the checks below judge them as they judge the unsettled ones
            # (a gap between two people that the network fills shows the wall behind).
            with timings.stage("people"):
                added = thread_map(
                    lambda pair: (
                        None
                        if pair[0] is None or pair[1] is None or pair[1].image is None
                        else people_added(
                            pair[0],
                            people.mask(pair[1].image, cfg.person_threshold),
                            cfg.person_covered_max,
                        )
                    ),
                    list(zip(model_masks, segs, strict=True)),
                    cfg.num_threads,
                )
                model_masks = tuple(
                    m if m is None or a is None else m | a
                    for m, a in zip(model_masks, added, strict=True)
                )
                unsettled = [
                    u if a is None else u | a for u, a in zip(unsettled, added, strict=True)
                ]
        hull = None
        masks: list[Mask | None] = list(model_masks)
        with_fg = sum(m is not None and bool(m.any()) for m in model_masks)
        if cfg.hull_consistency and with_fg >= 1:
            occ = self.occluders
            with timings.stage("visual_hull"):
                dists = silhouette_distances(model_masks)
                hull = visual_hull(
                    list(cams), list(model_masks), cfg.hull, occluders=occ, distances=dists
                )
            with timings.stage("hull_consistency"):
                masks = list(
                    hull_consistent_masks(
                        hull,
                        list(cams),
                        list(model_masks),
                        max_missing=cfg.hull.max_missing,
                        occluders=occ,
                    )
                )
                masks = [
                    None if m is None else (m if c is None else m & c)
                    for m, c in zip(model_masks, masks, strict=True)
                ]
            if cfg.hull_rescue:
                with timings.stage("hull_rescue"):
                    hull, masks, _ = hull_rescued(
                        hull,
                        list(cams),
                        masks,
                        list(model_masks),
                        unsettled,
                        cfg.hull,
                        occluders=occ,
                        distances=dists,
                    )
            tolerant = None
            if cfg.photo_check and hull.num_voxels:
                with timings.stage("tolerant_hull"):
                    tolerant = tolerant_hull(
                        hull,
                        list(cams),
                        list(model_masks),
                        cfg.hull,
                        occluders=occ,
                        distances=dists,
                    )
            if cfg.hull_fill:
                with timings.stage("hull_fill"):
                    masks = hull_filled_masks(
                        hull,
                        list(cams),
                        masks,
                        list(model_masks),
                        cfg.hull,
                        close_px=cfg.hull_fill_close_px,
                        occluders=occ,
                        distances=dists,
                        allowed=unsettled,
                        tolerant=tolerant,
                    )
            if cfg.photo_check and hull.num_voxels:
                with timings.stage("photo_check"):
                    sampled = tolerant if tolerant is not None and tolerant.num_voxels else hull
                    points, size, labels = _hull_samples(sampled, cfg.photo.max_points)
                    # Each frame at its model's exposure (its gain divided out).
                    exposed: list[NDArray[np.float32] | None] = [
                        None
                        if sg is None or sg.image is None
                        else np.asarray(sg.image / sg.gain.astype(np.float32), np.float32)
                        for sg in segs
                    ]
                    masks, _ = photo_consistent_masks(
                        points,
                        size,
                        list(cams),
                        masks,
                        exposed,
                        unsettled,
                        cfg.photo,
                        labels=labels,
                        num_threads=cfg.num_threads,
                    )
            if cfg.phantom_explained_px is not None:
                with timings.stage("phantom_explained"):
                    masks = phantom_explained_masks(
                        hull,
                        list(cams),
                        masks,
                        unsettled,
                        cfg.phantom_explained_px,
                        min_settled_px=cfg.photo.min_reference_px,
                    )
            if cfg.hull_explained_px is not None:
                with timings.stage("hull_explained"):
                    masks = hull_explained_masks(
                        hull, list(cams), masks, unsettled, cfg.hull_explained_px
                    )
        static = self.static_depth
        if cfg.static_check and static is not None and any(m is not None for m in masks):
            with timings.stage("static_check"):
                masks, _ = static_consistent_masks(
                    masks,
                    [None if sg is None else sg.image for sg in segs],
                    list(cams),
                    static,
                    cfg.static,
                    backgrounds=[m.background_image(working=True) for m in self.models],
                )
        checked = tuple(masks)
        refine = cfg.refine_px is not None and cfg.refine_px > 0
        if refine:
            base = _CheckedObjects(checked, cfg.objects)
            with timings.stage("refine"):
                for _ in range(cfg.refine_passes):
                    masks = self._refined(masks, segs, base)
        with timings.stage("objects"):
            found = thread_map(
                lambda m: None if m is None else find_objects(m, cfg.objects),
                list(masks),
                cfg.num_threads,
            )
            if refine:
                masks, found = _unglued(masks, found, base, cfg.objects)
            objects = tuple(found)
        return ForegroundResult(
            time_index=frames.time_index,
            masks=tuple(masks),
            model_masks=model_masks,
            objects=objects,
            hull=hull,
            checked_masks=checked,
            timings=timings,
            cameras=cams,
            segmentations=segs,
            hull_config=cfg.hull,
        )

    def _refined(
        self,
        masks: Sequence[Mask | None],
        segs: Sequence[Segmentation | None],
        base: _CheckedObjects,
    ) -> list[Mask | None]:
        """One pass of the outline refinement (``ForegroundConfig.refine_px``): its added
        pixels join no two objects of the masks before the first pass (``base``)."""
        cfg = self.config
        assert cfg.refine_px is not None
        refine_px = cfg.refine_px

        def one(c: int) -> Mask | None:
            m, sg = masks[c], segs[c]
            if m is None or sg is None or sg.image is None:
                return m
            return guided_mask(
                m,
                sg.image,
                refine_px,
                cfg.refine_eps,
                cfg.refine_min_push,
                groups=base.of(c),
                subsample=cfg.refine_subsample,
            )

        return thread_map(one, list(range(len(masks))), cfg.num_threads)

    def update(
        self,
        frames: FrameSet,
        result: ForegroundResult | None = None,
        *,
        segmentations: Sequence[Segmentation | None] | None = None,
    ) -> list[UpdateStats | None]:
        """Teach every camera's model one frame set (ghost repair + selective update).
        ``result``: this frame set's ``segment`` result, whose classifications are reused (or
        ``segmentations``, those of ``model_segmentations``)."""
        self._check(frames)
        segs: Sequence[Segmentation | None] = (
            segmentations
            if segmentations is not None
            else result.segmentations
            if result is not None
            and result.time_index == frames.time_index
            and result.segmentations
            else (None,) * len(self.rig)
        )
        jobs = list(zip(self.models, frames.images, segs, strict=True))
        return thread_map(
            lambda job: None if job[1] is None else job[0].update(job[1], job[2]),
            jobs,
            self.config.num_threads,
        )


def learn_model(
    frames: Iterable[Image],
    config: ForegroundConfig,
    *,
    camera: str = "",
    from_stream: bool = False,
) -> BackgroundModel:
    """One camera's background model from a clip of the empty scene, or from frames of the
    stream (``from_stream``), whose medians leave out the people the person model sees
    where ``person_model`` uses it (``BackgroundModel.learn``'s ``people``)."""
    frames = list(frames)
    people = _people(config, from_stream)
    masks = None
    if people is not None:
        # At the working resolution, as ``segment`` runs it.
        masks = [
            people.mask(
                downscale(
                    f, working_size((f.shape[1], f.shape[0]), config.background.working_pixels)
                ),
                config.person_threshold,
            )
            for f in frames
        ]
    return BackgroundModel.learn(frames, config.background, camera=camera, people=masks)


def _people(config: ForegroundConfig, from_stream: bool) -> PersonSegmenter | None:
    """The person model of models learned from a clip (``from_stream`` False) or from the
    stream (``ForegroundConfig.person_model``), or None."""
    setting = config.person_model
    if setting == "off" or (setting == "auto" and not from_stream):
        return None
    return person_segmenter(setting)


def people_added(model: Mask, people: Mask, covered_max: float) -> Mask:
    """The pixels of every connected region of ``people`` (8-connected) of which ``model``
    holds less than ``covered_max`` (``ForegroundConfig.person_covered_max``), outside
    ``model``."""
    n, labels = cv2.connectedComponents(people.view(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros_like(model)
    total = np.bincount(labels.ravel(), minlength=n)
    held = np.bincount(labels[model], minlength=n)
    add = held < covered_max * total
    add[0] = False
    return np.asarray(add[labels] & ~model, bool)


class _CheckedObjects:
    """The objects of the masks before the outline refinement, found per camera only when
    asked (``find_objects``)."""

    def __init__(self, masks: Sequence[Mask | None], config: ObjectConfig) -> None:
        self.masks = masks
        self.config = config
        self._labels: dict[int, NDArray[np.int32]] = {}

    def of(self, camera: int) -> Callable[[], NDArray[np.int32]]:
        """``guided_mask``'s ``groups`` for ``camera``: the objects before the first pass,
        whatever mask the pass starts from."""
        return functools.partial(self.labels, camera)

    def labels(self, camera: int) -> NDArray[np.int32]:
        if camera not in self._labels:
            mask = self.masks[camera]
            assert mask is not None
            self._labels[camera] = find_objects(mask, self.config).labels
        return self._labels[camera]


def _unglued(
    masks: Sequence[Mask | None],
    found: Sequence[ObjectSegmentation | None],
    base: _CheckedObjects,
    config: ObjectConfig,
) -> tuple[list[Mask | None], list[ObjectSegmentation | None]]:
    """The refined masks without the pixels they added to an object that holds two objects
    of the masks before the refinement (added pixels that brought two actors within the
    objects' fragment gap without touching them), and their objects found again."""
    out_masks, out_found = list(masks), list(found)
    for c, (m, seg) in enumerate(zip(masks, found, strict=True)):
        before = base.masks[c]
        if m is None or seg is None or before is None or seg.num_objects == 0:
            continue
        added = m & ~before
        if not added.any():
            continue
        # One component before: at most one object, nothing to glue.
        if cv2.connectedComponents(before.view(np.uint8), connectivity=8)[0] <= 2:
            continue
        labels = base.labels(c)
        both = before & m & (labels > 0) & (seg.labels > 0)
        glued = labels_joining(seg.labels[both], labels[both])
        if len(glued):
            kept = m & ~(added & np.isin(seg.labels, glued))
            out_masks[c] = kept
            out_found[c] = find_objects(kept, config)
    return out_masks, out_found
