"""What a long run keeps on disk: the newest task clouds, within a count and the free space.

A run writes every task's cloud (``tasks/<time>/``: about 1 MB per task on a 4-camera 720p
rig, 2 MB/s at two tasks per second, 7 GB an hour) and every background version a task
merged with (``backgrounds/``, tens of MB each on an HD rig). A live stream runs until it is
stopped: on an edge device's disk the run would end with a full disk. The session applies
two limits at each task's commit (:class:`CloudRetention`):

* **a count** (``keep_clouds``, ``--keep-clouds N``): after a task is committed, the clouds
  of all but the newest N tasks that wrote one are removed (None: all are kept);
* **the free space** (``min_free_mb``, ``--min-free-mb``, default 256 MiB): before a task's
  files are written, when the output's file system would be left with less than that, the
  background versions no kept task refers to and then the oldest task clouds are removed
  (never the newest one) until it would not (one warning, again every ten minutes while it
  goes on); when that is not enough the task's cloud is not written (counted; said the
  same way). Its metrics line and the run state, a few kB,
  are written either way, and a background the task took is written too (``--resume``
  needs the newest): should that fail, the run stops as before, every committed task kept.

Either way a background version goes with the last kept task that refers to it, except the
newest (``--resume`` restores it; ``background.ply`` is a hard link to it). A task whose
cloud is gone keeps its metrics line: the viewer and ``edgerecon report`` show the tasks
that have a cloud (``viewer.rundir.has_task_cloud``), and ``export`` of a removed task says
it is not there. The run's summary counts the clouds removed and the clouds not written.
"""

from __future__ import annotations

import logging
import math
import os
import re
import shutil
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

from edgerecon.runtime.state import (
    BACKGROUNDS,
    TASK_DROPPED,
    TASK_FOREGROUND,
    background_file,
    task_dir,
)

logger = logging.getLogger(__name__)

Version = tuple[int, int]

#: Bytes per point of a background file until one has been written (binary PLY: xyz,
#: colour, normal-free attributes; measured files are 27-31 bytes per point).
_BACKGROUND_BYTES_PER_POINT = 32.0
#: Tasks whose written bytes estimate the next one's (the largest of them).
_RECENT_TASKS = 8
#: A run that keeps removing clouds for space says so at most this often (seconds).
_SAY_EVERY_S = 600.0
_VERSION_FILE = re.compile(r"^v(\d+)\.(\d+)\.ply$")


@dataclass(frozen=True)
class RetentionConfig:
    """How many task clouds a run keeps and how much disk it leaves free."""

    keep_clouds: int | None = None
    """Keep the clouds of the newest N tasks that wrote one (None: all)."""
    min_free_mb: float = 256.0
    """Free space (MiB) the run leaves on its output's file system: older clouds go first,
    then the task's own cloud is not written (0: no check)."""

    def __post_init__(self) -> None:
        if self.keep_clouds is not None and self.keep_clouds < 1:
            raise ValueError(f"keep_clouds must be >= 1 (or None: all), got {self.keep_clouds}")
        if not self.min_free_mb >= 0:
            raise ValueError(f"min_free_mb must be >= 0, got {self.min_free_mb}")


def free_bytes(path: Path) -> int:
    """Free bytes for an unprivileged writer on the file system of ``path``."""
    return int(shutil.disk_usage(path).free)


class CloudRetention:
    """The task clouds a run has on disk, oldest first, and the two limits on them (see the
    module docstring). The session calls :meth:`make_room` before a task's files,
    :meth:`cloud_written` / :meth:`background_written` after each and :meth:`committed`
    after the task's commit point."""

    def __init__(
        self,
        root: str | os.PathLike[str],
        config: RetentionConfig | None = None,
        kept: Iterable[tuple[int, Version]] = (),
        *,
        disk_free: Callable[[Path], int] | None = None,
    ) -> None:
        self.root = Path(root)
        self.config = config or RetentionConfig()
        self._kept: deque[tuple[int, Version]] = deque(
            (t, v) for t, v in kept if (task_dir(self.root, t) / TASK_FOREGROUND).exists()
        )
        self._disk_free = disk_free
        """Free bytes of a folder's file system (None: ``free_bytes``)."""
        self._task_bytes: deque[int] = deque(maxlen=_RECENT_TASKS)
        self._bytes_per_point = _BACKGROUND_BYTES_PER_POINT
        self._short = False  # in a stretch of tasks whose cloud was not written
        self._said: dict[str, float] = {}  # when each warning was last given (monotonic)
        self.pruned = 0
        """Task clouds removed (either limit)."""
        self.skipped = 0
        """Task clouds not written for lack of space."""

    @property
    def kept(self) -> list[int]:
        """Time indices of the task clouds on disk, oldest first."""
        return [t for t, _ in self._kept]

    # ------------------------------------------------------------------ the session's calls
    def make_room(self, version: Version, background_points: int | None, *, cloud: bool) -> bool:
        """Before the files of a task that merges with background ``version`` (and writes
        that background, of ``background_points`` points, when not None): free space for
        them (see the module docstring). Returns whether the task's cloud may be written
        (``cloud``: the task has one to write)."""
        floor = self.config.min_free_mb * 2**20
        if floor <= 0:
            return cloud
        need = floor + (max(self._task_bytes, default=0) if cloud else 0)
        if background_points is not None:
            need += background_points * self._bytes_per_point
        free = self._free()
        if free is None or free >= need:
            if self._short:
                logger.info("disk: %s has room again; task clouds are written", self.root)
                self._short = False
            return cloud
        before = self.pruned
        free = self._prune_backgrounds(version, free)
        while free < need and len(self._kept) > 1:
            self._remove_task(*self._kept.popleft())
            free = self._prune_backgrounds(version, self._free() or 0)
        if self.pruned > before:
            self._say(
                "pruned",
                "disk: under %.0f MiB free on %s: the oldest task clouds are removed (%d so "
                "far, %d kept; --min-free-mb sets the floor)",
                self.config.min_free_mb,
                self.root,
                self.pruned,
                len(self._kept),
            )
        if not cloud:
            return False
        if free >= need:
            return True
        self.skipped += 1
        if not self._short:
            self._say(
                "short",
                "disk: %s has %.0f MiB free, under --min-free-mb %.0f with this task's files: "
                "task clouds are not written until there is room (metrics go on)",
                self.root,
                free / 2**20,
                self.config.min_free_mb,
            )
        self._short = True
        return False

    def _say(self, what: str, message: str, *args: object) -> None:
        """A warning, or a debug line when the same ``what`` was warned of within
        ``_SAY_EVERY_S``."""
        now = time.monotonic()
        quiet = now - self._said.get(what, -math.inf) < _SAY_EVERY_S
        (logger.debug if quiet else logger.warning)(message, *args)
        if not quiet:
            self._said[what] = now

    def cloud_written(self, time_index: int, version: Version) -> None:
        """A task's cloud is on disk (its bytes estimate the next tasks')."""
        d = task_dir(self.root, time_index)
        size = 0
        for name in (TASK_FOREGROUND, TASK_DROPPED):
            try:
                size += (d / name).stat().st_size
            except OSError:
                pass
        self._task_bytes.append(size)
        self._kept.append((time_index, version))

    def background_written(self, version: Version, points: int) -> None:
        """The background of ``version`` is on disk (its bytes per point estimate the next
        ones')."""
        try:
            size = (self.root / BACKGROUNDS / background_file(version)).stat().st_size
        except OSError:
            return
        if points > 0:
            self._bytes_per_point = max(1.0, size / points)

    def committed(self, version: Version) -> None:
        """After a task's commit (it merged with ``version``): the count limit."""
        keep = self.config.keep_clouds
        if keep is None or len(self._kept) <= keep:
            return
        while len(self._kept) > keep:
            self._remove_task(*self._kept.popleft())
        self._prune_backgrounds(version, 0)

    # ------------------------------------------------------------------ removal
    def _free(self) -> int | None:
        try:
            return (self._disk_free or free_bytes)(self.root)
        except OSError as exc:
            logger.debug("disk: free space of %s unknown (%s)", self.root, exc)
            return None

    def _remove_task(self, time_index: int, version: Version) -> None:
        d = task_dir(self.root, time_index)
        try:
            # The foreground first: without it the task has no cloud (``has_task_cloud``)
            # whatever an interrupted removal leaves.
            (d / TASK_FOREGROUND).unlink(missing_ok=True)
            shutil.rmtree(d, ignore_errors=True)
        except OSError as exc:
            logger.warning("disk: cannot remove %s (%s)", d, exc)
            return
        self.pruned += 1

    def _prune_backgrounds(self, current: Version, free: int) -> int:
        """Remove the background versions that no kept task refers to, except the newest
        and ``current``; returns ``free`` plus the bytes removed."""
        folder = self.root / BACKGROUNDS
        try:
            names = os.listdir(folder)
        except OSError:
            return free
        versions: dict[Version, str] = {}
        for name in names:
            match = _VERSION_FILE.match(name)
            if match:
                versions[int(match[1]), int(match[2])] = name
        if not versions:
            return free
        keep = {v for _, v in self._kept} | {current, max(versions)}
        for version, name in versions.items():
            if version in keep:
                continue
            path = folder / name
            try:
                size = path.stat().st_size
                path.unlink()
            except OSError as exc:
                logger.debug("disk: cannot remove %s (%s)", path, exc)
                continue
            free += size
        return free


__all__ = ["CloudRetention", "RetentionConfig", "free_bytes"]
