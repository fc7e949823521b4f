"""The front-end role: each task's critical path, the online evaluation, the optimizer.

Per task the front-end runs the one composition of a task (:func:`pipeline.reconstruct_task`)
with the optimizer's configuration (r, pi(N')), the foreground it computes itself (the scene
stage: :meth:`FrontEnd.obtain_foreground`, a few tens of milliseconds at the working
resolution; the front-end owns the background models and applies their scheduled updates,
see :mod:`edgerecon.scene.stream`: those whose frames have arrived by the end of a task
between two tasks, :meth:`FrontEnd.learn_updates`, the rest before the next task's scene
stage) and the newest background it holds. Once the foreground is
known it hands the frames and masks to the back-end (golden reference, background rebuilds).
The critical path ends when the merged cloud is ready; then the front-end estimates the
task's quality (by default from its own dense foreground and the masks,
:func:`~edgerecon.quality.online.silhouette_quality`; or against the back-end's golden
reference, the paper's estimate) and feeds (T, Q) to the controller.

The front-end owns the run's state that must survive a restart (:class:`FrontEndState`): the
controller, where pi(N') came from, the background version it holds and the back-end epochs
it handed out. The background models need no saving: they are a function of the stream
(:mod:`edgerecon.scene.stream`) and a resumed run rebuilds them.

Every task runs under a watchdog (:meth:`FrontEnd.run_task`): an exception in any stage, or a
task still running after ``RuntimeConfig.watchdog_s``, gives a failed record, never a dead run.

Plain Python, usable without a cluster; the Ray engine wraps it in an actor.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from edgerecon.config import MIN_CAMERAS, ReconstructionConfig
from edgerecon.geometry.camera import Rig
from edgerecon.optimize.controller import BisectionController
from edgerecon.optimize.selection import camera_mapping, visibility_from_points
from edgerecon.optimize.workload import WorkloadScaler, mask_area
from edgerecon.pipeline import (
    SplitPipelineConfig,
    TaskCancelled,
    num_objects,
    prepare_task_views,
    reconstruct_task,
    task_sparse,
)
from edgerecon.quality.online import OnlineQualityConfig, online_quality, silhouette_quality
from edgerecon.runtime.config import RuntimeConfig
from edgerecon.runtime.interrupt import AbandonedThreads, Runner
from edgerecon.runtime.messages import (
    BackgroundUpdate,
    BgVersion,
    GoldenReply,
    TaskMetrics,
    TaskPlan,
    TaskWork,
    describe_exception,
)
from edgerecon.scene.foreground import ForegroundResult
from edgerecon.scene.still import StillCache, StillPlan, StillSnapshot
from edgerecon.scene.stream import SceneTracker
from edgerecon.types import FrameSet, PointCloud, StageTimings

if TYPE_CHECKING:
    from edgerecon.runtime.engine import SceneModel

logger = logging.getLogger(__name__)

#: Hands a task's work to the back-end (never raises: a transport failure marks it lost).
SubmitFn = Callable[[TaskWork], None]
#: Waits for a reply: ``provider(timeout_s)`` returns the reply or None (late or unavailable).
GoldenProvider = Callable[[float], GoldenReply | None]

#: Fewer sparse points than this and camera selection also uses the dense foreground points.
_MIN_SELECTION_POINTS = 200


@dataclass(frozen=True, kw_only=True, eq=False)
class TaskOutput:
    """What a task publishes: its metrics and, unless it failed, its clouds. The merged
    cloud is ``scene.merge.compose(foreground, <the background of the task's version>,
    bg_version=..., dropped=bg_dropped)``; the background travels once per version, not with
    every task (a million points on an HD rig)."""

    metrics: TaskMetrics
    foreground: PointCloud | None
    bg_dropped: NDArray[np.int64] | None = None
    """Indices of the task's background points the foreground overrides."""
    background: PointCloud | None = None
    """The background the task merged with, when no earlier task published that version
    (the session saves each version once, and the newest for ``--resume``)."""


@dataclass(frozen=True, kw_only=True)
class FrontEndState:
    """The front-end's part of the run state (JSON-able; saved after every task)."""

    controller: dict[str, Any]
    pi_source: dict[str, Any] | None = None
    """Where pi(N') came from: ``{"task", "time_index", "rows"}`` of the golden task whose
    visibility it was computed from (None: not computed yet, or a fixed configuration)."""
    bg_version: BgVersion = field(default_factory=BgVersion)
    backend_epoch: int = 0
    """The last back-end epoch handed out."""
    backgrounds_received: int = 0
    workload_history: tuple[tuple[float, ...], ...] = ()
    """The recent tasks' (mask area, seconds before the MVS, r, MVS seconds)
    (``optimize.workload``: the reference of the next task's scale)."""

    def to_dict(self) -> dict[str, Any]:
        return {
            "controller": self.controller,
            "pi_source": self.pi_source,
            "bg_version": self.bg_version.to_list(),
            "backend_epoch": self.backend_epoch,
            "backgrounds_received": self.backgrounds_received,
            "workload_history": [list(x) for x in self.workload_history],
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> FrontEndState:
        return cls(
            controller=dict(d["controller"]),
            pi_source=d.get("pi_source"),
            bg_version=BgVersion.from_list(d.get("bg_version", 0)),
            backend_epoch=int(d.get("backend_epoch", 0)),
            backgrounds_received=int(d.get("backgrounds_received", 0)),
            workload_history=tuple(
                tuple(float(x) for x in entry) for entry in d.get("workload_history", ())
            ),
        )


@dataclass(frozen=True, kw_only=True, eq=False)
class BackendStart:
    """What a (re)starting back-end gets from the front-end (:meth:`FrontEnd.register_backend`)."""

    epoch: int
    first: bool
    """The first back-end of this front-end (it may start from the empty-scene clip)."""


@dataclass
class TaskGuard:
    """The watchdog's handle on a running task."""

    cancel: threading.Event = field(default_factory=threading.Event)
    committed: bool = False
    """The task fed the controller: it is going to finish."""


@dataclass(frozen=True, kw_only=True, eq=False)
class _Job:
    """One task's inputs on the front-end."""

    frames: FrameSet
    plan: TaskPlan
    submit: SubmitFn
    golden: GoldenProvider
    task: int
    updates: tuple[FrameSet, ...] = ()
    """Frames of the scheduled background updates due before this task (the session reads
    them; ``FrontEnd.pending_updates``)."""


def _loop_for_ever() -> None:
    """The ``hang`` drill: Python code that never returns."""
    n = 0
    while True:
        n += 1


class FixedController:
    """A controller that always returns one configuration (for baselines, e.g. the golden
    pipeline every task, and for comparing engines task by task)."""

    def __init__(self, scale: float, camera_ids: tuple[int, ...]) -> None:
        self.scale = float(scale)
        self.ids = tuple(camera_ids)
        self.search_steps = 0
        self.total_search_steps = 0

    def next_config(self) -> TaskPlan:
        return TaskPlan(time_index=-1, scale=self.scale, camera_ids=self.ids, phase="fixed")

    def observe(self, time_s: float, quality: float | None = None) -> None:
        del time_s, quality

    def set_camera_mapping(self, mapping: Any, restart: bool = False) -> None:
        del mapping, restart

    def set_deadline(self, deadline_s: float) -> None:
        del deadline_s

    def to_dict(self) -> dict[str, Any]:
        return {"format": "edgerecon-fixed", "scale": self.scale, "camera_ids": list(self.ids)}


def too_few_cameras(frames: FrameSet) -> bool:
    """Whether ``frames`` has fewer usable cameras than a task needs."""
    return len(frames.available) < MIN_CAMERAS


class FrontEnd:
    """Front-end node role (see module docstring)."""

    def __init__(
        self,
        rig: Rig,
        config: RuntimeConfig,
        controller: BisectionController | FixedController,
        scene: SceneTracker | None = None,
        *,
        restored: FrontEndState | None = None,
        background: PointCloud | None = None,
    ) -> None:
        self.rig = rig
        self.config = config
        self.controller = controller
        self.scene = scene
        self._scene_lock = threading.Lock()
        # Who holds the background models now, and a copy of them after their last update:
        # a stage that hangs holding them is abandoned with them (``_restore_scene``).
        self._scene_holder: threading.Thread | None = None
        self._scene_saved = None if scene is None else scene.snapshot()
        self._lock = threading.Lock()
        self._commit = threading.Lock()
        self.abandoned = AbandonedThreads()
        """The threads of abandoned work (a task past the watchdog, updates that hung)."""
        # The tasks' thread and the updates' between tasks, kept from call to call.
        self._tasks = Runner("task")
        self._updates = Runner("scene-updates")
        self._drill: str | None = None
        self._background = PointCloud.empty() if background is None else background
        self._bg_version = BgVersion()
        self._bg_published = BgVersion()
        self._backend_epoch = 0
        self._backends_registered = 0
        self.pi_source: dict[str, Any] | None = None
        self.backgrounds_received = 0
        self.workload = (
            None
            if config.workload is None
            else WorkloadScaler(
                config.workload, () if restored is None else restored.workload_history
            )
        )
        if restored is not None:
            self.pi_source = restored.pi_source
            self._backend_epoch = restored.backend_epoch
            self.backgrounds_received = restored.backgrounds_received
            if background is not None:
                self._bg_version = self._bg_published = restored.bg_version
        self.eval_threshold = config.eval_threshold_for(rig)
        self.still = None if config.still is None else StillCache(config.still)
        """The back-end's newest snapshot of the foreground (``scene.still``)."""
        self._still_failed = False

    # ------------------------------------------------------------------ run state
    def state(self) -> FrontEndState:
        """The state to save after a task. Its background version is the newest one a task
        published (the one ``background.ply`` holds), not a newer one received since: a
        resumed run restores that file with that version."""
        with self._lock:
            return FrontEndState(
                controller=self.controller.to_dict(),
                pi_source=self.pi_source,
                bg_version=self._bg_published,
                backend_epoch=self._backend_epoch,
                backgrounds_received=self.backgrounds_received,
                workload_history=() if self.workload is None else self.workload.history,
            )

    def register_backend(self) -> BackendStart:
        """A back-end (re)starts: its epoch (the next one), and whether it is the first."""
        with self._lock:
            self._backend_epoch += 1
            self._backends_registered += 1
            return BackendStart(epoch=self._backend_epoch, first=self._backends_registered == 1)

    @property
    def snapshots_received(self) -> int:
        """Snapshots of the still foreground taken (``scene.still``; 0 when it is off)."""
        return 0 if self.still is None else self.still.snapshots

    # ------------------------------------------------------------------ background pushes
    def push_background(self, update: BackgroundUpdate | StillSnapshot) -> BgVersion:
        """Take a newer background (older or duplicate versions are ignored), or the
        back-end's newest snapshot of the still foreground (``scene.still``). Returns the
        background version now held."""
        if isinstance(update, StillSnapshot):
            if self.still is not None:
                self.still.set_snapshot(update)
            return self.bg_version
        with self._lock:
            newer = update.version > self._bg_version
            if newer:
                self._background = update.cloud
                self._bg_version = update.version
                self.backgrounds_received += 1
            else:
                logger.info(
                    "front-end: ignoring background %s (holding %s)",
                    update.version,
                    self._bg_version,
                )
            held = self._bg_version
        return held

    @property
    def bg_version(self) -> BgVersion:
        return self._bg_version

    def background(self) -> tuple[PointCloud, BgVersion]:
        with self._lock:
            return self._background, self._bg_version

    def _background_to_publish(self, cloud: PointCloud, version: BgVersion) -> PointCloud | None:
        """``cloud`` (the background of ``version``, which a task merged with) unless that
        version was published already. The version a task used, not the newest held: every
        version a task refers to is then published (a newer one may arrive during a task)."""
        with self._lock:
            if version == self._bg_published:
                return None
            self._bg_published = version
            return cloud

    # ------------------------------------------------------------------ planning
    def next_plan(self, time_index: int) -> TaskPlan:
        cfg = self.controller.next_config()
        ids = tuple(int(i) for i in cfg.camera_ids)
        return TaskPlan(
            time_index=time_index, scale=float(cfg.scale), camera_ids=ids, phase=str(cfg.phase)
        )

    # ------------------------------------------------------------------ the scene stage
    def _tracker(self) -> SceneTracker:
        if self.scene is None:
            raise RuntimeError("this front-end was built without background models")
        return self.scene

    @contextlib.contextmanager
    def _holding_scene(self) -> Iterator[SceneTracker]:
        """The background models, held by this thread (one holder at a time)."""
        lock = self._scene_lock
        with lock:
            self._scene_holder = threading.current_thread()
            try:
                yield self._tracker()
            finally:
                if self._scene_lock is lock:  # not replaced since (``_restore_scene``)
                    self._scene_holder = None

    def _save_scene(self, scene: SceneTracker) -> None:
        """Keep a copy of the models after an update (under ``_holding_scene``), if they
        changed since the last copy."""
        saved = self._scene_saved
        if saved is None or (saved.next_update, saved.updates, saved.static_from) != (
            scene.next_update,
            scene.updates,
            scene.static_from,
        ):
            self._scene_saved = scene.snapshot()

    def _restore_scene(self, holder: threading.Thread, what: str) -> None:
        """``holder`` was abandoned (watchdog): if it holds the background models, they go
        with it (it may still change them) and the front-end goes on with the copy saved
        after their last update; the session then applies again the scheduled updates since
        (``pending_updates``), so later masks are those the models would have given."""
        saved = self._scene_saved
        if saved is None or self._scene_holder is not holder:
            return
        self.scene = saved.snapshot()
        self._scene_lock = threading.Lock()
        self._scene_holder = None
        logger.warning(
            "%s held the background models: going on with their copy (next update at time "
            "%d; the updates since are applied again)",
            what,
            saved.next_update,
        )

    def scene_model(self) -> SceneModel | None:
        """A copy of the background models as they are now (``SceneModel``, without a clip
        frame set; None: none), between two tasks: what a run that goes on with another rig
        starts from (``run --adopt-repairs``)."""
        from edgerecon.runtime.engine import SceneModel

        if self.scene is None:
            return None
        with self._holding_scene() as scene:
            copy = scene.snapshot()
        return SceneModel.of_tracker(copy)

    def pending_updates(self, time_index: int) -> list[int]:
        """Time indices of the scheduled background updates still to apply before the task
        of ``time_index`` (the session reads those frames for :meth:`run_task`)."""
        return [] if self.scene is None else self.scene.pending(time_index)

    @staticmethod
    def _learn_update(
        scene: SceneTracker,
        frames: FrameSet,
        result: ForegroundResult | None = None,
        *,
        defer_static: bool = True,
    ) -> None:
        """One scheduled background update (``SceneTracker.learn``); one that raises is
        skipped with a warning (the schedule moves on, ``SceneTracker.skip``): a frame set
        the models cannot learn must not fail every later task that would retry it, nor
        the task whose cloud is already out."""
        try:
            scene.learn(frames, result, defer_static=defer_static)
        except Exception as exc:
            logger.warning(
                "background update at time %d failed (%s): skipped, the models miss it",
                frames.time_index,
                describe_exception(exc),
            )
            scene.skip(frames.time_index)

    def learn_updates(self, updates: Sequence[FrameSet]) -> float:
        """Apply scheduled background updates between two tasks, off both critical paths:
        the session passes the frames of the updates due before the next task that have
        arrived by the end of this one (``SceneTracker.learn``, then the static scenes they
        make due). The next task's masks are those it would get with the updates on its own
        path (the models at its time index are the same). Bounded by the watchdog; an update
        that raises is skipped (``_learn_update``); one that hangs is abandoned with the
        models, and the front-end goes on with their copy (``_restore_scene``). Returns the
        seconds spent."""
        if not updates or self.scene is None:
            return 0.0

        def work() -> float:
            t0 = time.perf_counter()
            with self._holding_scene() as scene:
                for u in updates:
                    self._learn_update(scene, u)
                scene.settle()
                self._save_scene(scene)
            return time.perf_counter() - t0

        limit = self.config.watchdog_s
        start = time.perf_counter()
        run = self._updates.call(work, limit)
        if run.timed_out:
            logger.error("background updates between tasks: still running after %.1f s", limit)
            self._restore_scene(run.thread, "background updates abandoned between tasks")
            self.abandoned.abandon(run.thread, "background updates abandoned between tasks")
            return time.perf_counter() - start
        if run.error is not None:  # the next task retries it
            logger.warning(
                "background updates between tasks failed (%s); the next task applies what is left",
                describe_exception(run.error),
            )
            return time.perf_counter() - start
        return float(run.value or 0.0)

    def obtain_foreground(
        self,
        scene: SceneTracker,
        frames: FrameSet,
        updates: Sequence[FrameSet],
        timings: StageTimings,
    ) -> ForegroundResult:
        """The task's foreground: the scheduled background updates due before it (usually
        none or one: one per ``update_interval_s`` of stream time), then the segmentation at
        the working resolution. The masks are computed once, here, where they are needed
        first; the back-end gets them with the frames. ``scene``: the background models,
        held (``_holding_scene``)."""
        if updates:
            with timings.stage("scene_update"):
                for u in updates:
                    # A static scene due here is built after the critical path (settle).
                    self._learn_update(scene, u)
        with timings.stage("scene"):
            return scene.segment(frames)

    # ------------------------------------------------------------------ the task
    def run_task(
        self,
        frames: FrameSet,
        plan: TaskPlan,
        submit: SubmitFn,
        golden: GoldenProvider,
        *,
        task: int = 0,
        defects: Mapping[str, str] | None = None,
        updates: Sequence[FrameSet] = (),
    ) -> TaskOutput:
        """Run one task (critical path, then online evaluation and the optimizer step) under
        the watchdog: never raises (a failed task is a record). ``defects``: cameras the
        session left out (unusable frames), name -> defect; ``updates``: the frames of
        :meth:`pending_updates`."""
        guard = TaskGuard()
        box: dict[str, Any] = {}
        job = _Job(
            frames=frames,
            plan=plan,
            submit=submit,
            golden=golden,
            task=task,
            updates=tuple(updates),
        )

        def work() -> None:
            try:
                box["out"] = self._process(job, dict(defects or {}), guard)
            except BaseException as exc:  # recorded below, whatever it is
                box["exc"] = exc

        limit = self.config.watchdog_s
        run = self._tasks.call(work, limit, name=f"task-{task}")
        worker = run.thread
        with self._commit:
            abandoned = run.timed_out and not guard.committed
            if abandoned:
                guard.cancel.set()  # it stops at its next stage boundary, publishing nothing
                self._restore_scene(worker, f"task {task} (time {frames.time_index})")
                # The configuration took that long: the controller learns it.
                self.controller.observe(limit, None)
        if abandoned:
            error = f"watchdog: still running after {limit:.1f} s (abandoned)"
            logger.error("task %d (time %d): %s", task, frames.time_index, error)
            # A stage that never reaches a boundary (a loop that does not end) is stopped
            # too, once the commit lock is free and it had time to stop on its own: its
            # thread would take a core from every later task.
            self.abandoned.abandon(
                worker, f"task {task} (time {frames.time_index}) abandoned by the watchdog"
            )
            return self._failed(frames, task, error)
        run.wait()  # committed: only the metrics are left to build
        if "exc" in box:
            exc = box["exc"]
            error = describe_exception(exc)
            logger.error("task %d (time %d) failed: %s", task, frames.time_index, error)
            logger.debug("traceback", exc_info=exc)
            return self._failed(frames, task, error)
        out: TaskOutput = box["out"]
        return out

    def _failed(self, frames: FrameSet, task: int, error: str) -> TaskOutput:
        m = TaskMetrics.failed(
            task=task, time_index=frames.time_index, error=error, deadline_s=self.config.deadline_s
        )
        return TaskOutput(metrics=m, foreground=None)

    def inject_fault(self, kind: str) -> None:
        """Drill: ``"hang"`` makes the next task loop for ever in Python code (the watchdog
        abandons it and stops its thread; ``runtime.interrupt``)."""
        if kind != "hang":
            raise ValueError(f"unknown front-end fault {kind!r}: use 'hang'")
        self._drill = kind

    def _process(self, job: _Job, defects: dict[str, str], guard: TaskGuard) -> TaskOutput:
        frames, plan, golden, task = job.frames, job.plan, job.golden, job.task
        if self._drill == "hang":
            self._drill = None
            logger.warning("drill: task %d loops for ever (until the watchdog stops it)", task)
            _loop_for_ever()
        if defects and too_few_cameras(frames):
            return self._empty(job, defects)
        start = time.perf_counter()
        background, bg_version = self.background()
        want_golden = self.config.online_quality == "golden"
        segmented: list[ForegroundResult] = []

        def foreground(timings: StageTimings) -> ForegroundResult:
            with self._holding_scene() as scene:
                fg = self.obtain_foreground(scene, frames, job.updates, timings)
            segmented.append(fg)
            job.submit(
                TaskWork(
                    frames=frames,
                    foreground=fg.slim(),
                    golden=want_golden,
                    still_uses=None if self.still is None else self.still.uses(),
                )
            )
            return fg

        scale = plan.scale
        area: float | None = None
        before_mvs = 0.0

        def configs(r: float) -> tuple[ReconstructionConfig, SplitPipelineConfig]:
            return self.config.task_configs(r, self.rig, plan.camera_ids)

        def retune(fg: ForegroundResult) -> tuple[ReconstructionConfig, SplitPipelineConfig]:
            # Once the masks are known: the task's r from its workload (optimize.workload).
            nonlocal scale, area, before_mvs
            before_mvs = time.perf_counter() - start
            area = mask_area(fg.masks, plan.camera_ids)
            scale = self._workload_scale(plan, area, before_mvs)
            return configs(scale)

        task_config, split_config = configs(plan.scale)
        result = reconstruct_task(
            frames,
            self.rig,
            foreground,
            task_config,
            background=background,
            bg_version=bg_version.counter,
            split_config=split_config,
            sparse_scope=self._sparse_scope(plan.phase, want_golden),
            cancel=guard.cancel,
            retune=None if self.workload is None else retune,
            still=None if self.still is None else functools.partial(self._still_plan, plan, frames),
        )
        critical = time.perf_counter() - start
        timings = result.timings
        fg_rec = result.foreground

        # ---- after the critical path: online evaluation, the optimizer step and, when the
        # task's frame is on the update schedule, its background update (due for the next
        # task; it reuses this task's segmentation)
        fg = segmented[0]
        degraded, reason = False, ""
        quality: float | None = None
        if want_golden:
            with timings.stage("wait_golden"):
                ref = golden(self.config.golden_wait_s)
            if ref is None or ref.fg_points3D is None:
                degraded = True
                reason = (
                    f"no golden reference within {self.config.golden_wait_s:.1f} s"
                    if ref is None
                    else f"back-end golden reference: {ref.error}"
                )
            else:
                quality = online_quality(
                    fg_rec.fg_sparse.points3D,
                    ref.fg_points3D,
                    OnlineQualityConfig(threshold=self.eval_threshold),
                ).value
        else:
            with timings.stage("online_quality"):
                images = [None if sg is None else sg.image for sg in fg.segmentations] or None
                quality = silhouette_quality(
                    fg_rec.cloud.points3D, fg.cameras, fg.masks, images=images
                ).value
        with timings.stage("scene_update_after"), self._holding_scene() as scene:
            if guard.cancel.is_set():  # abandoned: the models are no longer this task's
                raise TaskCancelled(f"time {frames.time_index}: cancelled before its update")
            scene.settle()  # static scenes due before this task's frame first
            self._learn_update(scene, frames, fg, defer_static=False)
            self._save_scene(scene)
        sparse = result.sparse
        # A task without a foreground object (no mask pixel in its cameras, or masks that no
        # two cameras agree on: an empty visual hull; the stream's first second without an
        # empty-scene clip, an empty room) measures no MVS at its r: it is not an observation
        # (the adjustment would climb on it, and a golden task's pi(N') would come from no
        # foreground); the controller plans the same configuration again.
        task_area = area if area is not None else mask_area(fg.masks, plan.camera_ids)
        informative = task_area != 0.0 and (fg.hull is None or fg.hull.num_voxels > 0)
        mapping = (
            informative
            and plan.phase == "golden"
            and not isinstance(self.controller, FixedController)
        )
        if mapping and "sfm" not in timings.to_dict():
            # pi(N') needs the golden task's sparse visibility; its cloud did not (the hull
            # bounded the depth search): the SfM of the foreground runs after the task's
            # cloud, not on its critical path.
            with timings.stage("sfm_mapping"):
                sparse = task_sparse(
                    prepare_task_views(frames, self.rig, result.config),
                    self.rig,
                    fg.masks,
                    self.config.split.fg_mask_dilation_px,
                    result.config.sparse_config,
                )
        with self._commit:
            if guard.cancel.is_set():
                raise TaskCancelled(f"time {frames.time_index}: cancelled before the commit")
            if mapping:
                # Every golden task refreshes pi(N') (a golden re-search included).
                vis = sparse.visibility_matrix(len(self.rig))
                self._set_mapping(vis, fg_rec.cloud, task, frames.time_index)
            if informative:
                self.controller.observe(critical, quality)
                if self.workload is not None:
                    self.workload.record(area, before_mvs, scale, critical - before_mvs)
            guard.committed = True  # a late watchdog takes this result
        labels = fg_rec.labels
        return self._output(
            job,
            bg_version,
            background,
            fg_rec.cloud,
            result.bg_dropped,
            camera_ids=list(result.camera_ids),
            critical_path_s=round(critical, 6),
            stages=timings.to_dict(),
            deadline_met=critical <= self.config.deadline_s,
            online_fscore=quality,
            degraded=degraded,
            degraded_reason=reason,
            frame_defects=defects,
            num_sparse=sparse.num_points,
            num_sparse_fg=int(np.count_nonzero(labels > 0)),
            num_still_points=fg_rec.num_still,
            still_share=None if result.still is None else round(result.still.share, 4),
            num_objects=max(num_objects(labels), _cloud_objects(fg_rec.cloud)),
            scale=scale,
            planned_scale=None if scale == plan.scale else plan.scale,
        )

    def _still_plan(
        self, plan: TaskPlan, frames: FrameSet, fg: ForegroundResult
    ) -> StillPlan | None:
        """What the task densifies (``scene.still``); a golden task, the controller's
        reference, densifies all."""
        if self.still is None or plan.phase == "golden":
            return None
        try:
            return self.still.plan(frames.images, fg.masks, fg.time_index)
        except Exception as exc:  # an optimisation: the task densifies everything instead
            if not self._still_failed:
                logger.warning(
                    "time %d: the still foreground failed (%s): tasks densify their whole "
                    "foreground when it does",
                    fg.time_index,
                    describe_exception(exc),
                )
                self._still_failed = True
            return None

    def _workload_scale(self, plan: TaskPlan, area: float | None, spent_s: float) -> float:
        """The task's r: the controller's, scaled in the adjustment by the mask ``area`` and
        the time the controller's target leaves after the ``spent_s`` seconds before the
        MVS, against the recent tasks' (``optimize.workload``), within the controller's
        range."""
        ctrl = self.controller
        if self.workload is None or plan.phase != "adjust":
            return plan.scale
        if not isinstance(ctrl, BisectionController):
            return plan.scale
        target = ctrl.target_s
        factor = self.workload.factor(area, spent_s, target, plan.scale)
        if factor == 1.0:
            return plan.scale
        lo, hi = ctrl.scale_range(len(plan.camera_ids))
        # Out of a skipped interval upwards: as fast or faster, and finer.
        scaled = ctrl.undominated(min(max(plan.scale * factor, lo), max(hi, plan.scale)))
        return round(scaled, 6)

    def _sparse_scope(self, phase: str, want_golden: bool) -> str:
        """The task's ``sparse_scope``: "hull" skips SfM on the critical path, except when
        the online estimate is the paper's (it compares foreground sparse clouds). A golden
        task's SfM (pi(N') is built from its sparse visibility) runs after its cloud
        (``sfm_mapping``)."""
        scope = self.config.sparse_scope
        if scope == "hull" and want_golden:
            return "foreground"
        return scope

    def _empty(self, job: _Job, defects: dict[str, str]) -> TaskOutput:
        """A task whose frames are unusable: no foreground, the background alone."""
        background, bg_version = self.background()
        return self._output(
            job,
            bg_version,
            background,
            PointCloud.empty(),
            np.zeros(0, np.int64),
            camera_ids=job.frames.available,
            deadline_met=True,
            frame_defects=defects,
        )

    def _output(
        self,
        job: _Job,
        bg_version: BgVersion,
        background: PointCloud,
        foreground: PointCloud,
        dropped: NDArray[np.int64],
        **fields: Any,
    ) -> TaskOutput:
        """An ok task's output: ``foreground`` merged with ``background`` (of ``bg_version``)
        without the points at ``dropped``; ``fields`` are the metrics that differ between
        tasks."""
        fields.setdefault("scale", job.plan.scale)
        metrics = TaskMetrics(
            task=job.task,
            time_index=job.frames.time_index,
            status="ok",
            phase=job.plan.phase,
            num_cameras=len(fields["camera_ids"]),
            deadline_s=self.config.deadline_s,
            bg_version=bg_version.counter,
            bg_epoch=bg_version.epoch,
            num_fg_points=len(foreground),
            num_merged_points=len(foreground) + len(background) - len(dropped),
            search_steps=int(getattr(self.controller, "total_search_steps", 0)),
            wall_time=time.time(),
            **fields,
        )
        return TaskOutput(
            metrics=metrics,
            foreground=foreground,
            bg_dropped=dropped,
            background=self._background_to_publish(background, bg_version),
        )

    def _set_mapping(
        self, visibility: np.ndarray, fg_cloud: PointCloud, task: int, time_index: int
    ) -> None:
        """pi(N') from a golden task: its sparse visibility, topped up with the dense
        foreground's visibility when the sparse cloud is thin (wide-baseline rigs)."""
        vis = visibility
        if len(vis) < _MIN_SELECTION_POINTS and len(fg_cloud):
            extra = visibility_from_points(fg_cloud.points3D, self.rig.cameras, fg_cloud.normals)
            vis = np.vstack([vis, extra])
        mapping = camera_mapping(
            vis,
            camera_centers=self.rig.centers,
            viewing_directions=np.array([c.viewing_direction for c in self.rig]),
            sizes=range(len(self.rig), MIN_CAMERAS - 1, -1),
        )
        self.controller.set_camera_mapping(mapping)
        self.pi_source = {"task": task, "time_index": time_index, "rows": len(vis)}
        logger.info(
            "front-end: camera mapping pi(N') from task %d (time %d): %d visibility rows",
            task,
            time_index,
            len(vis),
        )


def _cloud_objects(cloud: PointCloud) -> int:
    """Objects among a foreground cloud's labels (a task without SfM has no sparse labels)."""
    return 0 if cloud.labels is None else num_objects(cloud.labels)
