"""Engines: where the two roles run. The embedded engine (default) runs both in this process;
the Ray engine (:mod:`edgerecon.runtime.ray_engine`) runs each as an actor on its own node.

Both drive the same :class:`FrontEnd` / :class:`BackEnd` classes through the same
:class:`BackendLink` health logic and :func:`run_frontend_task`, so a task gives the same
result on either engine; :class:`Engine` is what the session may call.

Back-end health: after a task whose masks did not arrive in time, the back-end is *lost*:
the front-end neither submits to it nor waits for it (tasks run degraded: local masks, no
online estimate) and checks every ``backend_retry_s`` seconds whether it answers again and is
idle; then it is used again from the next task on.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from edgerecon.io.dataset import Dataset
from edgerecon.optimize.controller import BisectionController
from edgerecon.pipeline import warm_up
from edgerecon.quality.frames import frame_defects, without_defective
from edgerecon.runtime.backend import BackEnd
from edgerecon.runtime.config import RuntimeConfig
from edgerecon.runtime.frontend import (
    FixedController,
    FrontEnd,
    FrontEndState,
    TaskOutput,
    too_few_cameras,
)
from edgerecon.runtime.messages import GoldenReply, MasksReply, TaskPlan
from edgerecon.scene.background import BackgroundState
from edgerecon.scene.foreground import ForegroundConfig, ForegroundResult, RigForeground
from edgerecon.types import FrameSet, PointCloud

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True, eq=False)
class SceneModel:
    """What both roles start from: the background models and, when the dataset has a clip of
    the empty scene, one frame set of it for the first background reconstruction."""

    states: tuple[BackgroundState, ...]
    initial_background: FrameSet | None
    learned_from: str
    """"background clip" or "first N frames"."""
    seconds: float


def learn_scene_model(
    dataset: Dataset,
    foreground: ForegroundConfig | None = None,
    warmup_frames: int = 30,
) -> SceneModel:
    """Learn the per-camera background models from the dataset's background clip, or from the
    first ``warmup_frames`` frames of the stream (the per-pixel median ignores actors that
    move)."""
    t0 = time.perf_counter()
    source = dataset.open_background()
    if source is not None:
        with source:
            framesets = list(source.iter_frames())
        fg = RigForeground.learn_from_framesets(dataset.rig, framesets, foreground)
        first = framesets[len(framesets) // 2]
        initial = FrameSet(time_index=-1, images=first.images)
        what = "background clip"
    else:
        with dataset.open_frames() as frames:
            stop = min(frames.num_frames, warmup_frames)
            framesets = list(frames.iter_frames(0, stop))
        fg = RigForeground.learn_from_framesets(dataset.rig, framesets, foreground)
        initial = None
        what = f"first {len(framesets)} frames"
    return SceneModel(
        states=tuple(fg.states()),
        initial_background=initial,
        learned_from=what,
        seconds=time.perf_counter() - t0,
    )


def foreground_at(
    dataset: Dataset,
    t: int,
    scene: SceneModel | None = None,
    *,
    adapt_frames: int = 5,
    config: ForegroundConfig | None = None,
) -> tuple[FrameSet, ForegroundResult]:
    """The frames of time ``t`` and their foreground, for the offline commands and the
    benchmarks: the scene model (learned here when not given) first adapts on the
    ``adapt_frames`` frames before ``t``, as it would have online."""
    scene = scene or learn_scene_model(dataset, config)
    model = RigForeground.from_states(dataset.rig, scene.states, config)
    with dataset.open_frames() as source:
        for k in range(max(0, t - adapt_frames), t):
            model.segment(source.read(k))
        frames = source.read(t)
    return frames, model.segment(frames)


def replay_scene_model(
    dataset: Dataset,
    scene: SceneModel,
    time_indices: Sequence[int],
    config: RuntimeConfig,
) -> SceneModel:
    """``scene`` after its background models learned from the frames of ``time_indices`` in
    order, as the back-end's did while serving those tasks (``--resume``: the resumed
    back-end segments the next frame with the models an uninterrupted run would have).
    Unusable cameras are left out as the session leaves them out."""
    if not time_indices:
        return scene
    t0 = time.perf_counter()
    model = RigForeground.from_states(dataset.rig, scene.states, config.foreground)
    with dataset.open_frames(missing="skip_camera") as source:
        framesets = (
            without_defective(fs, frame_defects(fs, config.frame_check))
            for fs in (source.read(t) for t in time_indices)
        )
        n = model.warm_up(framesets)
    logger.info("background models replayed %d frames in %.1f s", n, time.perf_counter() - t0)
    return dataclasses.replace(
        scene,
        states=tuple(model.states()),
        learned_from=f"{scene.learned_from} + {n} frames replayed",
        seconds=scene.seconds + time.perf_counter() - t0,
    )


class Engine(Protocol):
    """What an engine offers the session: where the two roles run is its business."""

    name: str

    def plan(self, time_index: int) -> TaskPlan:
        """The controller's configuration for the next task."""
        ...

    def run_task(
        self, frames: FrameSet, plan: TaskPlan, task: int, defects: Mapping[str, str]
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

    def close(self) -> None: ...


class BackendClient(Protocol):
    """The front-end's calls to a back-end, wherever it runs (None replies: late or lost)."""

    def submit(self, frames: FrameSet) -> None: ...
    def masks(self, time_index: int, timeout: float) -> MasksReply | None: ...
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
        """Whether to submit the next task to the back-end (checks a lost back-end at most
        every ``retry_s``)."""
        if not self.lost:
            return True
        now = time.monotonic()
        if now < self._next_check:
            return False
        self._next_check = now + self.retry_s
        status = self._ping()
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
        model_states=scene.states,
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
) -> TaskOutput:
    """One task on the front-end with the back-end's help while it is usable (the same on
    every engine: only ``backend``'s transport differs)."""
    t = frames.time_index
    use = backend is not None and not too_few_cameras(frames) and link.usable()
    if use and backend is not None:
        try:
            backend.submit(frames)
        except Exception as exc:  # the transport failed: a lost back-end
            link.mark_lost(f"submit failed: {type(exc).__name__}")
            use = False

    def masks(timeout: float) -> MasksReply | None:
        if not use or backend is None:
            return None
        reply = backend.masks(t, timeout)
        if reply is None:
            link.mark_lost(f"no masks for time {t} within {timeout:.1f} s")
        return reply

    def golden(timeout: float) -> GoldenReply | None:
        return backend.golden(t, timeout) if use and backend is not None else None

    out = frontend.run_task(frames, plan, masks, golden, task=task, defects=defects)
    out.metrics.submitted = use
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
        states = start.model_states or self.scene.states
        fg = RigForeground.from_states(self.dataset.rig, states, self.config.foreground)
        return BackEnd(
            self.dataset.rig,
            self.config,
            fg,
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
            self.backend = self._new_backend()
            self.backend_restarts += 1
            return None
        return status

    def plan(self, time_index: int) -> TaskPlan:
        return self.frontend.next_plan(time_index)

    def run_task(
        self, frames: FrameSet, plan: TaskPlan, task: int, defects: Mapping[str, str]
    ) -> TaskOutput:
        backend = self.backend
        client = _LocalBackend(backend)
        return run_frontend_task(self.frontend, self.link, client, frames, plan, task, defects)

    def state(self) -> FrontEndState:
        return self.frontend.state()

    def status(self) -> dict[str, Any]:
        return {
            "engine": self.name,
            "backgrounds_received": self.frontend.backgrounds_received,
            "bg_version": self.frontend.bg_version.to_list(),
            "backend_outages": self.link.outages,
            "backend_restarts": self.backend_restarts,
            "backend": self.backend.ping(),
        }

    def inject_backend_fault(self, kind: str, seconds: float = 0.0) -> None:
        self.backend.inject_fault(kind, seconds)

    def close(self) -> None:
        self.backend.stop(timeout=5.0)


class _LocalBackend:
    """:class:`BackendClient` of a back-end in this process."""

    def __init__(self, backend: BackEnd) -> None:
        self._backend = backend

    def submit(self, frames: FrameSet) -> None:
        self._backend.submit(frames)

    def masks(self, time_index: int, timeout: float) -> MasksReply | None:
        return self._backend.masks(time_index, timeout)

    def golden(self, time_index: int, timeout: float) -> GoldenReply | None:
        return self._backend.golden(time_index, timeout)
