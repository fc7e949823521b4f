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

Outputs in ``out_dir`` (each written atomically, so a crash never leaves a torn file):

* ``metrics.jsonl``: one JSON line per task (:class:`TaskMetrics`), failed tasks included;
* ``tasks/<time>/merged.ply``: the merged cloud of each task (label and ``bg_version`` per point);
* ``background.ply``: the newest background the front-end has merged;
* ``rig.json``: the rig (written when the run starts; the viewer draws its cameras);
* ``state.json``: the controller's state and progress, for ``--resume``;
* ``summary.json``: the run's summary (the paper's Table III).

``--resume`` continues after the last task recorded in ``metrics.jsonl`` with the saved
controller state and background.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from edgerecon.io.calibration import save_rig
from edgerecon.io.dataset import Dataset
from edgerecon.io.ply import atomic_write_text, read_ply, write_ply
from edgerecon.quality.metrics import fscore
from edgerecon.runtime.messages import TaskMetrics
from edgerecon.types import BACKGROUND_LABEL, EdgereconError

logger = logging.getLogger(__name__)

STATE_FORMAT = "edgerecon-run-state"


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
    """Write each task's merged cloud (tasks/<time>/merged.ply)."""
    ground_truth_threshold: float | None = None
    """When the dataset has ground truth: score each task's foreground against it at this
    distance (rig units) — the offline F-score. None = no offline scoring."""
    resume: bool = False
    duration_s: float | None = None
    """Live streams: stop starting tasks after this many seconds (None: until ``frames``'s
    stop, or Ctrl-C)."""
    fault: tuple[int, str, float] | None = None
    """Drill: (task number, fault kind, seconds) injected into the back-end before that task."""

    def __post_init__(self) -> None:
        if self.policy not in ("all", "newest"):
            raise ValueError(f"policy must be 'all' or 'newest', got {self.policy!r}")
        if self.duration_s is not None and not self.duration_s > 0:
            raise ValueError(f"duration must be > 0 seconds, got {self.duration_s}")


@dataclass
class RunSummary:
    """The run's aggregate (the shape of the paper's Table III, plus robustness counts)."""

    tasks: int = 0
    failed: int = 0
    degraded: int = 0
    frames_dropped: int = 0
    avg_scale: float = math.nan
    avg_cameras: float = math.nan
    cameras_used: list[int] = field(default_factory=list)
    avg_time_s: float = math.nan
    avg_time_converged_s: float = math.nan
    """Average critical path after the search ended (adjust phase)."""
    deadline_s: float = math.nan
    deadline_misses_converged: int = 0
    avg_online_fscore: float | None = None
    avg_offline_fscore: float | None = None
    backgrounds_pushed: int = 0
    search_steps: int = 0
    stage_means_s: dict[str, float] = field(default_factory=dict)
    engine: str = ""
    wall_s: float = 0.0
    stream: dict[str, Any] = field(default_factory=dict)
    """Live streams: the source's counts (``StreamFrameSource.stats``) and the tasks' sync
    spread (mean / max seconds)."""

    def to_dict(self) -> dict[str, Any]:
        d = dict(self.__dict__)
        for k, v in d.items():
            if isinstance(v, float) and not math.isfinite(v):
                d[k] = None
        return d


class Session:
    """Runs tasks on an engine and keeps the run's files (see module docstring)."""

    def __init__(
        self,
        dataset: Dataset,
        engine: Any,
        options: SessionOptions,
        out_dir: str | Path,
        *,
        deadline_s: float,
        on_task: Callable[[TaskMetrics], None] | None = None,
    ) -> None:
        self.dataset = dataset
        self.engine = engine
        self.options = options
        self.out = Path(out_dir)
        self.deadline_s = deadline_s
        self.on_task = on_task
        self.metrics: list[TaskMetrics] = []
        self.frames_dropped = 0
        self._gt: Any = None
        self._bg_written = 0
        self._stream: dict[str, Any] = {}
        if options.ground_truth_threshold is not None and dataset.ground_truth is not None:
            from edgerecon.synth import GroundTruth

            self._gt = GroundTruth.open(dataset.root)

    # ------------------------------------------------------------------ resume
    def load_previous(self) -> set[int]:
        """Metrics of earlier runs in ``out_dir`` (for ``--resume``); returns the timestamps
        already done."""
        path = self.out / "metrics.jsonl"
        if not path.exists():
            return set()
        done = set()
        for line in path.read_text().splitlines():
            if not line.strip():
                continue
            try:
                m = TaskMetrics.from_dict(json.loads(line))
            except (json.JSONDecodeError, TypeError):
                logger.warning("%s: skipping an unreadable line", path)
                continue
            self.metrics.append(m)
            done.add(m.time_index)
        return done

    # ------------------------------------------------------------------ the loop
    def _schedule(self, indices: list[int], done: set[int]) -> Iterator[int]:
        todo = [t for t in indices if t not in done]
        if self.options.policy == "all":
            yield from todo
            return
        fps = self.options.arrival_fps or (self.dataset.fps or 25.0) / self.options.frames.step
        start = time.monotonic()
        pos = 0
        while pos < len(todo):
            arrived = int((time.monotonic() - start) * fps)
            newest = min(max(arrived, pos), len(todo) - 1)
            self.frames_dropped += newest - pos
            yield todo[newest]
            pos = newest + 1

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
        spread = [m.sync_spread_s for m in self.metrics if m.sync_spread_s is not None]
        self._stream = {
            **stats,
            "sync_spread_mean_s": float(np.mean(spread)) if spread else None,
            "sync_spread_max_s": float(np.max(spread)) if spread else None,
        }

    def run(self) -> RunSummary:
        wall0 = time.perf_counter()
        self.out.mkdir(parents=True, exist_ok=True)
        save_rig(self.out / "rig.json", self.dataset.rig)
        done = self.load_previous() if self.options.resume else set()
        if not self.options.resume:
            for name in ("metrics.jsonl", "state.json", "summary.json"):
                (self.out / name).unlink(missing_ok=True)
        if self.dataset.is_live:
            if self.options.policy != "newest":
                raise EdgereconError("live streams take the newest frames: use --policy newest")
            schedule = self._live_schedule(done)
        else:
            indices = self.options.frames.indices(self.dataset.num_frames)
            if not indices:
                raise EdgereconError(
                    f"--frames selects no timestamp of {self.dataset.name} "
                    f"({self.dataset.num_frames} frames)"
                )
            schedule = self._schedule(indices, done)
        task = len(self.metrics)
        with self.dataset.open_frames(missing="skip_camera") as source:
            for t in schedule:
                if self.options.fault is not None and self.options.fault[0] == task:
                    _, kind, seconds = self.options.fault
                    logger.warning("drill: injecting back-end fault %r before task %d", kind, task)
                    self.engine.inject_backend_fault(kind, seconds)
                m = self._run_one(source, t, task)
                self.metrics.append(m)
                self._append_metrics(m)
                self._save_state(task)
                if self.on_task is not None:
                    self.on_task(m)
                task += 1
            if self.dataset.is_live:
                self._stream_stats(source)
        summary = self.summarise()
        summary.wall_s = round(time.perf_counter() - wall0, 3)
        atomic_write_text(self.out / "summary.json", json.dumps(summary.to_dict(), indent=2) + "\n")
        return summary

    def _run_one(self, source: Any, t: int, task: int) -> TaskMetrics:
        try:
            frames = source.read(t)
            plan = self.engine.plan(t)
            out = self.engine.run_task(frames, plan, task)
        except EdgereconError as exc:
            logger.error("task %d (time %d) failed: %s", task, t, exc)
            return TaskMetrics(
                task=task,
                time_index=t,
                status="failed",
                error=str(exc),
                deadline_s=self.deadline_s,
                wall_time=time.time(),
            )
        m = out.metrics
        m.sync_spread_s = frames.sync_spread_s
        if self._gt is not None and self.options.ground_truth_threshold is not None:
            ref = self._gt.reference_cloud(t, "foreground", min_views=2)
            m.offline_fscore = (
                fscore(out.foreground, ref, self.options.ground_truth_threshold)
                if len(ref)
                else None
            )
        if self.options.write_clouds:
            write_ply(self.out / "tasks" / f"{t:06d}" / "merged.ply", out.merged)
        if m.bg_version > self._bg_written and out.merged.labels is not None:
            write_ply(
                self.out / "background.ply",
                out.merged.select(out.merged.labels == BACKGROUND_LABEL),
            )
            self._bg_written = m.bg_version
        return m

    def _append_metrics(self, m: TaskMetrics) -> None:
        path = self.out / "metrics.jsonl"
        line = json.dumps(m.to_dict()) + "\n"
        # Append + fsync: a crash loses at most the task in progress, never earlier lines.
        with open(path, "a", encoding="utf-8") as f:
            f.write(line)
            f.flush()
            os.fsync(f.fileno())

    def _save_state(self, task: int) -> None:
        state = {
            "format": STATE_FORMAT,
            "version": 1,
            "dataset": str(self.dataset.root),
            "last_task": task,
            "bg_version": self._bg_written,
            "controller": self.engine.controller_state(),
        }
        atomic_write_text(self.out / "state.json", json.dumps(state) + "\n")

    # ------------------------------------------------------------------ summary
    def summarise(self) -> RunSummary:
        ok = [m for m in self.metrics if m.status == "ok"]
        s = RunSummary(
            tasks=len(self.metrics),
            failed=len(self.metrics) - len(ok),
            degraded=sum(m.degraded for m in ok),
            frames_dropped=self.frames_dropped,
            deadline_s=self.deadline_s,
            engine=getattr(self.engine, "name", ""),
            stream=dict(self._stream),
        )
        if ok:
            s.avg_scale = float(np.mean([m.scale for m in ok]))
            s.avg_cameras = float(np.mean([m.num_cameras for m in ok]))
            s.cameras_used = ok[-1].camera_ids
            s.avg_time_s = float(np.mean([m.critical_path_s for m in ok]))
            conv = [m for m in ok if m.phase == "adjust"] or [m for m in ok if m.phase == "fixed"]
            if conv:
                s.avg_time_converged_s = float(np.mean([m.critical_path_s for m in conv]))
                s.deadline_misses_converged = sum(not m.deadline_met for m in conv)
            on = [m.online_fscore for m in ok if m.online_fscore is not None]
            off = [m.offline_fscore for m in ok if m.offline_fscore is not None]
            s.avg_online_fscore = float(np.mean(on)) if on else None
            s.avg_offline_fscore = float(np.mean(off)) if off else None
            s.backgrounds_pushed = max(m.bg_version for m in ok)
            s.search_steps = max(m.search_steps for m in ok)
            stages: dict[str, list[float]] = {}
            for m in ok:
                for k, v in m.stages.items():
                    stages.setdefault(k, []).append(v)
            s.stage_means_s = {k: round(float(np.sum(v)) / len(ok), 4) for k, v in stages.items()}
        return s

    def previous_background(self) -> tuple[Any, int] | None:
        """The background saved by an earlier run (for ``--resume``), with its version."""
        path = self.out / "background.ply"
        state = self.out / "state.json"
        if not (path.exists() and state.exists()):
            return None
        version = int(json.loads(state.read_text()).get("bg_version", 0))
        self._bg_written = version
        return read_ply(path), version
