"""Which frames of a stream teach the background models: one definition for every command.

The masks of time index ``t`` are the segmentation of frame ``t`` by the background models *as
they are at t*, and the models at ``t`` are defined by the stream alone:

1. **bootstrap** — from the dataset's clip of the empty scene when it has one; otherwise the
   per-pixel median of ``bootstrap_frames`` frames spread evenly over the first
   ``bootstrap_span_s`` seconds of the stream (an actor who moves within that span is left
   out of the median; one who does not is learned as background until the ghost repair or the
   absorption catches up, see :mod:`edgerecon.scene.background`);
2. **updates** — every frame whose time index is a multiple of the update step
   ``max(1, round(fps x update_interval_s))`` and lies before ``t`` teaches the models, in
   order (ghost repair + selective update: a stopped actor is held, uncovered background is
   learned at once, the rest learns slowly).

3. **static scene** — with ``ForegroundConfig.static_check``, the update frame set whose time
   index is a multiple of the static step (``static.every_s`` of stream, a multiple of the
   update step) is also reconstructed outside its model masks at the working resolution
   (``pipeline.reconstruct_static``); the masks of every later time index are checked
   against the last ``static.keep`` such clouds for ghosts
   (``ghosts.static_consistent_masks``), so catching up builds those alone. Off by default
   (``ForegroundConfig.static_check``).

``edgerecon masks``, ``reconstruct --split`` and ``run`` all follow it, so one time index gets
the same masks from each (with the same settings), whatever the task schedule. The updates
cost one background-model update per camera per step, a few milliseconds at the working
resolution (50-80 ms for 4 cameras at 480x270; the online session applies those due before
the next task between two tasks, off both critical paths, ``Session._learn_ahead``): on a
25 fps stream with the default 0.5 s interval, one update every 12 frames;
with the static check, a static scene costs 0.5-0.8 s (hd4, 4 x 480x270) once every 2 s of
stream, after the critical path of the task whose frames it uses (or, when that frame was not
a task, of the next task).

What it cannot do: an actor who never moves during the bootstrap span and never moves away
stays background to the models (the person model, ``scene.people``, adds a person back where
several cameras agree: real people, rendered actors only in parts; nothing brings back a still
object that is not a person); a slowly moving actor whose old and new silhouettes overlap
leaves a ghost fused to the actor until they separate.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

import numpy as np

from edgerecon.dense.planes import Plane
from edgerecon.geometry.camera import Rig
from edgerecon.io.streams import LIVE_FRAMES
from edgerecon.pipeline import reconstruct_static
from edgerecon.progress import track
from edgerecon.scene.foreground import ForegroundConfig, ForegroundResult, RigForeground
from edgerecon.types import DataError, EdgereconError, FrameSet, Mask

if TYPE_CHECKING:
    from edgerecon.io.dataset import Dataset

logger = logging.getLogger(__name__)

#: Frame rate assumed for streams that do not state one (image folders without ``fps``).
DEFAULT_FPS = 25.0


class FrameReader(Protocol):
    """What the schedule reads frames from (``io.frames`` sources)."""

    @property
    def num_frames(self) -> int: ...

    def read(self, t: int) -> FrameSet: ...


def _rate(fps: float | None) -> float:
    """The stream's frame rate (``DEFAULT_FPS`` when unknown)."""
    return fps if fps is not None and fps > 0 else DEFAULT_FPS


def update_step(fps: float | None, config: ForegroundConfig) -> int:
    """Time-index step between two updates of the models."""
    return max(1, round(_rate(fps) * config.update_interval_s))


def static_step(fps: float | None, config: ForegroundConfig) -> int:
    """Time-index step between two static scenes (a multiple of the update step); 0 when
    the static check is off."""
    if not config.static_check:
        return 0
    step = update_step(fps, config)
    return step * max(1, round(_rate(fps) * config.static.every_s / step))


def read_spread(
    reader: FrameReader,
    indices: Sequence[int],
    *,
    on_error: Callable[[int, EdgereconError], None] | None = None,
) -> Iterator[FrameSet]:
    """The frame sets of ``indices`` (ascending). A live reader (``io.streams``: unbounded,
    each read the next fresh set whatever its index) reads every set from the first index
    to the last and gives those of ``indices``, so that its frames spread over as much of the
    stream as a recording's (eight reads in a row would take eight consecutive frames: a
    fraction of a second, in which nobody moves). ``on_error``: told of a read that raised
    (``EdgereconError``), which is then left out; without it the error propagates."""
    if not indices:
        return
    live = reader.num_frames >= LIVE_FRAMES
    wanted = set(indices)
    for t in range(indices[0], indices[-1] + 1) if live else indices:
        try:
            frames = reader.read(t)
        except EdgereconError as exc:
            if on_error is None:
                raise
            on_error(t, exc)
            continue
        if t in wanted:
            yield frames


def bootstrap_indices(num_frames: int, fps: float | None, config: ForegroundConfig) -> list[int]:
    """Time indices whose median bootstraps the models (no background clip)."""
    if num_frames < 1:
        raise DataError("the stream has no frames to learn the background from")
    span = max(1, min(num_frames, round(_rate(fps) * config.bootstrap_span_s)))
    idx = np.linspace(0, span - 1, min(span, config.bootstrap_frames)).round().astype(int)
    return sorted({int(i) for i in idx})


@dataclass
class SceneTracker:
    """The background models of a rig and where they are in the stream.

    ``segment(frames)`` gives the foreground of a frame set with the models as they are now;
    ``learn(frames)`` applies one scheduled update; ``catch_up(reader, t)`` applies every
    scheduled update before ``t`` that is still missing, reading the frames it needs.
    """

    foreground: RigForeground
    step: int
    """Update step in time indices."""
    next_update: int = 0
    """The next scheduled time index not yet learned."""
    learned_from: str = ""
    seconds: dict[str, float] = field(default_factory=dict)
    """Seconds spent: ``bootstrap`` (reading + median), ``updates``."""
    updates: int = 0
    """Scheduled updates applied."""
    ghosts: int = 0
    """Ghost blobs repaired by those updates."""
    skipped: int = 0
    """Scheduled updates skipped because they raised (``skip``)."""
    static_step: int = 0
    """Time-index step between two static scenes (0: none; ``static_step``)."""
    static_from: int | None = None
    """Time index of the frame set the current static scene was built from."""
    _deferred: list[tuple[FrameSet, list[Mask | None]]] = field(default_factory=list, repr=False)

    @property
    def rig(self) -> Rig:
        return self.foreground.rig

    def pending(self, t: int) -> list[int]:
        """Scheduled time indices before ``t`` not learned yet."""
        return list(range(self.next_update, t, self.step))

    def segment(self, frames: FrameSet) -> ForegroundResult:
        """The foreground of ``frames`` (the models are not changed)."""
        return self.foreground.segment(frames)

    def learn(
        self,
        frames: FrameSet,
        result: ForegroundResult | None = None,
        *,
        static: bool = True,
        defer_static: bool = False,
    ) -> float:
        """Apply the scheduled update of ``frames`` (its time index must be the next one on
        the schedule; a frame set before it is ignored), and build the static scene from it
        when it is on that schedule too (``static=False`` skips that: a later one replaces
        it; ``defer_static`` keeps it for :meth:`settle`, e.g. after a task's critical
        path). ``result``: this frame set's segmentation, reused. Returns the seconds it
        took."""
        t = frames.time_index
        if t < self.next_update or t % self.step:
            return 0.0
        if t != self.next_update:
            # Frames were skipped (a live stream dropped them): the schedule moves on.
            logger.debug("scene: schedule jumps from %d to %d", self.next_update, t)
        t0 = time.perf_counter()
        fg = self.foreground
        segs = (
            result.segmentations
            if result is not None and result.time_index == t and result.segmentations
            else fg.model_segmentations(frames)
        )
        stats = fg.update(frames, segmentations=segs)
        seconds = time.perf_counter() - t0
        self.next_update = t + self.step
        self.updates += 1
        self.ghosts += sum(s.ghosts for s in stats if s is not None)
        self.seconds["updates"] = self.seconds.get("updates", 0.0) + seconds
        if static and self.static_due(t):
            # Out of the static scene: the models' masks before the hull steps (whatever might
            # move) and the pixels that moved while a model learned (a still person whom the
            # models learned, a seated one, must not become the static scene).
            masks = [
                None if s is None else s.foreground | model.unsettled
                for s, model in zip(segs, fg.models, strict=True)
            ]
            if defer_static:
                self._deferred.append((frames, masks))
            else:
                seconds += self._build_static(frames, masks)
        return seconds

    def snapshot(self) -> SceneTracker:
        """An independent copy (``RigForeground.copy``): what a front-end falls back to when
        a stage holding the tracker hangs."""
        return dataclasses.replace(
            self,
            foreground=self.foreground.copy(),
            seconds=dict(self.seconds),
            _deferred=list(self._deferred),
        )

    def skip(self, t: int) -> None:
        """The scheduled update of time ``t`` could not be applied (its frames raised in the
        models' update): the schedule moves on without it, as without a frame that cannot
        be read. The models miss one update (a camera may hold part of it); the masks of
        later time indices may then differ from ``scene_at``'s until the models converge."""
        if t < self.next_update:
            return
        self.next_update = t - t % self.step + self.step
        self.skipped += 1

    def settle(self) -> float:
        """Build the static scenes that ``learn(..., defer_static=True)`` kept, in order (the
        last ``static.keep`` of them); returns seconds."""
        deferred, self._deferred = self._deferred, []
        keep = self.foreground.config.static.keep
        return sum((self._build_static(*d) for d in deferred[-keep:]), 0.0)

    def static_due(self, t: int) -> bool:
        """Whether the frame set of time ``t`` gives the next static scene."""
        return self.static_step > 0 and t % self.static_step == 0

    def _build_static(self, frames: FrameSet, keep_out: list[Mask | None]) -> float:
        """The static scene from ``frames`` outside ``keep_out`` at the working resolution. A
        failure keeps the previous scene (a warning)."""
        # Kept ones older than this are superseded (their order would be wrong after it).
        self._deferred = [d for d in self._deferred if d[0].time_index > frames.time_index]
        t0 = time.perf_counter()
        fg = self.foreground
        rig = dataclasses.replace(self.rig, cameras=fg.working_cameras)
        try:
            dense = reconstruct_static(fg.reduce(frames), rig, keep_out)
        except Exception as exc:  # a bad frame set must not stop the stream
            logger.warning(
                "scene: no static scene from time %d (%s); keeping the one from %s",
                frames.time_index,
                exc,
                self.static_from,
            )
            return time.perf_counter() - t0
        keep = fg.config.static.keep
        found = dense.stats.get("ground_plane")
        older = slice(max(0, len(fg.static_clouds) - keep + 1), None)
        fg.set_static_clouds(
            [*fg.static_clouds[older], dense.cloud.points3D],
            [*fg.static_floors[older], None if found is None else Plane(**found)],
        )
        self.static_from = frames.time_index
        seconds = time.perf_counter() - t0
        self.seconds["static"] = self.seconds.get("static", 0.0) + seconds
        logger.info(
            "scene: static scene from time %d: %d points in %.2f s",
            frames.time_index,
            len(dense.cloud),
            seconds,
        )
        return seconds

    def catch_up(self, reader: FrameReader, t: int, *, progress: bool = False) -> float:
        """Apply the scheduled updates before ``t`` that are missing, and build the latest
        ``static.keep`` static scenes among them (the earlier ones would be dropped); returns
        seconds."""
        todo = self.pending(t)
        due = [s for s in todo if self.static_due(s)]
        build = set(due[-self.foreground.config.static.keep :])
        seconds = 0.0
        it = track(todo, "background updates") if progress and len(todo) > 4 else todo
        for s in it:
            seconds += self.learn(reader.read(s), static=s in build)
        return seconds


def bootstrap_scene(
    rig: Rig,
    reader: FrameReader,
    fps: float | None,
    config: ForegroundConfig | None = None,
    *,
    clip: FrameReader | None = None,
    progress: bool = False,
) -> SceneTracker:
    """Background models at the start of the stream (step 1 of the module docstring):
    from ``clip`` (frames of the empty scene) when given, else from the stream's first
    ``bootstrap_span_s`` seconds."""
    config = config or ForegroundConfig()
    t0 = time.perf_counter()
    indices: list[int]
    if clip is not None:
        n = clip.num_frames
        keep = config.background.max_learning_frames
        indices = sorted({int(i) for i in np.linspace(0, n - 1, min(n, keep)).round()})
        source, what = clip, "background clip"
    else:
        indices = bootstrap_indices(reader.num_frames, fps, config)
        source = reader
        what = f"median of {len(indices)} frames of the stream (time {indices[0]}..{indices[-1]})"
    reads = read_spread(source, indices)
    framesets = list(
        track(reads, "learning the background", total=len(indices)) if progress else reads
    )
    fg = RigForeground.learn_from_framesets(rig, framesets, config, from_stream=clip is None)
    if fg.from_stream and fg.people is not None:
        what += ", the people the person model sees left out"
    seconds = time.perf_counter() - t0
    logger.info("scene: background models from the %s in %.1f s", what, seconds)
    people = fg.people
    if people is not None:
        logger.info("scene: people from the person model too (%s)", people.path)
    elif fg.from_stream and config.person_model == "auto":
        _say_no_person_model()
    return SceneTracker(
        foreground=fg,
        step=update_step(fps, config),
        static_step=static_step(fps, config),
        learned_from=what,
        seconds={"bootstrap": seconds},
    )


@functools.cache
def _say_no_person_model() -> None:
    """Once per process: models learned from the stream without the person model."""
    logger.warning(
        "no clip of the empty scene and no person model: people who stay still from the "
        "first frame stay background (`edgerecon models fetch` gets the model)"
    )


def scene_at(
    rig: Rig,
    reader: FrameReader,
    fps: float | None,
    t: int,
    config: ForegroundConfig | None = None,
    *,
    clip: FrameReader | None = None,
    progress: bool = False,
) -> SceneTracker:
    """The background models as they are when time index ``t`` is segmented (bootstrap, then
    every scheduled update before ``t``)."""
    tracker = bootstrap_scene(rig, reader, fps, config, clip=clip, progress=progress)
    tracker.catch_up(reader, t, progress=progress)
    return tracker


def dataset_scene_at(
    dataset: Dataset,
    t: int,
    config: ForegroundConfig | None = None,
    *,
    progress: bool = False,
) -> SceneTracker:
    """``scene_at`` for a dataset: its background clip if it has one, its stream, its fps."""
    clip = dataset.open_background()
    try:
        with dataset.open_frames() as source:
            return scene_at(
                dataset.rig, source, dataset.fps, t, config, clip=clip, progress=progress
            )
    finally:
        if clip is not None:
            clip.close()
