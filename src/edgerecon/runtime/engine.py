"""Engines: where the two roles run. The embedded engine (default) runs both in this process;
the Ray engine (:mod:`edgerecon.runtime.ray_engine`) runs each as an actor on its own node.

Both drive the same :class:`FrontEnd` / :class:`BackEnd` classes through the same
:class:`BackendLink` health logic, so a task gives the same result on either engine.

Back-end health: after a task whose masks did not arrive in time, the back-end is *lost*:
the front-end neither submits to it nor waits for it (tasks run degraded: local masks, no
online estimate) and checks every ``backend_retry_s`` seconds whether it answers again and is
idle; then it is used again from the next task on.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from edgerecon import progress
from edgerecon.io.dataset import Dataset
from edgerecon.optimize.controller import BisectionController
from edgerecon.pipeline import warm_up
from edgerecon.runtime.backend import BackEnd
from edgerecon.runtime.config import RuntimeConfig
from edgerecon.runtime.frontend import FixedController, FrontEnd, TaskOutput
from edgerecon.runtime.messages import BackgroundUpdate, GoldenReply, MasksReply, TaskPlan
from edgerecon.scene.background import BackgroundState
from edgerecon.scene.foreground import ForegroundConfig, RigForeground
from edgerecon.types import FrameSet

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


@progress.phase("learn the background model")
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


class Controller(Protocol):
    def next_config(self) -> Any: ...
    def observe(self, time_s: float, quality: float | None = None) -> None: ...
    def to_dict(self) -> dict[str, Any]: ...


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


class EmbeddedEngine:
    """Both roles in this process: the front-end runs on the caller's thread, the back-end on
    its own threads (background rebuilds at a lower OS priority). No set-up needed.

    A back-end that crashes is restarted by the engine (as a node that rejoins would be) once
    the front-end's next health check finds it dead.
    """

    name = "embedded"

    def __init__(
        self,
        dataset: Dataset,
        config: RuntimeConfig,
        controller: BisectionController | FixedController,
        scene: SceneModel,
    ) -> None:
        self.dataset = dataset
        self.config = config
        self.scene = scene
        warm_up()  # off the clock: the first task must not pay for loading the kernels
        self.frontend = FrontEnd(dataset.rig, config, controller, model_states=scene.states)
        self.backend = self._new_backend(scene.initial_background)
        self.link = BackendLink(self._ping, config.backend_retry_s)
        self.backend_restarts = 0

    def _new_backend(self, initial_background: FrameSet | None) -> BackEnd:
        fg = RigForeground.from_states(self.dataset.rig, self.scene.states, self.config.foreground)
        return BackEnd(
            self.dataset.rig,
            self.config,
            fg,
            push=self.frontend.push_background,
            initial_background=initial_background,
        ).start()

    def _ping(self) -> dict[str, Any] | None:
        status = self.backend.ping()
        if not status["alive"]:
            # The node is gone: bring up a fresh one (it re-learns from the model snapshot).
            logger.warning("embedded back-end died (%s): restarting it", status.get("error"))
            self.backend.stop(timeout=1.0)
            self.backend = self._new_backend(None)
            self.backend_restarts += 1
            return None
        return status

    def plan(self, time_index: int) -> TaskPlan:
        return self.frontend.next_plan(time_index)

    def run_task(self, frames: FrameSet, plan: TaskPlan, task: int) -> TaskOutput:
        t = frames.time_index
        backend = self.backend if self.link.usable() else None
        if backend is not None:
            backend.submit(frames)

        def masks(timeout: float) -> MasksReply | None:
            if backend is None:
                return None
            reply = backend.masks(t, timeout)
            if reply is None:
                self.link.mark_lost(f"no masks for time {t} within {timeout:.1f} s")
            return reply

        def golden(timeout: float) -> GoldenReply | None:
            return None if backend is None else backend.golden(t, timeout)

        out = self.frontend.process(frames, plan, masks, golden, task=task)
        if backend is None:
            out.metrics.degraded_reason = f"back-end lost ({self.link.lost_reason})"
        return out

    def controller_state(self) -> dict[str, Any]:
        return self.frontend.controller.to_dict()

    def push_background(self, update: BackgroundUpdate) -> None:
        self.frontend.push_background(update)

    def status(self) -> dict[str, Any]:
        return {
            "engine": self.name,
            "backgrounds_received": self.frontend.backgrounds_received,
            "bg_version": self.frontend.bg_version,
            "backend_outages": self.link.outages,
            "backend_restarts": self.backend_restarts,
            "backend": self.backend.ping(),
        }

    def inject_backend_fault(self, kind: str, seconds: float = 0.0) -> None:
        self.backend.inject_fault(kind, seconds)

    def close(self) -> None:
        self.backend.stop()
