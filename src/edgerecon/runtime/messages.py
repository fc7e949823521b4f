"""What the front-end and back-end roles exchange, and the per-task record.

Everything here is a small frozen dataclass of NumPy arrays and plain values, so it pickles
cheaply and travels through Ray's object store unchanged.
"""

from __future__ import annotations

import time
import traceback
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from edgerecon.scene.foreground import ForegroundResult
from edgerecon.types import FrameSet, PointCloud


@dataclass(frozen=True, order=True)
class BgVersion:
    """Version of a background cloud: (back-end epoch, counter). Every back-end the run
    starts (the first one, an embedded restart, a Ray actor restart, a resumed run) gets the
    next epoch from the front-end, which owns the count; each back-end counts its rebuilds
    from 1. Versions order as tuples, so a new back-end's first background is newer than
    anything an earlier one made, and a late push from a dead back-end is older."""

    epoch: int = 0
    counter: int = 0

    def __str__(self) -> str:
        return f"v{self.epoch}.{self.counter}" if self else "v0"

    def __bool__(self) -> bool:
        return self.counter > 0

    def to_list(self) -> list[int]:
        return [self.epoch, self.counter]

    @classmethod
    def from_list(cls, v: Any) -> BgVersion:
        """From ``[epoch, counter]`` (or a plain counter: a state written before epochs)."""
        if isinstance(v, int):
            return cls(0, v)
        epoch, counter = v
        return cls(int(epoch), int(counter))


@dataclass(frozen=True, kw_only=True)
class TaskPlan:
    """The configuration the optimizer chose for one task."""

    time_index: int
    scale: float
    camera_ids: tuple[int, ...]
    phase: str
    """Controller phase: "golden", "search", "adjust" or "fixed"."""


@dataclass(frozen=True, kw_only=True, eq=False)
class TaskWork:
    """What the front-end hands the back-end for one task, once its scene stage is done: the
    frames and their foreground (masks, objects, hull at the working resolution), for the
    golden reference and the background rebuilds. The back-end never segments: the masks
    are computed once, by the front-end that needs them first."""

    frames: FrameSet
    foreground: ForegroundResult
    golden: bool
    """Whether the front-end wants the golden reference of this task (online quality
    "golden")."""
    still_uses: tuple[int, int] | None = None
    """The time index of the newest snapshot of the still foreground the front-end holds
    and how many tasks used it (``scene.still``): the back-end makes fewer snapshots while
    none is used."""


@dataclass(frozen=True, kw_only=True, eq=False)
class GoldenReply:
    """The golden configuration's foreground sparse points of one timestamp (the reference
    of the online quality estimate)."""

    time_index: int
    fg_points3D: NDArray[np.float64] | None
    """None when the back-end failed on this timestamp (see ``error``)."""
    num_points: int
    """All sparse points of the golden reconstruction (foreground and background)."""
    seconds: float
    error: str = ""


@dataclass(frozen=True, kw_only=True, eq=False)
class BackgroundUpdate:
    """A background cloud rebuilt by the back-end in its idle time, pushed to the front-end."""

    version: BgVersion
    """(epoch of the back-end that built it, 1, 2, ... in the order it finished them)."""
    cloud: PointCloud
    seconds: float
    """Time the rebuild took on the back-end."""


#: Stages a task records after its cloud is out (not on its critical path): the paper's
#: online estimate's wait for the golden reference, the online estimate, the background
#: update of the task's frame, a golden task's SfM for pi(N') and the background updates due
#: before the next task that the session applies between the two (``Session._learn_ahead``).
AFTER_CRITICAL_PATH = (
    "wait_golden",
    "online_quality",
    "scene_update_after",
    "sfm_mapping",
    "scene_update_ahead",
)


@dataclass(kw_only=True)
class TaskMetrics:
    """One line of ``metrics.jsonl``."""

    task: int
    """Sequence number of the task in the run (0-based)."""
    time_index: int
    """Frame index (timestamp) reconstructed."""
    status: str
    """"ok", or "failed" (the task was skipped; see ``error``)."""
    phase: str = ""
    scale: float = 0.0
    """Image scale r of the task; above 1 (``RuntimeConfig.fine_foreground``): the golden
    camera set with the foreground's depth maps finer than the golden task's
    (``pipeline.task_configs``)."""
    planned_scale: float | None = None
    """The controller's r when the task ran at another (``RuntimeConfig.workload``: r
    scaled by the masks' area against the recent tasks'); None: the same."""
    num_cameras: int = 0
    camera_ids: list[int] = field(default_factory=list)
    critical_path_s: float = 0.0
    """Seconds from the task's start to its merged cloud (what the deadline constrains)."""
    stages: dict[str, float] = field(default_factory=dict)
    """Seconds per stage: the critical path's (sparse, wait for masks, split, foreground
    MVS, merge), then those of ``AFTER_CRITICAL_PATH``."""
    deadline_s: float = 0.0
    deadline_met: bool = False
    online_fscore: float | None = None
    """Online quality estimate (None without the back-end's golden reference)."""
    offline_fscore: float | None = None
    """Foreground F-score against ground truth (synthetic scenes, when evaluated)."""
    bg_version: int = 0
    """Background merged into this task's cloud: the counter of :class:`BgVersion` (0 =
    none yet)."""
    bg_epoch: int = 0
    """... and its back-end epoch: (bg_epoch, bg_version) never decreases over a run."""
    degraded: bool = False
    """True when the back-end did not serve this task in time (masks computed locally, or no
    golden reference: no online quality estimate)."""
    degraded_reason: str = ""
    submitted: bool = False
    """The frames went to the back-end (its background models learned from them)."""
    frame_defects: dict[str, str] = field(default_factory=dict)
    """Cameras left out of this task because their frame is unusable: name -> "black",
    "saturated" or "textureless". With fewer than 3 cameras left the task is empty (no
    foreground; the merged cloud is the background alone)."""
    frozen_cameras: list[str] = field(default_factory=list)
    """Cameras whose frames had not changed for ``FrameCheckConfig.frozen_after_s`` of the
    stream while the others' did (``quality.frames.FrozenCameras``): kept in the task, with
    their view of the moment they froze."""
    camera_moves: list[dict[str, Any]] = field(default_factory=list)
    """Cameras whose views these frames confirmed moved (``quality.frames.MovedCameras``:
    knocked, a mount that slipped; the back-end checks the calibration at once on frames
    from the move on): ``camera``, ``time_index`` (the first frame that showed it),
    ``shift_px`` (the image centre's motion), ``roll_deg``, ``turn_deg`` (the camera's turn
    that moves its image centre so far), ``across_stop`` (it moved while the run was
    stopped: seen against its view from before a ``--resume``)."""
    stabilised: dict[str, float | None] = field(default_factory=dict)
    """Cameras whose view moved (knocked, or that keep moving), their frame turned back
    onto their view before their first move (``quality.frames.Stabiliser``): the turn taken off, degrees (None:
    the frame gave no turn and was kept as it was)."""
    num_sparse: int = 0
    num_sparse_fg: int = 0
    num_fg_points: int = 0
    num_still_points: int = 0
    """Of ``num_fg_points``, those kept from the back-end's snapshot of the still foreground
    (``scene.still``; the task densified the rest)."""
    still_share: float | None = None
    """Share of the task's mask pixels that were still and not densified (None: the task
    densified its whole foreground)."""
    num_merged_points: int = 0
    num_objects: int = 0
    search_steps: int = 0
    """Configuration-search steps taken by the controller so far."""
    sync_spread_s: float | None = None
    """Live streams: newest minus oldest capture time of the task's frames, seconds."""
    cloud_written: bool = False
    """The task's cloud files were written (``tasks/<time>/``; a later task may remove them:
    ``runtime.retention``)."""
    cloud_skipped: bool = False
    """The task's cloud was not written: the output's disk was under ``--min-free-mb``."""
    error: str = ""
    """Why the task failed (status "failed"): the stage's exception, or the watchdog."""
    rss_mb: float | None = None
    """The resident memory of the run's main process when the task was committed, MB (None
    where the system does not say; ``runtime.memory.resident_mb``)."""
    wall_time: float = 0.0
    """Unix time when the task finished."""

    @property
    def background_version(self) -> BgVersion:
        return BgVersion(self.bg_epoch, self.bg_version)

    @classmethod
    def failed(cls, *, task: int, time_index: int, error: str, deadline_s: float) -> TaskMetrics:
        """The record of a task that produced nothing."""
        return cls(
            task=task,
            time_index=time_index,
            status="failed",
            error=error,
            deadline_s=deadline_s,
            wall_time=time.time(),
        )

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TaskMetrics:
        names = set(cls.__dataclass_fields__)
        return cls(**{k: v for k, v in d.items() if k in names})


#: The installed package's folder (``.../edgerecon``): frames in it are the product's.
_PACKAGE_DIR = Path(__file__).resolve().parent.parent


def describe_exception(exc: BaseException) -> str:
    """``"Type: message (in function, file:line)"`` of the innermost edgerecon frame: the
    reason a failed task records."""
    where = ""
    for frame in reversed(traceback.extract_tb(exc.__traceback__)):
        # The package's own files, not any path that happens to contain its name (a clone
        # in ~/edgerecon holds its virtual environment and tests too).
        path = Path(frame.filename).resolve()
        if path.is_relative_to(_PACKAGE_DIR):
            short = path.relative_to(_PACKAGE_DIR).as_posix()
            where = f" (in {frame.name}, {short}:{frame.lineno})"
            break
    return f"{type(exc).__name__}: {exc}{where}"
