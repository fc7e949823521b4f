"""Reading a run folder while the session writes it (or after it finished).

The session (``runtime.session``) writes every file atomically or by appending whole lines,
so a reader never sees a torn file: ``metrics.jsonl`` gains one JSON line per task,
a task's cloud files (``tasks/<time>/fg.ply`` and the background version they refer to)
appear (renamed into place) before its metrics line,
``rig.json`` is written when the run starts and ``summary.json`` when it ends. A fresh run in
the same folder deletes ``metrics.jsonl`` first; :meth:`RunFolder.poll` notices that (the file
shrank or was replaced) and starts over. This is all the viewer and ``edgerecon report``
need: they never talk to the running process, so they work the same for both engines and for
finished runs, and cost the critical path nothing but the disk writes it does anyway.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

from edgerecon.geometry.camera import Rig
from edgerecon.io.calibration import read_rig_json
from edgerecon.io.ply import read_ply, read_ply_meta
from edgerecon.runtime.messages import TaskMetrics
from edgerecon.runtime.state import (
    BACKGROUNDS,
    TASK_DROPPED,
    TASK_FOREGROUND,
    background_file,
    comment_background,
    task_dir,
)
from edgerecon.scene.merge import compose
from edgerecon.types import EdgereconError, PointCloud

logger = logging.getLogger(__name__)

METRICS = "metrics.jsonl"
RIG = "rig.json"
SUMMARY = "summary.json"
STATE = "state.json"
BACKGROUND = "background.ply"


def task_cloud_path(run_dir: str | os.PathLike[str], time_index: int) -> Path:
    """Where runs written before the background was stored once per version kept the merged
    cloud of the task at ``time_index`` (``RunFolder.cloud`` reads both layouts)."""
    return task_dir(run_dir, time_index) / "merged.ply"


def has_task_cloud(run_dir: str | os.PathLike[str], time_index: int) -> bool:
    """Whether the run wrote the cloud of the task at ``time_index`` (either layout)."""
    d = task_dir(run_dir, time_index)
    return (d / TASK_FOREGROUND).exists() or (d / "merged.ply").exists()


class RunFolder:
    """Incremental reader of a run folder (see module docstring).

    ``poll()`` returns the tasks recorded since the previous call; ``tasks`` holds them all.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.tasks: list[TaskMetrics] = []
        self.resets = 0
        """How many times a fresh run replaced the metrics being followed."""
        self._offset = 0
        self._inode: int | None = None
        self._partial = b""
        self._rig: Rig | None = None
        self._rig_tried = False
        self._rig_file: tuple[int, int, int] | None = None  # rig.json's (inode, mtime, size)
        self._bg_cache: tuple[tuple[int, int], PointCloud] | None = None

    @property
    def metrics_path(self) -> Path:
        return self.path / METRICS

    def exists(self) -> bool:
        """Whether the folder looks like a run (or the start of one)."""
        return any((self.path / name).exists() for name in (METRICS, RIG, STATE, SUMMARY))

    def poll(self) -> list[TaskMetrics]:
        """Tasks appended to ``metrics.jsonl`` since the last call (empty when none). When the
        file was replaced or shrank (a new run in this folder), ``tasks`` restarts."""
        try:
            st = os.stat(self.metrics_path)
        except FileNotFoundError:
            if self._offset or self.tasks:
                self._reset()
            return []
        if (self._inode is not None and st.st_ino != self._inode) or st.st_size < self._offset:
            self._reset()
        self._inode = st.st_ino
        if st.st_size == self._offset:
            return []
        with open(self.metrics_path, "rb") as f:
            f.seek(self._offset)
            data = f.read(st.st_size - self._offset)
        self._offset += len(data)
        data = self._partial + data
        lines = data.split(b"\n")
        self._partial = lines.pop()  # b"" after a complete last line
        new: list[TaskMetrics] = []
        for line in lines:
            if not line.strip():
                continue
            try:
                new.append(TaskMetrics.from_dict(json.loads(line)))
            except (json.JSONDecodeError, TypeError, UnicodeDecodeError):
                logger.warning("%s: skipping an unreadable line", self.metrics_path)
        self.tasks.extend(new)
        return new

    def _reset(self) -> None:
        logger.info("%s: a new run started in this folder", self.path)
        self.tasks = []
        self._offset = 0
        self._partial = b""
        self._inode = None
        self._rig = None
        self._rig_tried = False
        self._rig_file = None
        self.resets += 1

    # ------------------------------------------------------------------ files
    def rig(self) -> Rig | None:
        """The run's rig: ``rig.json`` (written by the session; read again when it is
        replaced: a resume with cameras placed again), else the dataset named in
        ``state.json`` (older runs); None when neither is readable."""
        try:
            st = (self.path / RIG).stat()
            current: tuple[int, int, int] | None = (st.st_ino, st.st_mtime_ns, st.st_size)
        except OSError:
            current = None
        if current is not None and current != self._rig_file:
            self._rig_tried = False
        if self._rig_tried:
            return self._rig
        self._rig_tried = True
        try:
            if current is not None:
                self._rig_file = current  # a file that does not read is tried once
                self._rig = read_rig_json(self.path / RIG)
            elif (self.path / STATE).exists():
                from edgerecon.io.dataset import open_dataset

                state = json.loads((self.path / STATE).read_text())
                self._rig = open_dataset(state["dataset"]).rig
        except (EdgereconError, OSError, KeyError, json.JSONDecodeError) as exc:
            logger.warning("%s: no rig for the viewer (%s)", self.path, exc)
        return self._rig

    def cloud(self, time_index: int) -> PointCloud | None:
        """The merged cloud of the task at ``time_index``, None when it was not written (or
        was removed since: ``runtime.retention``):
        the task's foreground, then its background version without the points the
        foreground overrode (``scene.merge.compose``; the session writes the parts,
        ``runtime.state.OutputFolder.write_task_cloud``), or a run's older ``merged.ply``."""
        d = task_dir(self.path, time_index)
        try:
            if (d / "merged.ply").exists():
                return read_ply(d / "merged.ply")
            if not (d / TASK_FOREGROUND).exists():
                return None
            version = comment_background(read_ply_meta(d / TASK_FOREGROUND).comments)
            if version is None:
                raise EdgereconError(f"{d / TASK_FOREGROUND}: no background version in its header")
            foreground = read_ply(d / TASK_FOREGROUND)
            dropped = np.load(d / TASK_DROPPED)
            background = self._background_version(version)
        except (EdgereconError, OSError, ValueError) as exc:
            if not (d / TASK_FOREGROUND).exists():  # removed meanwhile (runtime.retention)
                logger.debug("%s: task %d: %s", self.path, time_index, exc)
            else:
                logger.warning("%s: task %d: %s", self.path, time_index, exc)
            return None
        return compose(foreground, background, bg_version=version[1], dropped=dropped)

    def _background_version(self, version: tuple[int, int]) -> PointCloud:
        """The background of ``version`` (empty for v0.0: no background yet); the last one
        read is kept (consecutive tasks share their background)."""
        if self._bg_cache is not None and self._bg_cache[0] == version:
            return self._bg_cache[1]
        if version == (0, 0):
            cloud = PointCloud.empty()
        else:
            cloud = read_ply(self.path / BACKGROUNDS / background_file(version))
        self._bg_cache = (version, cloud)
        return cloud

    def background(self) -> PointCloud | None:
        """The newest background the run has written, None before the first."""
        path = self.path / BACKGROUND
        try:
            return read_ply(path) if path.exists() else None
        except EdgereconError as exc:
            logger.warning("%s", exc)
            return None

    def summary(self) -> dict[str, Any] | None:
        """``summary.json`` of a finished run (None while it runs)."""
        path = self.path / SUMMARY
        try:
            data = json.loads(path.read_text()) if path.exists() else None
        except (OSError, json.JSONDecodeError):
            return None
        return data if isinstance(data, dict) else None

    def original_s(self) -> float | None:
        """The original pipeline's time the run measured (``--deadline P%``): from
        ``summary.json``, or while the run goes on from ``state.json``; None when it did
        not measure it."""
        summary = self.summary()
        if summary is not None:
            value = summary.get("original_s")
        else:
            try:
                original = json.loads((self.path / STATE).read_text()).get("original")
            except (OSError, json.JSONDecodeError, AttributeError):
                return None
            value = original.get("seconds") if isinstance(original, dict) else None
        return float(value) if isinstance(value, int | float) and value > 0 else None

    @property
    def finished(self) -> bool:
        return (self.path / SUMMARY).exists()

    def newest_with_cloud(self, upto: int | None = None) -> TaskMetrics | None:
        """The newest task (at or before position ``upto`` in ``tasks``) whose merged cloud
        exists."""
        stop = len(self.tasks) if upto is None else min(upto + 1, len(self.tasks))
        for m in reversed(self.tasks[:stop]):
            if m.status == "ok" and has_task_cloud(self.path, m.time_index):
                return m
        return None


def read_run(path: str | os.PathLike[str]) -> RunFolder:
    """A ``RunFolder`` with every task recorded so far; ``EdgereconError`` when the folder
    is not a run."""
    run = RunFolder(path)
    if not run.path.is_dir():
        raise EdgereconError(f"run folder not found: {run.path}")
    if not run.metrics_path.exists():
        raise EdgereconError(
            f"{run.path}: not a run folder (no {METRICS}; `edgerecon run --out DIR` writes one)"
        )
    run.poll()
    return run
