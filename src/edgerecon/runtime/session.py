"""The online session: the stream of tasks, outputs, resume, and the run's summary.

Frame policy (frames can arrive faster than tasks finish):

* ``all`` (default): every timestamp of ``--frames A:B:STEP`` becomes a task, in order — what
  the paper evaluated (each timestamp is a task) and what makes runs comparable.
* ``newest``: frames of ``--frames`` arrive in real time at ``arrival_fps`` (default: the
  dataset's fps divided by STEP); when the front-end is free it takes the newest frame that has
  arrived and drops the older ones (counted in the summary as ``frames_dropped``). This is
  what a live deployment does: the user always sees the most recent state of the scene.

Live streams (``frames.kind = "stream"``, :mod:`edgerecon.io.streams`): the policy is
``newest`` (the source's readers keep only each camera's newest frame, and every task takes
the newest synchronized set); tasks are numbered 0, 1, ... and go on for ``duration_s`` (or
until ``frames.stop`` tasks, or Ctrl-C). Each task records its sync spread; the summary
adds the source's counts (waits, cameras left out, frames dropped).

Outputs in ``out_dir`` (each written atomically, so a crash never leaves a torn file; 0644):

* ``metrics.jsonl``: one JSON line per task (:class:`TaskMetrics`), failed tasks included;
* ``tasks/<time>/fg.ply`` and ``bg_dropped.npy``: each task's part of its merged cloud (the
  foreground, labels and ``bg_version`` per point, its background version in a header
  comment; the indices of the background points it overrode). ``viewer.rundir.RunFolder.cloud``
  composes the merged cloud (a background is a million points on an HD rig: stored with every
  task it was 47 MB per task on an 8-camera 1080p rig);
* ``backgrounds/v<epoch>.<counter>.ply``: every background version a task merged with, once;
* ``background.ply``: the newest of them (the background itself, as the back-end built it;
  ``--resume`` restores it);
* ``rig.json``: the rig (written when the run starts; the viewer draws its cameras);
  ``rig.<k>.json``: the rig before the k-th resume with cameras placed again
  (:mod:`edgerecon.runtime.state`);
* ``rig.repaired.json``: written at the end when the back-end's last calibration check
  found a camera moved and a re-aim or placement that makes the calibration fit (``edgerecon
  calib --adopt`` names it in the dataset; ``run --adopt-repairs`` does so during the run,
  :class:`RepairDue`);
* ``views.npz``: each camera's reference view of the move detector
  (``quality.frames.MovedCameras``) and of the cameras whose frames are turned back
  (``quality.frames.Stabiliser``), saved every ``_VIEWS_EVERY_S`` and at the end:
  ``--resume`` compares the first frames after a stop with them (a camera knocked while the
  run was stopped) and goes on turning back the swaying ones;
* ``state.json``: the run state (:class:`~edgerecon.runtime.state.RunState`), written last for
  each task: the commit point of ``--resume``;
* ``summary.json``: the run's summary (the paper's Table III), also after Ctrl-C;
* ``.lock``: held while the run lives (who holds it).

A long run keeps the newest task clouds within ``--keep-clouds`` and leaves ``--min-free-mb``
free on the disk (:mod:`edgerecon.runtime.retention`): older clouds and the background
versions only they refer to are removed after a task's commit; on a disk that is still too
full a task's cloud is not written (its metrics line is). Every metrics line stays.

Frames are checked before a task starts (:mod:`edgerecon.quality.frames`): a black,
saturated or textureless frame's camera is left out of the task; a task left with fewer than
3 cameras gives an empty result (no foreground, the background alone). One warning when
frames become unusable, one line when they recover.

``--resume`` continues after the last committed task with the saved run state and
background (see :mod:`edgerecon.runtime.online`).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from edgerecon.config import MIN_CAMERAS
from edgerecon.geometry.camera import Rig, rotation_angle_deg
from edgerecon.io.calibration import save_rig
from edgerecon.io.dataset import Dataset
from edgerecon.io.frames import FrameSource
from edgerecon.io.ply import atomic_write_text, ply_frame
from edgerecon.quality.frames import (
    FrameCheckConfig,
    FrozenCameras,
    MovedCameras,
    Stabiliser,
    frame_defects,
    without_defective,
)
from edgerecon.quality.metrics import fscore
from edgerecon.runtime.engine import Engine, SceneModel
from edgerecon.runtime.frontend import TaskOutput
from edgerecon.runtime.memory import peak_resident_mb, resident_mb
from edgerecon.runtime.messages import TaskMetrics, describe_exception
from edgerecon.runtime.retention import CloudRetention, RetentionConfig
from edgerecon.runtime.state import (
    REPAIRED_RIG_FILE,
    DatasetIdentity,
    OriginalTiming,
    OutputFolder,
    Recalibration,
    RunState,
)
from edgerecon.scene.merge import foreground_part
from edgerecon.scene.stream import DEFAULT_FPS
from edgerecon.types import EdgereconError, FrameSet

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class FrameRange:
    """Timestamps ``start, start + step, ...`` below ``stop`` (None = end of the stream)."""

    start: int = 0
    stop: int | None = None
    step: int = 1

    def __post_init__(self) -> None:
        if self.start < 0 or self.step < 1 or (self.stop is not None and self.stop < self.start):
            raise ValueError(f"invalid frame range {self.start}:{self.stop}:{self.step}")

    @classmethod
    def parse(cls, text: str) -> FrameRange:
        """``A:B:STEP``, ``A:B``, ``A:`` or ``A`` (one frame)."""
        parts = text.split(":")
        try:
            if len(parts) == 1:
                a = int(parts[0])
                return cls(start=a, stop=a + 1)
            a = int(parts[0]) if parts[0] else 0
            b = int(parts[1]) if len(parts) > 1 and parts[1] else None
            s = int(parts[2]) if len(parts) > 2 and parts[2] else 1
        except ValueError:
            raise ValueError(f"--frames must look like A:B:STEP, got {text!r}") from None
        return cls(start=a, stop=b, step=s)

    def indices(self, num_frames: int) -> list[int]:
        stop = num_frames if self.stop is None else min(self.stop, num_frames)
        return list(range(self.start, stop, self.step))


@dataclass(frozen=True, kw_only=True)
class SessionOptions:
    """How the session walks the stream and what it writes."""

    frames: FrameRange = field(default_factory=FrameRange)
    policy: str = "all"
    """"all" or "newest" (see module docstring)."""
    arrival_fps: float | None = None
    """Frame arrival rate for the "newest" policy (default: dataset fps / step)."""
    write_clouds: bool = True
    """Write each task's cloud (``tasks/<time>/fg.ply`` and ``bg_dropped.npy``; the background
    versions are written either way: ``--resume`` needs the newest)."""
    retention: RetentionConfig = field(default_factory=RetentionConfig)
    """How many task clouds the run keeps and the free space it leaves on the disk
    (``runtime.retention``: ``--keep-clouds``, ``--min-free-mb``)."""
    ground_truth_threshold: float | None = None
    """When the dataset has ground truth: score each task's foreground against it at this
    distance (rig units) — the offline F-score. None = no offline scoring."""
    resume: bool = False
    """Continue the run in the output folder (same dataset, same frame start and step)."""
    duration_s: float | None = None
    """Live streams: stop starting tasks after this many seconds (None: until ``frames``'s
    stop, or Ctrl-C)."""
    overwrite: bool = False
    """Replace the run files of a non-empty output folder (refused otherwise)."""
    keep_metrics: int | None = None
    """The task records the session keeps in memory and returns, the newest (None: every
    one; ``metrics.jsonl`` has every one, and the summary counts every one either way). A
    live stream's run keeps 1000 (``cli.run``): its records would grow for hours."""
    faults: tuple[tuple[int, str, float], ...] = ()
    """Drills: (task number, fault kind, seconds) injected before that task (``hang``: into
    the front-end, the others into the back-end)."""
    adopt_repairs: bool = False
    """``run --adopt-repairs``: when the back-end's calibration check (confirmed) finds a
    camera it can re-aim or place again so that the calibration fits, the session stops
    after the task in progress with :class:`RepairDue` (summary and ``rig.repaired.json``
    written); the caller names that rig in the dataset and resumes."""

    def __post_init__(self) -> None:
        if self.policy not in ("all", "newest"):
            raise ValueError(f"policy must be 'all' or 'newest', got {self.policy!r}")
        if self.duration_s is not None and not self.duration_s > 0:
            raise ValueError(f"duration must be > 0 seconds, got {self.duration_s}")
        if self.keep_metrics is not None and self.keep_metrics < 1:
            raise ValueError(f"keep_metrics must be >= 1 (or None), got {self.keep_metrics}")
        if self.resume and self.overwrite:
            raise ValueError("--resume and --overwrite exclude each other")
        for task, kind, seconds in self.faults:
            if task < 0 or kind not in FAULT_KINDS or not seconds >= 0:
                raise ValueError(
                    f"--inject-fault: TASK >= 0, KIND in {FAULT_KINDS}, SECONDS >= 0; got "
                    f"{task}:{kind}:{seconds}"
                )


#: Faults a drill can inject: the back-end's (``kill``: the Ray engine only) and the
#: front-end's ``hang`` (the task loops for ever).
FAULT_KINDS = ("stall", "crash", "kill", "hang")


def offline_fscore_label(threshold: float | None, unit: str = "") -> str:
    """The summary row's name for ``RunSummary.avg_offline_fscore`` (with its distance)."""
    at = "" if threshold is None else f", d = {threshold:.3g} {unit}".rstrip()
    return f"avg. F-score of FG (vs ground truth{at})"


def camera_moves_row(moves: list[dict[str, Any]]) -> tuple[str, str]:
    """The summary table's row of the cameras whose view moved (``RunSummary.camera_moves``),
    for ``run`` and ``report``: each move of a camera that moved up to 3 times; one line for
    one that kept moving (a swaying mount: hundreds of moves)."""
    by_camera: dict[str, list[dict[str, Any]]] = {}
    for m in moves:
        by_camera.setdefault(m["camera"], []).append(m)
    parts = []
    for name, ms in by_camera.items():
        if len(ms) > 3:
            turns = [m["turn_deg"] for m in ms]
            parts.append(
                f"{name} kept moving: {len(ms)} moves recorded, time {ms[0]['time_index']} to "
                f"{ms[-1]['time_index']} ({min(turns):.2f}-{max(turns):.2f} degrees)"
            )
            continue
        parts += [
            f"{name} "
            + ("across a stop, " if m.get("across_stop") else "")
            + f"at time {m['time_index']} (about {m['turn_deg']:.2f} degrees)"
            for m in ms
        ]
    return ("cameras whose view moved", "; ".join(parts) or "-")


def stabilised_row(stabilised: dict[str, dict[str, Any]]) -> tuple[str, str]:
    """The summary table's row of the cameras whose frames were turned back onto their view
    (``RunSummary.stabilised``), for ``run`` and ``report``."""
    return (
        "cameras turned back onto their view (knocked, swaying)",
        "; ".join(
            f"{name}: {st['tasks']} tasks, {st['mean_deg']:.2f} degrees on average, "
            f"{st['max_deg']:.2f} at most"
            + (f" ({st['unmeasured']} kept as they were)" if st.get("unmeasured") else "")
            for name, st in stabilised.items()
        )
        or "-",
    )


@dataclass
class RunSummary:
    """The run's aggregate (the shape of the paper's Table III, plus robustness counts)."""

    tasks: int = 0
    failed: int = 0
    degraded: int = 0
    empty: int = 0
    """Tasks whose frames were unusable (fewer than 3 usable cameras): no foreground."""
    frames_dropped: int = 0
    avg_scale: float = math.nan
    avg_cameras: float = math.nan
    cameras_used: list[int] = field(default_factory=list)
    avg_time_s: float = math.nan
    avg_time_converged_s: float = math.nan
    """Average critical path after the search ended (adjust phase)."""
    deadline_s: float = math.nan
    deadline_share: float | None = None
    """The deadline as a share of ``original_s`` (``run --deadline 40%``), None when given
    in seconds."""
    original_s: float | None = None
    """The original pipeline's time (r = 1, every camera, the whole scene) measured on the
    run's first timestamp before its first task; None: not measured."""
    original_node: str | None = None
    """The Ray node ``original_s`` was measured on (the front-end's, a run on a cluster);
    None: the run's own process."""
    online_over_original: float | None = None
    """The average critical path over ``original_s`` (the paper: 0.46 at its deadlines)."""
    deadline_misses_converged: int = 0
    avg_online_fscore: float | None = None
    avg_offline_fscore: float | None = None
    offline_threshold: float | None = None
    """Distance threshold of ``avg_offline_fscore`` (None: no ground truth)."""
    unit: str = ""
    """The rig's unit of length (that of ``offline_threshold``)."""
    backgrounds_pushed: int = 0
    """Backgrounds the front-end took over the whole run (resumes included)."""
    clouds_written: int = 0
    """Tasks whose cloud was written (``tasks/<time>/``) over the whole run."""
    clouds_kept: int = 0
    """Of them, those still on disk at the end (``--keep-clouds``, ``--min-free-mb``:
    ``runtime.retention``)."""
    clouds_skipped: int = 0
    """Tasks whose cloud was not written: the disk was under ``--min-free-mb``."""
    bg_version: list[int] = field(default_factory=lambda: [0, 0])
    """(back-end epoch, counter) of the newest background held at the end."""
    backend_restarts: int = 0
    abandoned_threads: list[str] = field(default_factory=list)
    """Abandoned work whose thread still runs at the end (stopped, but blocked inside a
    native call since; ``runtime.interrupt``): empty when every one ended."""
    search_steps: int = 0
    snapshots_pushed: int = 0
    """Snapshots of the still foreground the front-end took (``scene.still``; this
    process's, not those before a ``--resume``)."""
    still_tasks: int = 0
    """Tasks that kept the back-end's snapshot of the still foreground (``scene.still``)
    and densified the rest."""
    avg_still_share: float | None = None
    """Their average share of mask pixels still (not densified)."""
    stage_means_s: dict[str, float] = field(default_factory=dict)
    """Mean seconds per stage over the ok tasks (``wait_golden`` comes after the critical
    path)."""
    engine: str = ""
    wall_s: float = 0.0
    interrupted: bool = False
    """The run was stopped (Ctrl-C, SIGTERM) before its last task: ``--resume`` goes on."""
    calibration: dict[str, Any] | None = None
    """The back-end's last check of the calibration against the frames
    (``RuntimeConfig.calib_check_s``: ``time``, ``fits``, ``off``, ``message``, and when it
    does not fit ``repair``: what ``edgerecon calib --write`` would do, and when that fits
    ``repaired_rig_file``: ``rig.repaired.json`` in the run folder, the rig it makes,
    which ``edgerecon calib --adopt`` names in the dataset); None: none made (no background
    rebuild yet, or the check off)."""
    camera_moves: list[dict[str, Any]] = field(default_factory=list)
    """Cameras whose views moved during the run (``TaskMetrics.camera_moves`` of every
    task, each with ``seen_at``: the time index of the task that confirmed it; the first
    100: a camera that keeps moving for hours does not grow the summary)."""
    stabilised: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Cameras whose frames were turned back onto their view (``TaskMetrics.stabilised``):
    per camera ``tasks``, ``unmeasured`` (tasks whose frame gave no turn: kept as it was),
    ``mean_deg`` and ``max_deg`` of the turns taken off."""
    recalibrations: list[dict[str, Any]] = field(default_factory=list)
    """The resumes that went on with cameras placed again since the run started
    (``runtime.state.Recalibration``: ``from_task``, ``cameras``, ``moved``, ``turned_deg``,
    ``previous_rig``), oldest first."""
    stream: dict[str, Any] = field(default_factory=dict)
    """Live streams: the source's counts (``StreamFrameSource.stats``) and the tasks' sync
    spread (mean / max seconds)."""
    memory_mb: dict[str, float | None] = field(default_factory=dict)
    """The main process's resident memory, MB: ``first`` and ``last`` task's (a resumed
    run's first is that of the run's first task), ``peak``: the larger of this process's
    peak and every task's (each is in ``metrics.jsonl``, ``rss_mb``)."""

    def to_dict(self) -> dict[str, Any]:
        d = dict(self.__dict__)
        for k, v in d.items():
            if isinstance(v, float) and not math.isfinite(v):
                d[k] = None
        return d


class RepairDue(Exception):
    """The run stopped at a task boundary to take a repaired calibration
    (``SessionOptions.adopt_repairs``): its summary and ``rig.repaired.json`` are written;
    ``rig`` (world coordinates) is what to name in the dataset before a ``--resume``;
    ``scene``: the front-end's background models at the next task, without their static
    scenes (made with the poses before), for ``run_online(scene=...)`` (None: learn them
    again)."""

    def __init__(
        self,
        summary: RunSummary,
        metrics: list[TaskMetrics],
        rig: Rig,
        scene: SceneModel | None = None,
    ) -> None:
        super().__init__(f"a repaired calibration after {summary.tasks} tasks")
        self.summary = summary
        self.metrics = metrics
        self.rig = rig
        self.scene = scene


class RunInterrupted(KeyboardInterrupt):
    """The run was stopped by a signal; its summary is written and ``--resume`` goes on."""

    def __init__(self, summary: RunSummary, metrics: list[TaskMetrics]) -> None:
        super().__init__(f"interrupted after {summary.tasks} tasks")
        self.summary = summary
        self.metrics = metrics


def _same(value: int | None) -> int | None:
    return value


@dataclass
class _Mean:
    total: float = 0.0
    count: int = 0

    def add(self, value: float) -> None:
        self.total += float(value)
        self.count += 1

    @property
    def value(self) -> float:
        return self.total / self.count if self.count else math.nan


@dataclass
class RunTotals:
    """What the summary needs of every task, added up as tasks are committed: a run's
    memory does not grow with its tasks (a live stream runs for hours; the records
    themselves are in ``metrics.jsonl`` and, up to ``SessionOptions.keep_metrics``, in
    ``Session.metrics``)."""

    tasks: int = 0
    failed: int = 0
    degraded: int = 0
    empty: int = 0
    clouds_written: int = 0
    clouds_skipped: int = 0
    scale: _Mean = field(default_factory=_Mean)
    cameras: _Mean = field(default_factory=_Mean)
    cameras_used: list[int] = field(default_factory=list)
    time: _Mean = field(default_factory=_Mean)
    adjust_time: _Mean = field(default_factory=_Mean)
    adjust_misses: int = 0
    fixed_time: _Mean = field(default_factory=_Mean)
    fixed_misses: int = 0
    online: _Mean = field(default_factory=_Mean)
    offline: _Mean = field(default_factory=_Mean)
    search_steps: int = 0
    still_share: _Mean = field(default_factory=_Mean)
    stages: dict[str, float] = field(default_factory=dict)
    spread: _Mean = field(default_factory=_Mean)
    spread_max: float | None = None
    rss_first: float | None = None
    rss_last: float | None = None
    rss_max: float = 0.0
    moves: list[dict[str, Any]] = field(default_factory=list)
    stabilised: dict[str, dict[str, Any]] = field(default_factory=dict)

    def add(self, m: TaskMetrics) -> None:
        self.tasks += 1
        for name, deg in m.stabilised.items():
            st = self.stabilised.setdefault(
                name, {"tasks": 0, "unmeasured": 0, "mean_deg": 0.0, "max_deg": 0.0}
            )
            st["tasks"] += 1
            if deg is None:
                st["unmeasured"] += 1
                continue
            measured = st["tasks"] - st["unmeasured"]
            st["mean_deg"] = round(st["mean_deg"] + (deg - st["mean_deg"]) / measured, 3)
            st["max_deg"] = max(st["max_deg"], deg)
        for move in m.camera_moves[: max(0, 100 - len(self.moves))]:
            self.moves.append({**move, "seen_at": m.time_index})
        if m.rss_mb is not None:
            self.rss_last = m.rss_mb
            self.rss_max = max(self.rss_max, m.rss_mb)
            self.rss_first = m.rss_mb if self.rss_first is None else self.rss_first
        self.clouds_written += bool(m.cloud_written)
        self.clouds_skipped += bool(m.cloud_skipped)
        if m.sync_spread_s is not None:
            self.spread.add(m.sync_spread_s)
            self.spread_max = max(self.spread_max or 0.0, m.sync_spread_s)
        if m.status != "ok":
            self.failed += 1
            return
        self.degraded += bool(m.degraded)
        if m.frame_defects and m.num_cameras < MIN_CAMERAS:
            self.empty += 1
            return  # averages over the tasks that reconstructed
        self.scale.add(m.scale)
        self.cameras.add(m.num_cameras)
        self.cameras_used = list(m.camera_ids)
        self.time.add(m.critical_path_s)
        if m.phase == "adjust":
            self.adjust_time.add(m.critical_path_s)
            self.adjust_misses += not m.deadline_met
        elif m.phase == "fixed":
            self.fixed_time.add(m.critical_path_s)
            self.fixed_misses += not m.deadline_met
        if m.online_fscore is not None:
            self.online.add(m.online_fscore)
        if m.offline_fscore is not None:
            self.offline.add(m.offline_fscore)
        if m.still_share is not None:
            self.still_share.add(m.still_share)
        self.search_steps = max(self.search_steps, m.search_steps)
        for k, v in m.stages.items():
            self.stages[k] = self.stages.get(k, 0.0) + float(v)


#: Moves of one camera said as warnings (``Session._note_moved``); then once that it keeps
#: moving.
_MOVES_SAID = 3
#: Wall seconds between two saves of the move detector's reference views (``views.npz``;
#: also saved when the run ends or stops).
_VIEWS_EVERY_S = 10.0


class Session:
    """Runs tasks on an engine and keeps the run's files (see module docstring)."""

    def __init__(
        self,
        dataset: Dataset,
        engine: Engine,
        options: SessionOptions,
        folder: OutputFolder,
        *,
        deadline_s: float,
        deadline_share: float | None = None,
        original: OriginalTiming | None = None,
        frame_check: FrameCheckConfig | None = None,
        previous: list[TaskMetrics] | None = None,
        on_task: Callable[[TaskMetrics], None] | None = None,
        recalibrations: tuple[Recalibration, ...] = (),
    ) -> None:
        self.dataset = dataset
        self.recalibrations = recalibrations
        """The run's resumes with cameras placed again (``runtime.state``), kept in its state."""
        self.engine = engine
        self.options = options
        self.folder = folder
        self.out = folder.path
        self.deadline_s = deadline_s
        self.deadline_share = deadline_share
        self.original = original
        self.frame_check = frame_check or FrameCheckConfig()
        self.on_task = on_task
        previous = list(previous or [])
        self.totals = RunTotals()
        for m in previous:
            self.totals.add(m)
        keep = options.keep_metrics
        self.metrics: list[TaskMetrics] = previous if keep is None else previous[-keep:]
        """The task records in memory, oldest first: every one, or the newest
        ``keep_metrics`` (``metrics.jsonl`` has every one)."""
        self._done = {m.time_index for m in previous}
        self.identity = DatasetIdentity.of(dataset)
        self.frames_dropped = 0
        self._defects: dict[str, str] = {}
        self._frozen = FrozenCameras(self.frame_check, fps=dataset.fps or DEFAULT_FPS)
        self._moved = MovedCameras(self.frame_check)
        self._stabiliser = Stabiliser()
        self._moves_said: dict[str, int] = {}
        self._views_from: int | None = None
        """The time index of the reference views restored from before a stop."""
        self._views_saved = time.monotonic()
        if options.resume:
            self._restore_views()
        # The schedule's lower bound on the next task's time index, as of now (None: no
        # next task, or not known): the background updates before it can be applied
        # between tasks (``_learn_ahead``).
        self._next_bound: Callable[[], int | None] = functools.partial(_same, None)
        self._gt: Any = None
        self._stream: dict[str, Any] = {}
        self.retention = CloudRetention(
            self.out,
            options.retention,
            ((m.time_index, (m.bg_epoch, m.bg_version)) for m in previous if m.status == "ok"),
        )
        if options.ground_truth_threshold is not None and dataset.ground_truth is not None:
            from edgerecon.synth import GroundTruth

            self._gt = GroundTruth.open(dataset.root)

    # ------------------------------------------------------------------ the loop
    def _schedule(self, indices: list[int], done: set[int]) -> Iterator[int]:
        todo = [t for t in indices if t not in done]
        if self.options.policy == "all":
            for i, t in enumerate(todo):
                nxt = todo[i + 1] if i + 1 < len(todo) else None
                self._next_bound = functools.partial(_same, nxt)
                yield t
            return
        fps = self.options.arrival_fps or (self.dataset.fps or 25.0) / self.options.frames.step
        start = time.monotonic()

        def newest_from(pos: int) -> int:
            # The next task takes the newest frame that has arrived (at least todo[pos]).
            arrived = int((time.monotonic() - start) * fps)
            return min(max(arrived, pos), len(todo) - 1)

        pos = 0
        while pos < len(todo):
            newest = newest_from(pos)
            self.frames_dropped += newest - pos
            after = newest + 1

            def bound(after: int = after) -> int | None:
                # Frames only arrive: the next task's frame is at least the newest one now.
                return todo[newest_from(after)] if after < len(todo) else None

            self._next_bound = bound
            yield todo[newest]
            pos = after

    def _live_schedule(self, done: set[int]) -> Iterator[int]:
        """Live streams: tasks ``start, start + 1, ...`` (after those done) until
        ``duration_s`` has passed or ``frames.stop``; each read takes the newest frames."""
        end = (
            None if self.options.duration_s is None else time.monotonic() + self.options.duration_s
        )
        t = max(done | {self.options.frames.start - 1}) + 1
        stop = self.options.frames.stop
        while (stop is None or t < stop) and (end is None or time.monotonic() < end):
            yield t
            t += 1

    def _stream_stats(self, source: Any) -> None:
        stats = source.stats()
        self.frames_dropped = int(stats["frames_dropped"])
        spread = self.totals.spread
        self._stream = {
            **stats,
            "sync_spread_mean_s": spread.value if spread.count else None,
            "sync_spread_max_s": self.totals.spread_max,
        }

    def run(self) -> RunSummary:
        """Run every task not yet committed; Ctrl-C writes the summary and raises
        :class:`RunInterrupted`."""
        wall0 = time.perf_counter()
        save_rig(self.out / "rig.json", self.dataset.rig)
        done = self._done
        if self.dataset.is_live:
            if self.options.policy != "newest":
                raise EdgereconError("live streams take the newest frames: use --policy newest")
            schedule = self._live_schedule(done)
        else:
            schedule = self._schedule(self.options.frames.indices(self.dataset.num_frames), done)
        try:
            with self.dataset.open_frames(missing="skip_camera") as source:
                try:
                    for t in schedule:
                        self._task(source, t, self.totals.tasks)
                        repaired = self._repair_due()
                        if repaired is not None:
                            scene = self._scene_model()
                            summary = self._finish(wall0, interrupted=True)
                            raise RepairDue(summary, self.metrics, repaired, scene)
                finally:
                    if self.dataset.is_live:
                        self._stream_stats(source)
        except KeyboardInterrupt:
            summary = self._finish(wall0, interrupted=True)
            raise RunInterrupted(summary, self.metrics) from None
        return self._finish(wall0, interrupted=False)

    def _finish(self, wall0: float, *, interrupted: bool) -> RunSummary:
        self._save_views()
        summary = self.summarise()
        summary.interrupted = interrupted
        summary.wall_s = round(time.perf_counter() - wall0, 3)
        try:
            status = self.engine.status()
            summary.backgrounds_pushed = int(status.get("backgrounds_received", 0))
            summary.snapshots_pushed = int(status.get("snapshots_received", 0))
            summary.bg_version = list(status.get("bg_version", [0, 0]))
            summary.backend_restarts = int(status.get("backend_restarts", 0))
            summary.abandoned_threads = [str(w) for w in status.get("abandoned_threads", [])]
            backend = status.get("backend") or {}
            summary.calibration = self._repaired_rig(
                self._with_turned_back(backend.get("calibration"))
            )
            if summary.abandoned_threads:
                logger.warning(
                    "%d abandoned thread(s) still running at the end: %s",
                    len(summary.abandoned_threads),
                    "; ".join(summary.abandoned_threads),
                )
        except Exception as exc:  # the summary is written even when an engine is gone
            logger.warning("engine status unavailable for the summary: %s", exc)
        atomic_write_text(self.out / "summary.json", json.dumps(summary.to_dict(), indent=2) + "\n")
        return summary

    def _repair_due(self) -> Rig | None:
        """With ``adopt_repairs``: the rig of the back-end's confirmed repair, when there is
        one (asked after each task: a look-up in the back-end's counters)."""
        if not self.options.adopt_repairs:
            return None
        if not self.dataset.is_live and self._next_bound() is None:
            return None  # the last task: rig.repaired.json is written at the end anyway
        try:
            verdict = (self.engine.status().get("backend") or {}).get("calibration") or {}
            rig = verdict.get("repaired_rig") if verdict.get("confirmed") else None
            return None if rig is None else Rig.from_dict(rig)
        except Exception as exc:  # a back-end that does not answer: no repair now
            logger.debug("calibration verdict unavailable: %s", exc)
            return None

    def _scene_model(self) -> SceneModel | None:
        """The front-end's background models now, without their static scenes (None when
        the engine cannot give them: the next run learns them again)."""
        try:
            model = self.engine.scene_model()
        except Exception as exc:
            logger.warning("the background models could not be handed on: %s", exc)
            return None
        return None if model is None else model.without_geometry()

    def _with_turned_back(self, verdict: dict[str, Any] | None) -> dict[str, Any] | None:
        """The back-end's last calibration verdict, with the rig whose cameras that were
        knocked (not those that kept moving) are re-aimed by the turn taken off their frames
        since (``Stabiliser.steady_turn``) as its repair, when it has none of its own (its
        checks saw the frames turned back: they fit), and one warning that says so."""
        rig = self.dataset.rig
        turns = {}
        for i in sorted(self._stabiliser.cameras):
            if self._moves_said.get(rig[i].name, 0) > _MOVES_SAID:
                continue  # a camera that sways: no pose of its own
            R = self._stabiliser.steady_turn(i)
            if R is not None:
                turns[i] = R
        if not turns or (verdict is not None and "repaired_rig" in verdict):
            return verdict
        cams = list(rig)
        for i, R in turns.items():
            cams[i] = dataclasses.replace(cams[i], R=R @ cams[i].R, t=R @ cams[i].t)
        repair = "; ".join(
            f"{rig[i].name} re-aimed by {rotation_angle_deg(R, np.eye(3)):.2f} degrees "
            "(the turn taken off its frames since it moved)"
            for i, R in turns.items()
        )
        logger.warning(
            "%s: the rig so re-aimed is written to %s in the run's folder (`edgerecon calib "
            "--dataset DIR --adopt OUT/%s` names it in the dataset; `--resume` then goes on "
            "with it, its frames no longer turned back)",
            repair,
            REPAIRED_RIG_FILE,
            REPAIRED_RIG_FILE,
        )
        out: dict[str, Any] = dict(verdict or {"time": None, "short": "not checked"})
        out["repair"] = repair
        out["repaired_rig"] = dataclasses.replace(rig, cameras=tuple(cams)).in_world().to_dict()
        return out

    def _repaired_rig(self, verdict: dict[str, Any] | None) -> dict[str, Any] | None:
        """The back-end's last calibration verdict for the summary: a rig its repair made
        fit is written to ``rig.repaired.json`` (named in the verdict's
        ``repaired_rig_file``); a verdict without one removes an older one there (none
        made: it stays)."""
        if verdict is None:
            return None
        path = self.out / REPAIRED_RIG_FILE
        verdict = dict(verdict)
        rig = verdict.pop("repaired_rig", None)
        try:
            if rig is None:
                path.unlink(missing_ok=True)
            else:
                save_rig(path, Rig.from_dict(rig))
                verdict["repaired_rig_file"] = REPAIRED_RIG_FILE
        except (OSError, ValueError) as exc:
            logger.warning("%s: %s", path, exc)
        return verdict

    def _task(self, source: FrameSource, t: int, task: int) -> None:
        for when, kind, seconds in self.options.faults:
            if when == task:
                role = "front-end" if kind == "hang" else "back-end"
                logger.warning("drill: injecting %s fault %r before task %d", role, kind, task)
                try:
                    if kind == "hang":
                        self.engine.inject_frontend_fault(kind)
                    else:
                        self.engine.inject_backend_fault(kind, seconds)
                except Exception as exc:  # a drill must not end the run either
                    logger.error("drill: injecting %r failed: %s", kind, exc)
        out = self._run_one(source, t, task)
        m = out.metrics
        self._learn_ahead(source, m)
        try:
            if m.status == "ok":
                self._score(m, t, out)
                rig = self.dataset.rig
                version = (m.bg_epoch, m.bg_version)
                cloud = self.options.write_clouds and out.foreground is not None
                bg_points = None if out.background is None else len(out.background)
                room = self.retention.make_room(version, bg_points, cloud=cloud)
                m.cloud_skipped = cloud and not room
                if out.background is not None:  # before the task that refers to it
                    self.folder.write_background(
                        out.background,
                        version,
                        **ply_frame(rig),
                    )
                    self.retention.background_written(version, len(out.background))
                if cloud and room and out.foreground is not None:
                    self.folder.write_task_cloud(
                        t,
                        foreground_part(out.foreground, m.bg_version),
                        np.zeros(0, np.int64) if out.bg_dropped is None else out.bg_dropped,
                        version,
                        **ply_frame(rig),
                    )
                    self.retention.cloud_written(t, version)
                    m.cloud_written = True
            # Background, cloud, metrics line, then the run state: the commit point.
            m.rss_mb = resident_mb()
            self.folder.append_metrics(m)
            self._keep(m)
            RunState(
                dataset=self.identity,
                frames=(
                    self.options.frames.start,
                    self.options.frames.stop,
                    self.options.frames.step,
                ),
                policy=self.options.policy,
                deadline_s=self.deadline_s,
                tasks_done=self.totals.tasks,
                frontend=self.engine.state(),
                original=self.original,
                recalibrations=self.recalibrations,
            ).save(self.out)
            if m.status == "ok":  # after the commit point: older clouds beyond --keep-clouds
                self.retention.committed((m.bg_epoch, m.bg_version))
            if time.monotonic() - self._views_saved >= _VIEWS_EVERY_S:
                self._save_views()
        except OSError as exc:  # disk full, folder removed: stop with what is committed
            raise EdgereconError(
                f"cannot write the outputs of task {task} to {self.out} ({exc}); the run "
                f"stopped after {self.totals.tasks} committed tasks: fix it and --resume"
            ) from None
        if self.on_task is not None:
            self.on_task(m)

    def _run_one(self, source: FrameSource, t: int, task: int) -> TaskOutput:
        moved: list[dict[str, Any]] = []
        try:
            # The frames of the background models' scheduled updates due before t, read
            # first (sources stream forwards), unusable cameras left out as in tasks.
            updates = self._update_frames(source, t)
            frames = source.read(t)
            defects = frame_defects(frames, self.frame_check)
            frames = without_defective(frames, defects)
            named = {self.dataset.rig[i].name: d for i, d in enumerate(defects) if d is not None}
            self._note_defects(t, named)
            self._note_frozen(t, frames)
            moved = self._note_moved(t, frames)
            frames, turned = self._stabiliser.apply(frames)
            plan = self.engine.plan(t)
            out = self.engine.run_task(frames, plan, task, named, updates)
            out.metrics.sync_spread_s = frames.sync_spread_s
            out.metrics.frozen_cameras = [
                self.dataset.rig[i].name for i in sorted(self._frozen.frozen)
            ]
            out.metrics.camera_moves = moved
            out.metrics.stabilised = {self.dataset.rig[i].name: d for i, d in turned.items()}
            return out
        except Exception as exc:  # any stage, any engine: a failed record, never a dead run
            error = describe_exception(exc)
            logger.error("task %d (time %d) failed: %s", task, t, error)
            logger.debug("traceback", exc_info=exc)
            m = TaskMetrics.failed(task=task, time_index=t, error=error, deadline_s=self.deadline_s)
            m.camera_moves = moved
            return TaskOutput(metrics=m, foreground=None)

    def _learn_ahead(self, source: FrameSource, m: TaskMetrics) -> None:
        """After a task's cloud, before its commit: the scheduled background updates due
        before the next task whose frames have arrived, applied now rather than on the next
        task's critical path (the models at its time index are the same, so are its masks).
        Their seconds are this task's ``scene_update_ahead`` stage (after its cloud). A
        failure here is logged; the next task applies what is left itself."""
        bound = self._next_bound()
        if bound is None:  # the last task, or a live stream (its schedule gives none)
            return
        try:
            seconds = self.engine.learn_updates(self._update_frames(source, bound))
        except Exception as exc:  # the next task applies the updates itself
            logger.warning("background updates between tasks: %s", describe_exception(exc))
            return
        if seconds > 0.0:
            m.stages["scene_update_ahead"] = round(seconds, 6)

    def _update_frames(self, source: FrameSource, t: int) -> list[FrameSet]:
        """The frames of the background models' scheduled updates due before ``t``, unusable
        cameras left out as in tasks; a frame that cannot be read is skipped (the schedule
        moves on without it)."""
        out = []
        for s in self.engine.pending_updates(t):
            try:
                frames = source.read(s)
            except EdgereconError as exc:
                logger.debug("background update at time %d skipped: %s", s, exc)
                continue
            frames = without_defective(frames, frame_defects(frames, self.frame_check))
            out.append(self._stabiliser.apply(frames)[0])
        return out

    def _note_defects(self, t: int, defects: dict[str, str]) -> None:
        """One warning when frames become unusable, one line when they recover."""
        if defects == self._defects:
            return
        if defects:
            logger.warning(
                "time %d: unusable frames (%s): those cameras are left out of the tasks (a "
                "task with fewer than 3 cameras gives an empty result) until they recover",
                t,
                ", ".join(f"{k} {v}" for k, v in defects.items()),
            )
        else:
            logger.warning("time %d: every camera's frames are usable again", t)
        self._defects = defects

    def _note_frozen(self, t: int, frames: FrameSet) -> None:
        """One warning when a camera's frames stop changing while the others' go on, one
        line when they change again (``quality.frames.FrozenCameras``)."""
        froze, thawed = self._frozen.update(frames)
        names = self.dataset.rig.names
        if froze:
            logger.warning(
                "time %d: camera%s %s sent the same frame for %g s while the others' changed "
                "(a stuck camera, or a stream repeating its last frame?): the tasks keep "
                "%s view of the moment it froze until it changes",
                t,
                "s" if len(froze) > 1 else "",
                ", ".join(names[i] for i in froze),
                self.frame_check.frozen_after_s,
                "their" if len(froze) > 1 else "its",
            )
        if thawed:
            logger.warning(
                "time %d: camera%s %s sent a new frame again",
                t,
                "s" if len(thawed) > 1 else "",
                ", ".join(names[i] for i in thawed),
            )

    def _save_views(self) -> None:
        """The move detector's reference views in ``views.npz`` (as of the last task); a
        failed write is said, not fatal (the views only serve a later ``--resume``)."""
        self._views_saved = time.monotonic()
        if not self.metrics:
            return
        names = self.dataset.rig.names
        views = {names[i]: v for i, v in sorted(self._moved.references().items())}
        steady = {names[i]: v for i, v in sorted(self._stabiliser.references().items())}
        moves = {n: self._moves_said.get(n, 0) for n in steady}
        if not views:
            return
        try:
            self.folder.write_views(views, self.metrics[-1].time_index, steady, moves)
        except OSError as exc:
            logger.warning("the cameras' reference views were not saved: %s", exc)

    def _restore_views(self) -> None:
        """A resumed run's move detector starts from the views saved before the stop, and
        the cameras whose frames were turned back go on being so, without their moves said
        again (the cameras placed again at this resume start afresh: their new pose is
        their view)."""
        saved = self.folder.read_views()
        if saved is None:
            return
        time_index, views, steady, moves = saved
        again = (
            set() if self.folder.recalibration is None else set(self.folder.recalibration.cameras)
        )
        names = self.dataset.rig.names
        refs = {names.index(n): v for n, v in views.items() if n in names and n not in again}
        self._moved.restore(refs)
        self._views_from = time_index
        for name, ref in steady.items():
            if name not in names or name in again or not self.frame_check.stabilise:
                continue
            cam = self.dataset.rig[names.index(name)]
            self._stabiliser.start(names.index(name), ref.astype(np.float32), cam)
            # A file from before the counts were kept: as a camera that kept moving.
            said = self._moves_said[name] = moves.get(name, _MOVES_SAID + 1)
            logger.warning(
                "%s %s before the stop: its frames are turned back onto its view as before%s",
                name,
                "kept moving" if said > _MOVES_SAID else "was knocked",
                " (its moves recorded, not said)" if said > _MOVES_SAID else "",
            )
        logger.debug(
            "the cameras' views as of time %d restored (%d cameras)", time_index, len(refs)
        )

    def _steady_from(self, camera: int, said: int) -> bool:
        """Whether ``camera``'s frames are turned back onto its view before its first move
        from now on, after a move said ``said`` times: at its first move (a knock) unless
        the run re-poses moved cameras (``adopt_repairs``: the back-end's check finds the
        new pose on its frames as they come), at the move after which it keeps moving in
        every run; a camera already turned back forgets the turns measured before this move
        (``_with_turned_back``)."""
        if camera in self._stabiliser.cameras:
            self._stabiliser.forget(camera)
            return True
        due = said == _MOVES_SAID + 1 or (said == 1 and not self.options.adopt_repairs)
        reference = self._moved.first_reference(camera)
        if not (due and self.frame_check.stabilise and reference is not None):
            return False
        assert reference is not None
        self._stabiliser.start(camera, reference, self.dataset.rig[camera])
        return True

    def _note_moved(self, t: int, frames: FrameSet) -> list[dict[str, Any]]:
        """A warning when a camera's view moved (``quality.frames.MovedCameras``), and the
        back-end asked to check the calibration on the frames from the move on at once
        (rather than at its next ``calib_check_s``), its frames turned back onto its view
        before the move from then on (``_steady_from``); the moves' records. A camera that
        keeps moving (a mount that sways, a camera held by hand) is said
        ``_MOVES_SAID`` times, then once that it keeps moving; its moves are still recorded
        (no more checks asked for: the back-end's every ``calib_check_s`` go on)."""
        records = []
        for move in self._moved.update(frames):
            cam = self.dataset.rig[move.camera]
            said = self._moves_said[cam.name] = self._moves_said.get(cam.name, 0) + 1
            image = frames.images[move.camera]
            assert image is not None
            # The turn of a pinhole camera that moves its image centre so far, and rolls it.
            focal = float(cam.K[0, 0]) * image.shape[1] / cam.width
            dx, dy = move.shift_px
            turn = math.hypot(math.degrees(math.atan2(math.hypot(dx, dy), focal)), move.roll_deg)
            records.append(
                {
                    "camera": cam.name,
                    "time_index": move.time_index,
                    "shift_px": list(move.shift_px),
                    "roll_deg": move.roll_deg,
                    "turn_deg": round(turn, 3),
                    "across_stop": move.across_stop,
                }
            )
            # A knocked camera (without --adopt-repairs, which re-poses it instead) and one
            # that keeps moving: its frames turned back onto its view before its first move.
            was = move.camera in self._stabiliser.cameras
            steady = self._steady_from(move.camera, said)
            # The frames the back-end checks: from the move on, or from this task's on when
            # they are turned back (those between the move and now went in as they came).
            since = t if steady else move.time_index
            if said == _MOVES_SAID + 1:
                logger.warning(
                    "time %d: %s's view keeps moving (%d moves; a mount that sways, a camera "
                    "held by hand? The run expects static cameras): its moves are recorded "
                    "in the tasks' camera_moves, no longer said%s",
                    t,
                    cam.name,
                    said,
                    (
                        "; its frames go on being turned back onto its view before its first move"
                        if was
                        else "; from now on each of its frames is turned back onto its view "
                        "before its first move (the turn taken off in the tasks' stabilised)"
                    )
                    if steady
                    else "",
                )
            when = (
                f"while the run was stopped (between time {self._views_from} and time "
                f"{move.time_index}, where it went on)"
                if move.across_stop
                else f"at time {move.time_index}"
            )
            logger.log(
                logging.WARNING if said <= _MOVES_SAID else logging.DEBUG,
                "time %d: %s's view moved %s (its static scene %.1f px %s, %.1f px "
                "%s, rolled %.2f degrees: about %.2f degrees of the camera); knocked, or its "
                "mount slipped? %sThe back-end checks the calibration on the frames from time "
                "%d",
                t,
                cam.name,
                when,
                abs(dx),
                "right" if dx >= 0 else "left",
                abs(dy),
                "down" if dy >= 0 else "up",
                move.roll_deg,
                turn,
                "From now on its frames are turned back onto its view before the move (a "
                "turn on its mount: the calibration fits them again; the turn taken off in "
                "the tasks' stabilised). "
                if steady and not was and said <= _MOVES_SAID
                else "",
                since,
            )
            if said > _MOVES_SAID:
                continue
            try:
                self.engine.check_calibration(since, [cam.name])
            except Exception as exc:  # a back-end that does not answer: its own check serves
                logger.debug("calibration check not requested: %s", describe_exception(exc))
        return records

    def _score(self, m: TaskMetrics, t: int, out: TaskOutput) -> None:
        if self._gt is None or self.options.ground_truth_threshold is None:
            return
        try:
            ref = self._gt.reference_cloud(t, "foreground", min_views=2)
        except EdgereconError as exc:  # ground truth of this time unreadable: no score
            logger.warning("time %d: no offline score (%s)", t, exc)
            return
        if len(ref) and out.foreground is not None:
            m.offline_fscore = fscore(out.foreground, ref, self.options.ground_truth_threshold)

    def _keep(self, m: TaskMetrics) -> None:
        self.metrics.append(m)
        keep = self.options.keep_metrics
        if keep is not None and len(self.metrics) > keep:
            del self.metrics[: len(self.metrics) - keep]
        self.totals.add(m)

    # ------------------------------------------------------------------ summary
    def summarise(self) -> RunSummary:
        t = self.totals
        s = RunSummary(
            tasks=t.tasks,
            failed=t.failed,
            degraded=t.degraded,
            empty=t.empty,
            frames_dropped=self.frames_dropped,
            deadline_s=self.deadline_s,
            deadline_share=self.deadline_share,
            original_s=None if self.original is None else self.original.seconds,
            original_node=None if self.original is None else self.original.node,
            engine=getattr(self.engine, "name", ""),
            recalibrations=[r.to_dict() for r in self.recalibrations],
            camera_moves=list(t.moves),
            stabilised={k: dict(v) for k, v in t.stabilised.items()},
            stream=dict(self._stream),
            clouds_written=t.clouds_written,
            clouds_kept=len(self.retention.kept),
            clouds_skipped=t.clouds_skipped,
            memory_mb={
                "first": t.rss_first,
                "last": t.rss_last,
                "peak": max(peak_resident_mb() or 0.0, t.rss_max) or None,
            },
        )
        reconstructed = t.time.count  # averages over the tasks that reconstructed
        if reconstructed:
            s.avg_scale = t.scale.value
            s.avg_cameras = t.cameras.value
            s.cameras_used = list(t.cameras_used)
            s.avg_time_s = t.time.value
            if s.original_s is not None:
                s.online_over_original = round(s.avg_time_s / s.original_s, 3)
            conv, misses = (
                (t.adjust_time, t.adjust_misses)
                if t.adjust_time.count
                else (t.fixed_time, t.fixed_misses)
            )
            if conv.count:
                s.avg_time_converged_s = conv.value
                s.deadline_misses_converged = misses
            s.avg_online_fscore = t.online.value if t.online.count else None
            s.avg_offline_fscore = t.offline.value if t.offline.count else None
            s.offline_threshold = self.options.ground_truth_threshold if t.offline.count else None
            s.unit = self.dataset.rig.unit
            s.search_steps = t.search_steps
            s.still_tasks = t.still_share.count
            s.avg_still_share = round(t.still_share.value, 4) if t.still_share.count else None
            s.stage_means_s = {k: round(v / reconstructed, 4) for k, v in t.stages.items()}
        return s
