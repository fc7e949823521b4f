"""Per-task image scale from the task's own workload, on top of the controller's r.

The minor adjustment steers one r for a stretch of tasks from their average time, but the
foreground's time at one r follows the area of the task's masks (hd4 / hd4p at 40 %: the
foreground's seconds correlate 0.92-0.95 with mask area x r^2, 0.83-0.88 with r^2 alone), and
the scene stage before it takes 0.2-0.45 s as the actors come and go: a task with twice the
foreground ran late while the next one left time unused. Once the scene stage has given a
task its masks (before any of its MVS), :class:`WorkloadScaler` scales the controller's r by

    ((mean area of the recent tasks / this task's area)
     x (time left for the MVS in this task / the recent tasks' mean)) ^ exponent

within ``[1 / max_factor, max_factor]`` (time left: the controller's target time less what
the task spent before its MVS). The MVS's work per task then stays near what the controller
measured, and the controller keeps steering r from the times as before (they vary less).
Pure state, no clock::

    scaler = WorkloadScaler(WorkloadConfig())
    f = scaler.factor(area, spent_s, target_s)  # 1.0 until the history is long enough
    scaler.record(area, spent_s)                # every task, whatever its phase
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from edgerecon.types import Mask


@dataclass(frozen=True, kw_only=True)
class WorkloadConfig:
    """How a task's r follows its masks' area (``RuntimeConfig.workload``)."""

    window: int = 8
    """Tasks in the reference: the mean area of the last ``window`` tasks."""
    min_history: int = 3
    """Tasks recorded before any task is scaled (factor 1 until then)."""
    exponent: float = 0.5
    """The factor is (reference / area) ^ exponent: 0.5 when the foreground's time grows
    with area x r^2 (it grows as r^1.4-2.2 at one time index on hd4p)."""
    max_factor: float = 1.3
    """The factor stays in [1 / max_factor, max_factor]: one task's masks (an actor
    walking in, a mask that lost an arm) move r by at most this much."""

    def __post_init__(self) -> None:
        if self.window < 1 or self.min_history < 1 or self.min_history > self.window:
            raise ValueError(
                f"WorkloadConfig: need 1 <= min_history <= window, got {self.min_history}, "
                f"{self.window}"
            )
        if not (math.isfinite(self.exponent) and self.exponent >= 0):
            raise ValueError(f"WorkloadConfig.exponent must be >= 0, got {self.exponent}")
        if not (math.isfinite(self.max_factor) and self.max_factor >= 1):
            raise ValueError(f"WorkloadConfig.max_factor must be >= 1, got {self.max_factor}")


def mask_area(masks: Sequence[Mask | None], camera_ids: Sequence[int]) -> float | None:
    """The task's workload: the mean share of foreground pixels over the task's cameras
    (None when none of them has a mask)."""
    chosen = [masks[c] for c in camera_ids if 0 <= c < len(masks)]
    shares = [float(np.count_nonzero(m)) / m.size for m in chosen if m is not None and m.size]
    return float(np.mean(shares)) if shares else None


class WorkloadScaler:
    """The factor of the next task's r from its area and the recent ones' (module doc)."""

    def __init__(
        self,
        config: WorkloadConfig | None = None,
        history: Sequence[tuple[float, float]] = (),
    ):
        self.config = config or WorkloadConfig()
        self._tasks: deque[tuple[float, float]] = deque(maxlen=self.config.window)
        for area, spent in history:
            self.record(area, spent)

    @property
    def history(self) -> tuple[tuple[float, float], ...]:
        """The recorded (area, seconds before the MVS), oldest first (what a resumed run
        starts from)."""
        return tuple(self._tasks)

    def reference(self) -> tuple[float, float] | None:
        """The recent tasks' mean area and mean seconds before their MVS (None: too few
        recorded)."""
        if len(self._tasks) < self.config.min_history:
            return None
        area, spent = np.mean(np.array(self._tasks), axis=0)
        return float(area), float(spent)

    def factor(
        self, area: float | None, spent_s: float | None = None, target_s: float | None = None
    ) -> float:
        """How much this task's r is scaled: 1 without a reference or an area. With
        ``spent_s`` (this task's seconds before its MVS) and ``target_s`` (the time the
        controller steers the tasks to), also by the share of the target left for the MVS
        against the recent tasks'."""
        c = self.config
        ref = self.reference()
        if area is None or ref is None or ref[0] <= 0 or c.exponent == 0:
            return 1.0
        ratio = ref[0] / area if area > 0 else math.inf
        if spent_s is not None and target_s is not None and target_s > 0:
            usual, left = target_s - ref[1], target_s - spent_s
            if usual > 0.1 * target_s:  # else the MVS's share says nothing
                ratio *= max(left, 0.0) / usual
        if not ratio > 0:
            return 1.0 / c.max_factor
        f = ratio**c.exponent
        return float(min(max(f, 1.0 / c.max_factor), c.max_factor))

    def record(self, area: float | None, spent_s: float = 0.0) -> None:
        """A task's area and seconds before its MVS join the reference (no area, e.g. a task
        without masks: nothing)."""
        if area is None or not (math.isfinite(area) and area >= 0):
            return
        spent = float(spent_s) if math.isfinite(spent_s) and spent_s >= 0 else 0.0
        self._tasks.append((float(area), spent))


__all__ = ["WorkloadConfig", "WorkloadScaler", "mask_area"]
