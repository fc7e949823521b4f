"""``run_online``: assemble the online system (output folder, run state, controller, scene
model, engine, session).

Everything that can be checked is checked before any heavy work (learning the background
models, warming up the kernels, starting Ray): the options against the dataset, the output
folder (writable, not locked by another run, empty unless ``--overwrite``, or holding a run
of this dataset and frame range for ``--resume``).

``--resume`` restores the run state together (:class:`~edgerecon.runtime.state.RunState`):
the controller (a new ``--deadline`` is applied to it and the configuration search
restarts), pi(N') and where it came from, the background cloud and its version, the last
back-end epoch (the new back-end counts on from the next one); the background models are
rebuilt from the stream up to the next task (they are a function of the stream alone,
:mod:`edgerecon.scene.stream`), so the resumed run segments the next frame as an
uninterrupted run would. A dataset whose calibration placed some cameras again since the
run's last task (``edgerecon calib --write``) is resumed with the new rig, its saved
background dropped (:mod:`edgerecon.runtime.state`).

A deadline given as a share of the original pipeline (``run --deadline 40%``,
``RuntimeConfig.deadline_share``) is set here, before the controller exists: the original
pipeline (r = 1, every camera, the whole scene; the paper's baseline and the ``reconstruct``
command's) runs twice on the first timestamp to run whose frames every camera can use,
timed by its own stage timings (the faster counts), while nothing else runs
(:func:`measure_original`); a resumed run takes the time it started with from the run state.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from edgerecon import progress
from edgerecon.config import ReconstructionConfig
from edgerecon.geometry.camera import Rig
from edgerecon.io.dataset import Dataset
from edgerecon.io.ply import ply_frame
from edgerecon.optimize.controller import BisectionController, ControllerConfig
from edgerecon.pipeline import dominated_scales, fine_scale_limit, reconstruct, warm_up
from edgerecon.quality.frames import frame_defects
from edgerecon.runtime.config import RuntimeConfig
from edgerecon.runtime.engine import (
    EmbeddedEngine,
    Engine,
    SceneModel,
    learn_scene_model,
    relearned,
)
from edgerecon.runtime.frontend import FixedController
from edgerecon.runtime.memory import MMAP_THRESHOLD, long_run, start_heap_trimmer, tune_malloc
from edgerecon.runtime.messages import TaskMetrics
from edgerecon.runtime.session import RunSummary, Session, SessionOptions
from edgerecon.runtime.state import DatasetIdentity, OriginalTiming, OutputFolder
from edgerecon.types import EdgereconError, FrameSet, StageTimings

logger = logging.getLogger(__name__)

ENGINES = ("embedded", "ray")


def make_controller(
    dataset: Dataset,
    config: RuntimeConfig,
    *,
    fixed: tuple[float, tuple[int, ...] | None] | None = None,
    controller_config: ControllerConfig | None = None,
    saved_state: dict[str, Any] | None = None,
    recalibrated: bool = False,
) -> BisectionController | FixedController:
    """The optimizer (Algorithm 1) or, with ``fixed=(scale, camera_ids)``, one configuration
    for every task (None camera ids = all). A saved controller takes ``config``'s deadline
    (a changed one restarts its search); ``recalibrated`` (cameras placed again since it was
    saved): its search restarts with a golden task, whose visibility gives pi(N') again (the
    saved one came from the poses before). The controller's ``r_fine`` is the rig's
    (``pipeline.fine_scale_limit``; a given one capped at it), None with
    ``config.fine_foreground`` off."""
    n = len(dataset.rig)
    if fixed is not None:
        scale, ids = fixed
        return FixedController(scale, tuple(range(n)) if ids is None else tuple(ids))
    if saved_state is not None and saved_state.get("format") == "edgerecon-controller":
        ctrl = BisectionController.from_dict(saved_state)
        if ctrl.config.deadline_s != config.deadline_s:
            logger.warning(
                "--resume with a new deadline (%.3g s, was %.3g s): the configuration search "
                "restarts",
                config.deadline_s,
                ctrl.config.deadline_s,
            )
            ctrl.set_deadline(config.deadline_s)
        if recalibrated:
            logger.warning(
                "the camera subsets pi(N') came from the calibration before: the configuration "
                "search restarts with a golden task"
            )
            ctrl.restart("calibration", golden=True)
        return ctrl
    cc = controller_config or ControllerConfig(
        deadline_s=config.deadline_s, adjust_target=config.adjust_target
    )
    # Above r_max: as far as the rig's foreground can get finer (``pipeline.task_configs``),
    # at most a given r_fine, nothing with fine_foreground off.
    limit = fine_scale_limit(dataset.rig, config.dense, config.split)
    fine = limit if cc.r_fine is None else min(cc.r_fine, limit)
    fine_or_none = fine if config.fine_foreground and fine > cc.r_max else None
    if fine_or_none != cc.r_fine:
        cc = dataclasses.replace(cc, r_fine=fine_or_none)
    if config.skip_dominated_scales and not cc.skip_scales:
        skip = dominated_scales(
            dataset.rig,
            cc.r_min,
            cc.r_max,
            cc.r_fine,
            dense_config=config.dense,
            split_config=config.split,
        )
        if skip:
            logger.info(
                "r skipped (a larger r costs less): %s",
                ", ".join(f"{a:.3g}-{b:.3g}" for a, b in skip),
            )
        cc = dataclasses.replace(cc, skip_scales=skip)
    return BisectionController(cc, None, n)


#: Runs of the original pipeline behind ``measure_original``: the least time counts (load
#: only adds time; one run on this 2-core machine varied by 1.55-1.91 s on one capture).
ORIGINAL_RUNS = 2
#: A run of the original pipeline longer than this (seconds) is not repeated (an 8-camera
#: 4K rig would otherwise wait minutes before its first task).
_ORIGINAL_LONG_S = 20.0
#: Timestamps ``measure_original`` may try over a recorded stream.
_ORIGINAL_TRIES = 5


#: Times the original pipeline on one frame set: ``(frames, rig, config, runs)`` to
#: ``(timings or None, why nothing was timed, where it ran)`` (:func:`time_original` here;
#: ``ray_engine.FrontendTimer`` on the Ray front-end's node).
OriginalTimer = Callable[
    [FrameSet, Rig, ReconstructionConfig, int], tuple[StageTimings | None, str, str | None]
]


def time_original(
    frames: FrameSet, rig: Rig, rc: ReconstructionConfig, runs: int = ORIGINAL_RUNS
) -> tuple[StageTimings | None, str, str | None]:
    """The original pipeline on ``frames``, timed by its own stages after the compiled
    kernels are loaded: the fastest of ``runs`` runs (one when it takes more than 20 s);
    ``(None, why)`` when it finds nothing (an error, an empty dense cloud). The third value
    says where it ran: None, this process."""
    warm_up()
    n = len(rig)
    best: StageTimings | None = None
    for i in range(max(1, runs)):
        with progress.phase(
            f"the original pipeline at time {frames.time_index} (r = 1, {n} cameras), run {i + 1}"
        ):
            try:
                result = reconstruct(frames, rig, rc)
            except EdgereconError as exc:
                return best, str(exc), None
        if result.dense is None or not result.dense.num_points:
            return best, "an empty dense cloud", None
        if best is None or result.timings.total < best.total:
            best = result.timings
        if result.timings.total > _ORIGINAL_LONG_S:
            break  # a long pipeline's noise averages out over its length
    return best, "", None


def measure_original(
    dataset: Dataset,
    config: RuntimeConfig,
    times: Sequence[int],
    runs: int = ORIGINAL_RUNS,
    *,
    timer: OriginalTimer = time_original,
) -> OriginalTiming:
    """The original pipeline (r = 1, every camera, the whole scene, the run's sparse and
    whole-scene dense settings) timed by ``timer`` (:func:`time_original`: its own stages,
    the fastest of ``runs`` runs, in this process), on the first of ``times`` (ascending)
    whose frames every camera can use (none missing, black, saturated or textureless:
    ``quality.frames``) and whose dense cloud is not empty: the lights out or a covered lens
    at the first timestamp would time a pipeline that finds nothing. The frames are read
    here; a Ray run's ``timer`` ships them to the front-end's node, where its tasks will
    run. ``EdgereconError`` when none of them serves (the deadline must then be given in
    seconds)."""
    rc = ReconstructionConfig(
        scale=1.0, sparse_config=config.sparse, dense_config=config.background_dense
    )
    skipped: list[str] = []
    with dataset.open_frames(missing="skip_camera") as source:
        for t in times:
            frames = source.read(t)
            defects = frame_defects(frames, config.frame_check)
            unusable = [
                f"{cam.name} {'no frame' if im is None else d}"
                for cam, im, d in zip(dataset.rig, frames.images, defects, strict=True)
                if im is None or d is not None
            ]
            if unusable:
                skipped.append(f"time {frames.time_index}: {', '.join(unusable)}")
                continue
            best, why, node = timer(frames, dataset.rig, rc, runs)
            if best is None:
                skipped.append(f"time {frames.time_index}: {why}")
                continue
            if skipped:
                logger.warning(
                    "the original pipeline timed at time %d (%s)",
                    frames.time_index,
                    "; ".join(skipped),
                )
            return OriginalTiming.of(frames.time_index, best, node=node)
    raise EdgereconError(
        "the deadline is a share of the original pipeline's time, which could not be "
        f"measured ({'; '.join(skipped)}): give --deadline in seconds"
    )


def original_times(dataset: Dataset, todo: Sequence[int], first: int) -> list[int]:
    """The timestamps ``measure_original`` tries: the first task's, then four more spread
    over the tasks to run (a live stream: its newest frames, three times)."""
    if dataset.is_live:
        return [first, first + 1, first + 2]
    if not todo:
        return [first]
    picks = np.linspace(0, len(todo) - 1, _ORIGINAL_TRIES).round().astype(int)
    return sorted({todo[int(i)] for i in picks})


def check_options(
    dataset: Dataset,
    options: SessionOptions,
    *,
    engine: str = "embedded",
    fixed: tuple[float, tuple[int, ...] | None] | None = None,
) -> None:
    """Every option against the dataset, before any work (``ValueError`` naming it)."""
    if engine not in ENGINES:
        raise ValueError(f"--engine must be one of {ENGINES}, got {engine!r}")
    fr = options.frames
    if not dataset.is_live and not fr.indices(dataset.num_frames):
        raise ValueError(
            f"--frames {fr.start}:{'' if fr.stop is None else fr.stop}:{fr.step} selects no "
            f"timestamp of {dataset.name} (frames 0..{dataset.num_frames - 1})"
        )
    if any(kind == "kill" for _, kind, _ in options.faults) and engine != "ray":
        raise ValueError(
            "--inject-fault TASK:kill kills the back-end actor's process: it needs "
            "--engine ray (use stall or crash with the embedded engine)"
        )
    if fixed is not None:
        scale, ids = fixed
        if not 0 < scale <= 1:
            raise ValueError(f"--fixed must be a scale in (0, 1], got {scale:g}")
        if ids is not None:
            n = len(dataset.rig)
            if len(set(ids)) != len(ids) or not all(0 <= i < n for i in ids) or len(ids) < 3:
                raise ValueError(
                    f"--cameras must name at least 3 distinct cameras of the rig (ids 0..{n - 1} "
                    f"or names {', '.join(dataset.rig.names)}), got {list(ids)}"
                )


def run_online(
    dataset: Dataset,
    config: RuntimeConfig,
    options: SessionOptions,
    out_dir: str | Path,
    *,
    engine: str = "embedded",
    address: str | None = None,
    fixed: tuple[float, tuple[int, ...] | None] | None = None,
    controller_config: ControllerConfig | None = None,
    scene: SceneModel | None = None,
    on_task: Callable[[TaskMetrics], None] | None = None,
    on_ready: Callable[[SceneModel], None] | None = None,
    command: str = "",
    original: OriginalTiming | None = None,
) -> tuple[RunSummary, list[TaskMetrics]]:
    """Run the online system on ``dataset`` and return its summary and per-task metrics
    (:class:`~edgerecon.runtime.session.RunInterrupted` after Ctrl-C, summary written).

    ``original``: the original pipeline's time when the caller measured it (``demo``);
    otherwise a run whose deadline is a share measures it (:func:`measure_original`), and a
    resumed one takes it from its state."""
    check_options(dataset, options, engine=engine, fixed=fixed)
    fr = options.frames
    with OutputFolder(out_dir).acquire(command) as folder:
        saved = folder.prepare(
            resume=options.resume,
            overwrite=options.overwrite,
            identity=DatasetIdentity.of(dataset),
            frames=(fr.start, fr.stop, fr.step),
            rig=dataset.rig,
        )
        previous = [] if saved is None else folder.read_metrics(saved.tasks_done)
        done = {m.time_index for m in previous}
        todo: list[int] = []
        if dataset.is_live:  # tasks are numbered on: no frame index to catch up to
            first = max(done, default=fr.start - 1) + 1
        else:
            todo = [t for t in fr.indices(dataset.num_frames) if t not in done]
            first = todo[0] if todo else 0
        # Before the roles' threads and the rebuild's process start (runtime.memory): a
        # long run also maps image-sized blocks on their own.
        long = long_run(live=dataset.is_live, duration_s=options.duration_s, num_tasks=len(todo))
        tune_malloc(mmap_threshold=MMAP_THRESHOLD if long else None)
        start_heap_trimmer()
        if original is None and saved is not None:
            original = saved.original
        share = config.deadline_share
        joined = False  # a Ray cluster joined to time the original pipeline on it
        if share is not None:
            measured_before = original is not None
            if original is None:
                times = original_times(dataset, todo, first)
                if engine == "ray" and address:
                    # On a cluster the front-end may be another device than this one: the
                    # deadline is a share of the pipeline's time where the tasks will run.
                    from edgerecon.runtime.ray_engine import FrontendTimer

                    timer = FrontendTimer(address)
                    try:
                        original = measure_original(dataset, config, times, timer=timer)
                    except BaseException:
                        timer.release()
                        raise
                    joined = timer.joined
                else:
                    original = measure_original(dataset, config, times)
            config = config.with_original(original.seconds)
            logger.warning(
                "deadline %.3g s: %.0f %% of the original pipeline's %.3f s (r = 1, %d cameras, "
                "the whole scene at time %d%s%s)",
                config.deadline_s,
                100 * share,
                original.seconds,
                len(dataset.rig),
                original.time_index,
                "" if original.node is None else f", on the front-end's Ray node {original.node}",
                ", as measured when the run started"
                if saved is not None and measured_before
                else "",
            )
        if controller_config is not None and controller_config.deadline_s != config.deadline_s:
            controller_config = dataclasses.replace(controller_config, deadline_s=config.deadline_s)
        controller = make_controller(
            dataset,
            config,
            fixed=fixed,
            controller_config=controller_config,
            saved_state=None if saved is None else saved.frontend.controller,
            recalibrated=folder.recalibration is not None,
        )
        if scene is None:
            # The background models as they are at the first task still to run (the one
            # stream definition of edgerecon.scene.stream: a resumed run continues with the
            # models an uninterrupted run would have).
            scene = learn_scene_model(dataset, config.foreground, first)
        if folder.recalibration is not None:
            # The cameras re-posed now: their models show the scene as they saw it before.
            names = dataset.rig.names
            moved = [names.index(n) for n in folder.recalibration.cameras if n in names]
            scene = relearned(scene, dataset, moved, first, config.foreground)
        if scene.initial_background is not None and (
            folder.recalibration is not None or (saved is not None and saved.recalibrations)
        ):
            # The empty-scene clip shows the cameras as they were before the run re-posed one:
            # rebuilt with the new poses, or checked (the check turned the camera back to
            # where the clip has it: a repaired run undid its own repair), it misleads. The
            # back-end starts from the stream's frames.
            logger.info(
                "the empty-scene clip predates the cameras re-posed in this run: the back-end "
                "rebuilds from the stream's frames"
            )
            scene = dataclasses.replace(scene, initial_background=None)
        if on_ready is not None:
            on_ready(scene)
        restored = None if saved is None else saved.frontend
        background = None if saved is None else folder.read_background()
        if saved is not None:
            rig = dataset.rig
            version = saved.frontend.bg_version
            folder.ensure_background(
                background,
                (version.epoch, version.counter),
                **ply_frame(rig),
            )
            logger.warning(
                "resuming after %d tasks (background %s, back-end epoch %d)",
                saved.tasks_done,
                "none yet" if background is None else saved.frontend.bg_version,
                saved.frontend.backend_epoch,
            )
        eng: Engine
        if engine == "ray":
            from edgerecon.runtime.ray_engine import RayEngine

            eng = RayEngine(
                dataset,
                config,
                controller,
                scene,
                address=address,
                restored=restored,
                background=background,
                joined=joined,
            )
        else:
            eng = EmbeddedEngine(
                dataset, config, controller, scene, restored=restored, background=background
            )
        try:
            session = Session(
                dataset,
                eng,
                options,
                folder,
                deadline_s=config.deadline_s,
                deadline_share=config.deadline_share,
                original=original,
                frame_check=config.frame_check,
                previous=previous,
                on_task=on_task,
                recalibrations=() if saved is None else saved.recalibrations,
            )
            summary = session.run()
            return summary, session.metrics
        finally:
            eng.close()


__all__ = ["ENGINES", "check_options", "make_controller", "measure_original", "run_online"]
