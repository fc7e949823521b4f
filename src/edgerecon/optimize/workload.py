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
the task spent before its MVS). Relative to the recent tasks, so the factors average about
1 and the controller keeps steering its r from the tasks' times as before (they vary less).
A task is not made coarser when its MVS, predicted at the controller's r from the recent
tasks' cost per unit of area x r^2, fits the target anyway (a controller at its ceiling with
time to spare keeps its r). An absolute prediction alone was measured and not kept: it
expects time to grow as r^2 where it grows slower, makes every task coarser, and the
controller's r climbed to its ceiling against it (hd4p at 40 %: the controller at r = 2,
the tasks at 1.54, and a false "deadline above the finest configuration"). Pure state, no
clock::

    scaler = WorkloadScaler(WorkloadConfig())
    f = scaler.factor(area, spent_s, target_s, r)  # 1.0 until the history is long enough
    scaler.record(area, spent_s, r * f, mvs_s)     # every finished task, whatever its phase
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from edgerecon.types import Mask


@dataclass(frozen=True, kw_only=True)
class WorkloadConfig:
    """How a task's r follows its masks' area (``RuntimeConfig.workload``)."""

    window: int = 8
    """Tasks in the reference (their mean area, time before the MVS and MVS cost)."""
    min_history: int = 3
    """Tasks recorded before any task is scaled (factor 1 until then)."""
    exponent: float = 0.5
    """The factor is (area and time ratio) ^ exponent, the MVS's time taken to grow with
    area x r^(1 / exponent): 0.5 for r^2 (it grows as r^1.4-2.2 at one time index on hd4p).
    0: r is never scaled."""
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
    """The factor of the next task's r from its area and the time it has left against the
    recent tasks' (module doc)."""

    def __init__(
        self,
        config: WorkloadConfig | None = None,
        history: Sequence[Sequence[float]] = (),
    ):
        self.config = config or WorkloadConfig()
        self._tasks: deque[tuple[float, float, float, float]] = deque(maxlen=self.config.window)
        for entry in history:
            if len(entry) == 4:
                area, spent, scale, mvs = (float(x) for x in entry)
                self.record(area, spent, scale, mvs)

    @property
    def history(self) -> tuple[tuple[float, float, float, float], ...]:
        """The recent tasks' (area, seconds before the MVS, r, MVS seconds), oldest first
        (what a resumed run starts from)."""
        return tuple(self._tasks)

    def reference(self) -> tuple[float, float] | None:
        """The recent tasks' mean area and mean seconds before their MVS (None: too few
        recorded)."""
        if len(self._tasks) < self.config.min_history:
            return None
        area, spent = np.mean(np.array(self._tasks)[:, :2], axis=0)
        return float(area), float(spent)

    def predicted_mvs(self, area: float, scale: float) -> float | None:
        """The MVS seconds of a task of ``area`` at ``scale`` from the recent tasks' cost per
        unit of area x r^(1 / exponent) (a ratio of sums: the tasks with the most work
        weigh most); None: too few recorded."""
        if len(self._tasks) < self.config.min_history or self.config.exponent <= 0:
            return None
        t = np.array(self._tasks)
        work = float(np.sum(self._work(t[:, 0], t[:, 2])))
        if work <= 0:
            return None
        return float(np.sum(t[:, 3])) / work * float(self._work(max(area, 0.0), scale))

    def _work(self, area: Any, scale: Any) -> Any:
        return area * np.power(scale, 1.0 / self.config.exponent)

    def factor(
        self,
        area: float | None,
        spent_s: float | None = None,
        target_s: float | None = None,
        scale: float | None = None,
    ) -> float:
        """How much this task's r is scaled: 1 without a reference or an area. The area
        against the recent mean; with ``spent_s`` (this task's seconds before its MVS) and
        ``target_s`` (the time the controller steers the tasks to) also the time left for
        the MVS against the recent tasks'; with ``scale`` (the controller's r) never below 1
        for a task whose predicted time at that r fits the target (a controller at its
        ceiling with time to spare keeps its r)."""
        c = self.config
        ref = self.reference()
        if area is None or ref is None or ref[0] <= 0 or c.exponent == 0:
            return 1.0
        ratio = ref[0] / area if area > 0 else math.inf
        if spent_s is not None and target_s is not None and target_s > 0:
            usual, left = target_s - ref[1], target_s - spent_s
            if usual > 0.1 * target_s:  # else the MVS's share says nothing
                ratio *= max(left, 0.0) / usual
            if scale is not None and ratio < 1.0:
                mvs = self.predicted_mvs(area, scale)
                if mvs is not None and spent_s + mvs <= target_s:
                    return 1.0
        if not ratio > 0:  # no time left (0, or an empty mask with none: nan)
            return 1.0 / c.max_factor
        f = ratio**c.exponent
        return float(min(max(f, 1.0 / c.max_factor), c.max_factor))

    def record(
        self, area: float | None, spent_s: float = 0.0, scale: float = 1.0, mvs_s: float = 0.0
    ) -> None:
        """A finished task: its area, seconds before its MVS, the r it ran at and its MVS's
        seconds. Tasks without an area (no masks) teach nothing."""
        if area is None or not (math.isfinite(area) and area >= 0):
            return
        spent = float(spent_s) if math.isfinite(spent_s) and spent_s >= 0 else 0.0
        r = float(scale) if math.isfinite(scale) and scale > 0 else 1.0
        mvs = float(mvs_s) if math.isfinite(mvs_s) and mvs_s >= 0 else 0.0
        self._tasks.append((float(area), spent, r, mvs))


__all__ = ["WorkloadConfig", "WorkloadScaler", "mask_area"]
