"""Engines: where the two roles run. The embedded engine (default) runs both in this process;
the Ray engine (:mod:`edgerecon.runtime.ray_engine`) runs each as an actor on its own node.

Both drive the same :class:`FrontEnd` / :class:`BackEnd` classes through the same
:class:`BackendLink` health logic and :func:`run_frontend_task`, so a task gives the same
result on either engine; :class:`Engine` is what the session may call.

Back-end health: when the back-end cannot take a task (the transport fails) or, with the
golden online estimate, does not deliver the reference in time, it is *lost*: the front-end
stops submitting to it (tasks still run whole: the masks are the front-end's own; the
background stops advancing, and golden-estimate tasks run degraded) and checks every
``backend_retry_s`` seconds whether it answers again and is idle; then it is used again from
the next task on.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from edgerecon import progress
from edgerecon.dense.planes import Plane
from edgerecon.geometry.camera import Rig
from edgerecon.io.dataset import Dataset
from edgerecon.io.streams import LIVE_FRAMES
from edgerecon.optimize.controller import BisectionController
from edgerecon.pipeline import warm_up
from edgerecon.runtime.backend import BackEnd
from edgerecon.runtime.config import RuntimeConfig
from edgerecon.runtime.frontend import (
    FixedController,
    FrontEnd,
    FrontEndState,
    TaskOutput,
    too_few_cameras,
)
from edgerecon.runtime.messages import GoldenReply, TaskPlan, TaskWork
from edgerecon.scene.background import BackgroundState
from edgerecon.scene.foreground import (
    ForegroundConfig,
    ForegroundResult,
    RigForeground,
    learn_model,
)
from edgerecon.scene.stream import (
    SceneTracker,
    bootstrap_indices,
    bootstrap_scene,
    dataset_scene_at,
    read_spread,
)
from edgerecon.types import EdgereconError, FrameSet, Image, PointCloud, Points3D

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True, eq=False)
class SceneModel:
    """What the roles start from: the background models at the first task (and where that
    is on their update schedule) and, when the dataset has a clip of the empty scene, one
    frame set of it for the first background reconstruction."""

    states: tuple[BackgroundState, ...]
    step: int
    """Update step of the models' schedule (time indices)."""
    next_update: int
    """The next scheduled update the models have not learned."""
    initial_background: FrameSet | None
    learned_from: str
    """What the models were bootstrapped from (the clip, or frames of the stream)."""
    seconds: float
    static_step: int = 0
    """Step of the static scenes (time indices; 0: none)."""
    static_from: int | None = None
    """Time index the static scene was built from (None: none yet)."""
    static_clouds: tuple[Points3D, ...] = ()
    """The static scene's clouds, oldest first (the ghost check's; ``scene.stream``)."""
    static_floors: tuple[Plane | None, ...] = ()
    """Per static cloud, its ground plane (or None)."""
    from_stream: bool | None = None
    """Whether the models were learned from the stream, not from a clip of the empty scene
    (the person model's ``auto``); None: as ``initial_background`` says (no clip frame)."""

    @classmethod
    def of_tracker(
        cls, tracker: SceneTracker, initial_background: FrameSet | None = None, seconds: float = 0.0
    ) -> SceneModel:
        """What ``tracker``'s models are now (their states are taken as they are: pass a
        copy of a tracker that goes on learning)."""
        return cls(
            states=tuple(tracker.foreground.states()),
            step=tracker.step,
            next_update=tracker.next_update,
            initial_background=initial_background,
            learned_from=tracker.learned_from,
            seconds=seconds,
            static_step=tracker.static_step,
            static_from=tracker.static_from,
            static_clouds=tracker.foreground.static_clouds,
            static_floors=tracker.foreground.static_floors,
            from_stream=tracker.foreground.from_stream,
        )

    def without_geometry(self) -> SceneModel:
        """The models without their static scenes (3D clouds made with the rig's poses):
        what goes on after cameras were placed again (the next static step builds them)."""
        return dataclasses.replace(self, static_clouds=(), static_floors=(), static_from=None)

    def tracker(self, rig: Rig, config: ForegroundConfig | None = None) -> SceneTracker:
        """Live background models (a copy: the snapshot stays as it is)."""
        fg = RigForeground.from_states(
            rig,
            self.states,
            config,
            from_stream=(
                self.initial_background is None if self.from_stream is None else self.from_stream
            ),
        )
        fg.set_static_clouds(self.static_clouds, self.static_floors)
        return SceneTracker(
            foreground=fg,
            step=self.step,
            next_update=self.next_update,
            learned_from=self.learned_from,
            static_step=self.static_step if fg.config.static_check else 0,
            static_from=self.static_from,
        )


@progress.phase("learn the background model")
def learn_scene_model(
    dataset: Dataset,
    foreground: ForegroundConfig | None = None,
    start: int = 0,
) -> SceneModel:
    """The background models as they are at time index ``start`` (the first task): the
    bootstrap of :mod:`edgerecon.scene.stream` (background clip, or frames spread over the
    stream's first second), then the scheduled updates before ``start``."""
    t0 = time.perf_counter()
    clip = dataset.open_background()
    try:
        with dataset.open_frames() as source:
            tracker = bootstrap_scene(dataset.rig, source, dataset.fps, foreground, clip=clip)
            tracker.catch_up(source, start)
            initial = None
            if clip is not None:
                initial = FrameSet(time_index=-1, images=clip.read(clip.num_frames // 2).images)
    finally:
        if clip is not None:
            clip.close()
    return SceneModel.of_tracker(tracker, initial, time.perf_counter() - t0)


def relearned(
    model: SceneModel,
    dataset: Dataset,
    cameras: Sequence[int],
    before: int,
    config: ForegroundConfig | None = None,
) -> SceneModel:
    """``model`` with the background models of ``cameras`` learned again from the stream's
    frames before time index ``before`` (the median of ``bootstrap_frames`` over the
    ``bootstrap_span_s`` before it, as a stream's bootstrap): cameras re-posed during a run
    no longer see the scene as their models learned it (a clip of the empty scene, or the
    frames before the knock). A live stream keeps no frames behind: its models learn from
    its next ``bootstrap_span_s`` instead, its sets spread over it as a live run's bootstrap
    spreads them (``scene.stream.read_spread``; ``before`` is then only a label)."""
    config = config or ForegroundConfig()
    if not cameras or before < 1:
        return model
    if dataset.is_live:
        # Its next span (``read_spread`` reads every set of it, keeps these).
        times = [before + i for i in bootstrap_indices(LIVE_FRAMES, dataset.fps, config)]
        what = "the live stream's next frames"
    else:
        offsets = bootstrap_indices(before, dataset.fps, config)
        start = before - (offsets[-1] + 1)
        times = [start + i for i in offsets]
        what = f"time {times[0]}..{times[-1]}"

    def left_out(t: int, exc: EdgereconError) -> None:  # the others serve
        logger.warning("scene: time %d left out of the models learned again: %s", t, exc)

    frames: dict[int, list[Image]] = {c: [] for c in cameras}
    with dataset.open_frames(missing="skip_camera") as source:
        for fs in read_spread(source, times, on_error=left_out):
            for c in cameras:
                if (image := fs.images[c]) is not None:
                    frames[c].append(image)
    states = list(model.states)
    for c in cameras:
        name = dataset.rig[c].name
        if not frames[c]:
            logger.warning("scene: no frame of %s to learn its models again from", name)
            continue
        states[c] = learn_model(frames[c], config, camera=name, from_stream=True).state
    logger.info(
        "scene: the background models of %s learned again from %s",
        ", ".join(dataset.rig[c].name for c in cameras),
        what,
    )
    return dataclasses.replace(model, states=tuple(states))


def foreground_at(
    dataset: Dataset, t: int, config: ForegroundConfig | None = None
) -> tuple[FrameSet, ForegroundResult]:
    """The frames of time ``t`` and their foreground as the online system computes it (for
    the offline commands and the benchmarks)."""
    tracker = dataset_scene_at(dataset, t, config)
    with dataset.open_frames() as source:
        frames = source.read(t)
    return frames, tracker.segment(frames)


class Engine(Protocol):
    """What an engine offers the session: where the two roles run is its business."""

    name: str

    def plan(self, time_index: int) -> TaskPlan:
        """The controller's configuration for the next task."""
        ...

    def pending_updates(self, time_index: int) -> list[int]:
        """Time indices whose frames the scheduled background updates need before the task
        of ``time_index`` (the session reads them and passes them to :meth:`run_task`)."""
        ...

    def learn_updates(self, updates: Sequence[FrameSet]) -> float:
        """Apply scheduled background updates between two tasks (``FrontEnd.learn_updates``);
        returns the seconds spent."""
        ...

    def run_task(
        self,
        frames: FrameSet,
        plan: TaskPlan,
        task: int,
        defects: Mapping[str, str],
        updates: Sequence[FrameSet] = (),
    ) -> TaskOutput:
        """Run one task; never raises for a failed task (its record says why)."""
        ...

    def state(self) -> FrontEndState:
        """The front-end's part of the run state, for ``state.json``."""
        ...

    def status(self) -> dict[str, Any]:
        """Health and counters (backgrounds received, outages, restarts)."""
        ...

    def inject_backend_fault(self, kind: str, seconds: float = 0.0) -> None:
        """Drills: ``stall`` / ``crash`` (both engines), ``kill`` (Ray: the actor's process)."""
        ...

    def inject_frontend_fault(self, kind: str) -> None:
        """Drill: ``hang`` (the next task loops for ever; ``FrontEnd.inject_fault``)."""
        ...

    def check_calibration(self, since: int, cameras: Sequence[str]) -> None:
        """Ask the back-end to check the calibration at once, on the first task's frames
        from time index ``since`` on and only on frame sets from then on (``cameras``' views
        moved then: ``BackEnd.check_calibration``); fire and forget."""
        ...

    def scene_model(self) -> SceneModel | None:
        """The front-end's background models as they are now, between two tasks (None:
        none), with the clip frame set the engine started from: what a run that goes on
        starts from instead of learning them again."""
        ...

    def close(self) -> None: ...


class BackendClient(Protocol):
    """The front-end's calls to a back-end, wherever it runs (None replies: late or lost)."""

    def submit(self, work: TaskWork) -> None: ...
    def golden(self, time_index: int, timeout: float) -> GoldenReply | None: ...


def restart_reason(status: Mapping[str, Any] | None, watchdog_s: float) -> str | None:
    """Why a back-end must be replaced (dead, or stuck on one task past the watchdog), or
    None when it is fine."""
    if status is None:
        return "does not answer"
    if not status.get("alive"):
        return f"died ({status.get('error')})"
    if float(status.get("task_age_s", 0.0)) > watchdog_s:
        return f"stuck on one task for {status['task_age_s']:.0f} s (watchdog {watchdog_s:.0f} s)"
    return None


class BackendLink:
    """Health bookkeeping of the front-end's view of the back-end (engine-agnostic).

    ``ping()`` returns the back-end's status dict, or None when it does not answer.
    """

    def __init__(self, ping: Callable[[], dict[str, Any] | None], retry_s: float) -> None:
        self._ping = ping
        self.retry_s = retry_s
        self.lost = False
        self.lost_reason = ""
        self._next_check = 0.0
        self.outages = 0

    def usable(self) -> bool:
        """Whether to submit the next task to the back-end. A healthy back-end is pinged at
        most every ``retry_s`` too (nothing waits on it for the task itself, so a dead one
        would otherwise go unnoticed and the background stop advancing); a lost one is
        checked as often whether it is back."""
        now = time.monotonic()
        if now < self._next_check:
            return not self.lost
        self._next_check = now + self.retry_s
        status = self._ping()
        if not self.lost:
            if status is None:  # dead or stuck: the engine is bringing up a new one
                self.mark_lost("does not answer its health check")
                return False
            return True
        if (
            status is not None
            and status.get("alive")
            and not status.get("busy")
            and not status.get("stalled")
        ):
            logger.warning("back-end is back (was lost: %s)", self.lost_reason)
            self.lost = False
            self.lost_reason = ""
            return True
        return False

    def mark_lost(self, reason: str) -> None:
        if not self.lost:
            logger.warning("back-end lost: %s; tasks run degraded until it returns", reason)
            self.outages += 1
        self.lost = True
        self.lost_reason = reason
        self._next_check = time.monotonic() + self.retry_s


def start_frontend(
    dataset: Dataset,
    config: RuntimeConfig,
    controller: BisectionController | FixedController,
    scene: SceneModel,
    restored: FrontEndState | None,
    background: PointCloud | None,
) -> FrontEnd:
    """The front-end role in this process, its kernels loaded off the clock (the first task
    must not pay for it), restored from a run state when resuming."""
    warm_up()
    return FrontEnd(
        dataset.rig,
        config,
        controller,
        scene.tracker(dataset.rig, config.foreground),
        restored=restored,
        background=background,
    )


def run_frontend_task(
    frontend: FrontEnd,
    link: BackendLink,
    backend: BackendClient | None,
    frames: FrameSet,
    plan: TaskPlan,
    task: int,
    defects: Mapping[str, str],
    updates: Sequence[FrameSet] = (),
) -> TaskOutput:
    """One task on the front-end with the back-end's help while it is usable (the same on
    every engine: only ``backend``'s transport differs)."""
    t = frames.time_index
    use = backend is not None and not too_few_cameras(frames) and link.usable()
    submitted = False

    def submit(work: TaskWork) -> None:
        nonlocal use, submitted
        if not use or backend is None:
            return
        try:
            backend.submit(work)
            submitted = True
        except Exception as exc:  # the transport failed: a lost back-end
            link.mark_lost(f"submit failed: {type(exc).__name__}")
            use = False

    def golden(timeout: float) -> GoldenReply | None:
        if not submitted or backend is None:
            return None
        reply = backend.golden(t, timeout)
        if reply is None:
            link.mark_lost(f"no golden reference for time {t} within {timeout:.1f} s")
        return reply

    out = frontend.run_task(
        frames, plan, submit, golden, task=task, defects=defects, updates=updates
    )
    out.metrics.submitted = submitted
    if not use and out.metrics.degraded:
        out.metrics.degraded_reason = f"back-end lost ({link.lost_reason})"
    return out


class EmbeddedEngine:
    """Both roles in this process: the front-end runs on the caller's thread, the back-end on
    its own threads (background rebuilds at a lower OS priority). No set-up needed.

    A back-end that crashes, or is stuck on one task past the watchdog, is replaced by a new
    one (as a node that rejoins would be) with the next epoch and the newest model snapshot,
    once the front-end's next health check finds it.
    """

    name = "embedded"

    def __init__(
        self,
        dataset: Dataset,
        config: RuntimeConfig,
        controller: BisectionController | FixedController,
        scene: SceneModel,
        *,
        restored: FrontEndState | None = None,
        background: PointCloud | None = None,
    ) -> None:
        self.dataset = dataset
        self.config = config
        self.scene = scene
        self.frontend = start_frontend(dataset, config, controller, scene, restored, background)
        self.backend = self._new_backend()
        self.link = BackendLink(self._ping, config.backend_retry_s)
        self.backend_restarts = 0

    def _new_backend(self) -> BackEnd:
        start = self.frontend.register_backend()
        return BackEnd(
            self.dataset.rig,
            self.config,
            push=self.frontend.push_background,
            initial_background=self.scene.initial_background if start.first else None,
            epoch=start.epoch,
        ).start()

    def _ping(self) -> dict[str, Any] | None:
        status = self.backend.ping()
        reason = restart_reason(status, self.config.watchdog_s)
        if reason is not None:
            # The node is gone or stuck: bring up a fresh one (from the newest snapshot).
            logger.warning("embedded back-end %s: restarting it", reason)
            self.backend.stop(timeout=1.0)
            stuck = self.backend.task_thread
            if stuck is not None and stuck.is_alive():
                # Stuck in its task: stopped (its rebuild thread ends after its rebuild).
                self.frontend.abandoned.abandon(
                    stuck, "the embedded back-end's stuck task", grace_s=0.0
                )
            self.backend = self._new_backend()
            self.backend_restarts += 1
            return None
        return status

    def plan(self, time_index: int) -> TaskPlan:
        return self.frontend.next_plan(time_index)

    def pending_updates(self, time_index: int) -> list[int]:
        return self.frontend.pending_updates(time_index)

    def learn_updates(self, updates: Sequence[FrameSet]) -> float:
        return self.frontend.learn_updates(updates)

    def run_task(
        self,
        frames: FrameSet,
        plan: TaskPlan,
        task: int,
        defects: Mapping[str, str],
        updates: Sequence[FrameSet] = (),
    ) -> TaskOutput:
        client = _LocalBackend(self.backend)
        return run_frontend_task(
            self.frontend, self.link, client, frames, plan, task, defects, updates
        )

    def state(self) -> FrontEndState:
        return self.frontend.state()

    def status(self) -> dict[str, Any]:
        backend = self.backend.ping()
        return {
            "engine": self.name,
            "backgrounds_received": self.frontend.backgrounds_received,
            "snapshots_received": self.frontend.snapshots_received,
            "bg_version": self.frontend.bg_version.to_list(),
            "backend_outages": self.link.outages,
            "backend_restarts": self.backend_restarts,
            "abandoned_threads": self.frontend.abandoned.running()
            + list(backend.get("abandoned_threads", [])),
            "backend": backend,
        }

    def inject_backend_fault(self, kind: str, seconds: float = 0.0) -> None:
        self.backend.inject_fault(kind, seconds)

    def inject_frontend_fault(self, kind: str) -> None:
        self.frontend.inject_fault(kind)

    def check_calibration(self, since: int, cameras: Sequence[str]) -> None:
        self.backend.check_calibration(since, cameras)

    def scene_model(self) -> SceneModel | None:
        model = self.frontend.scene_model()
        if model is None:
            return None
        return dataclasses.replace(model, initial_background=self.scene.initial_background)

    def close(self) -> None:
        self.backend.stop(timeout=5.0)


class _LocalBackend:
    """:class:`BackendClient` of a back-end in this process."""

    def __init__(self, backend: BackEnd) -> None:
        self._backend = backend

    def submit(self, work: TaskWork) -> None:
        self._backend.submit(work)

    def golden(self, time_index: int, timeout: float) -> GoldenReply | None:
        return self._backend.golden(time_index, timeout)
