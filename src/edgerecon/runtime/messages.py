"""What the front-end and back-end roles exchange, and the per-task record.

Everything here is a small frozen dataclass of NumPy arrays and plain values, so it pickles
cheaply and travels through Ray's object store unchanged.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from edgerecon.scene.background import BackgroundState
from edgerecon.scene.foreground import ForegroundResult
from edgerecon.types import PointCloud


@dataclass(frozen=True, kw_only=True)
class TaskPlan:
    """The configuration the optimizer chose for one task."""

    time_index: int
    scale: float
    camera_ids: tuple[int, ...]
    phase: str
    """Controller phase: "golden", "search", "adjust" or "fixed"."""


@dataclass(frozen=True, kw_only=True, eq=False)
class MasksReply:
    """The back-end's foreground of one timestamp."""

    time_index: int
    foreground: ForegroundResult
    seconds: float


@dataclass(frozen=True, kw_only=True, eq=False)
class GoldenReply:
    """The golden configuration's foreground sparse points of one timestamp (the reference
    of the online quality estimate)."""

    time_index: int
    fg_points3D: NDArray[np.float64]
    num_points: int
    """All sparse points of the golden reconstruction (foreground and background)."""
    seconds: float


@dataclass(frozen=True, kw_only=True, eq=False)
class BackgroundUpdate:
    """A background cloud rebuilt by the back-end in its idle time, pushed to the front-end."""

    version: int
    """1, 2, ... in the order the back-end finished them."""
    cloud: PointCloud
    seconds: float
    """Time the rebuild took on the back-end."""
    model_states: tuple[BackgroundState, ...] | None = None
    """Snapshot of the background models, so the front-end can compute masks itself if the
    back-end is lost (degraded mode)."""


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
    num_cameras: int = 0
    camera_ids: list[int] = field(default_factory=list)
    critical_path_s: float = 0.0
    """Seconds from the task's start to its merged cloud (what the deadline constrains)."""
    stages: dict[str, float] = field(default_factory=dict)
    """Breakdown of the critical path (sparse, wait for masks, split, foreground MVS, merge)."""
    deadline_s: float = 0.0
    deadline_met: bool = False
    online_fscore: float | None = None
    """Online quality estimate (None without the back-end's golden reference)."""
    offline_fscore: float | None = None
    """Foreground F-score against ground truth (synthetic scenes, when evaluated)."""
    bg_version: int = 0
    """Background version merged into this task's cloud (0 = none yet)."""
    degraded: bool = False
    """True when the back-end did not serve this task (masks computed locally, no online
    quality estimate)."""
    degraded_reason: str = ""
    num_sparse: int = 0
    num_sparse_fg: int = 0
    num_fg_points: int = 0
    num_merged_points: int = 0
    num_objects: int = 0
    search_steps: int = 0
    """Configuration-search steps taken by the controller so far."""
    sync_spread_s: float | None = None
    """Live streams: newest minus oldest capture time of the task's frames, seconds."""
    error: str = ""
    wall_time: float = 0.0
    """Unix time when the task finished."""

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TaskMetrics:
        names = set(cls.__dataclass_fields__)
        return cls(**{k: v for k, v in d.items() if k in names})
