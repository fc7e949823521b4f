"""The online configuration controller: the paper's Algorithm 1 (bisection over the image scale
r for each camera-subset size N', stepping N' down), its three early-exit rules, the final
argmax over the stored solutions, the minor-adjustment procedure, and re-entering the search
when conditions change for good.

It is a pure state machine driven by observations — no clock, no I/O, no randomness::

    ctrl = BisectionController(ControllerConfig(deadline_s=5.0), camera_mapping, num_cameras=7)
    for task in tasks:
        cfg = ctrl.next_config()          # TaskConfig(scale, camera_ids, num_cameras, phase)
        time_s, quality = run(task, cfg)  # reconstruct + online quality estimate
        ctrl.observe(time_s, quality)

Phases: ``golden`` (r = 1 with every available camera; its result is the reference of the
online quality estimate and its sparse cloud gives the visibility for camera selection),
``search`` (Algorithm 1) and ``adjust`` (minor adjustment of r at the chosen N'). The state
machine, the rules and the re-search triggers are described in ``docs/OPTIMIZER.md``.
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import math
import statistics
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from edgerecon.optimize.selection import CameraMapping, CameraSelector

logger = logging.getLogger(__name__)

Phase = Literal["golden", "search", "adjust"]
CameraMappingLike = (
    CameraMapping | CameraSelector | Mapping[int, Sequence[int]] | Callable[[int], Sequence[int]]
)

_EPS = 1e-9
_R_HISTORY = 500  # adjusted r values kept for the drift trigger
#: Above r_max, r grows by r sqrt(dl / t), at most this share per task: the foreground's own
#: time grows as r^1.4-2.2 there at one time index (hd4p, t = 98 and 170: r 1 -> 1.4 -> 2
#: took 0.36 -> 0.59 -> 1.30 s and 0.72 -> 1.12 -> 1.94 s), but the next task's workload
#: differs: on hd4p at 40 % a 40 % cap took r 1.40 -> 1.88 and the time 0.98 -> 2.27 s
#: against a 1.85 s deadline.
_FINE_CLIMB = 0.25

#: The adjustment goes up when the last two tasks both took less than this share of its
#: target, whatever the window's mean (which lags behind a slow stretch that is over).
_CLEARLY_UNDER = 0.8
# ``late_share``: adjusted tasks measured before their own spread counts, and the spread
# assumed until then (the tasks' times around their running average on the real rigs
# here: 0.12-0.13 on caliscope_charuco at 40 %).
_LATE_MIN = 8
_LATE_PRIOR = 0.12


@dataclass(frozen=True, kw_only=True)
class ControllerConfig:
    """Parameters of Algorithm 1, the minor adjustment and the re-search triggers."""

    deadline_s: float
    """The user's deadline Δt per task, seconds."""
    r_min: float = 0.3
    """Smallest image scale (paper: 0.3)."""
    r_max: float = 1.0
    """Largest image scale (paper: 1.0)."""
    tau: float = 0.01
    """Bisection resolution: a level's search ends when r_hi - r_lo <= tau (paper: 0.01)."""
    min_cameras: int = 3
    """Smallest camera subset N' (the pipeline needs 3)."""
    margin_s: float = 0.0
    """Absolute acceptance margin, seconds: during the search a task counts as meeting the
    deadline when T <= Δt + margin_s + margin_rel * Δt (the paper accepted 1 s)."""
    margin_rel: float = 0.0
    """Relative acceptance margin (share of Δt), added to ``margin_s``."""
    golden_first: bool = True
    """Run the golden configuration (r_max, all cameras) as the first task, as the paper does;
    when it meets the deadline the search ends after one step."""
    prune_fewer_cameras: bool = True
    """Rule 2: on entering a smaller N' (once a feasible solution exists) measure Q at r_max
    first and stop the whole search when even that does not beat the best solution."""
    prune_bisection: bool = True
    """Rule 3: abandon an N' when a too-slow r already has quality <= the best solution."""
    baseline_confirm: float = 1.5
    """Rule 1 skips an N' for the whole search on one measurement of r_min. When that task
    took at most this multiple of the accepted time, r_min is measured once more and the
    level is skipped only if it misses again (0 = never): one task slowed by another
    process (the back-end's first background rebuild starting) once made the search drop a
    camera for the rest of the stretch (caliscope_charuco at 40 %: r_min with 4 cameras
    0.62 s against 0.43 s in the next run; 3 cameras after it, foreground F vs golden
    0.89 -> 0.84). The golden task gets the same second measurement: the run's first task
    shares the machine with the back-end's first work, and one miss started a search of 7-8
    tasks at lower scales where the golden configuration fits (caliscope_charuco at 40 %:
    1.50 s without its SfM against 1.46 s, then r = 1 from the search's end on)."""
    adjust_step: float = 0.02
    """Minor-adjustment step of r after the search (paper: 0.02)."""
    adjust_max_step: float = 0.1
    """Largest step when the running average is far from the target: half the change of r
    that would bring it there if time grew with r squared, between ``adjust_step`` and this
    (= ``adjust_step``: the paper's fixed steps). Under timing noise alone the step stays
    ``adjust_step``; after the workload jumps (a second actor walks in) r follows within a few
    tasks instead of tens."""
    r_fine: float | None = None
    """Above ``r_max``, up to this, only the minor adjustment goes, and only with every
    available camera: when the golden configuration leaves part of the deadline unused, r
    climbs on into configurations finer than the golden one (the caller says what r > 1
    means; the online system: the foreground's depth maps at r / 2^L of the frames, where
    the golden configuration densifies at level L, ``pipeline.task_configs``). The search
    (Algorithm 1) and the golden task stay in [r_min, r_max]. None (= r_max): off here;
    the online system (``runtime.online.make_controller``) then takes the rig's limit, and
    caps a given value at it, unless ``RuntimeConfig.fine_foreground`` is False."""
    skip_scales: tuple[tuple[float, float], ...] = ()
    """Beyond the paper: open intervals (a, b) of r that no task runs, because a task at
    b costs less and is finer (the online system's foreground sweeps its planes on a
    pyramid whose level drops to a coarser one at b: on 1280-wide frames r = 0.55 cost
    0.42 s where r = 0.6 cost 0.30 s; ``pipeline.dominated_scales``, set by
    ``runtime.online.make_controller``). A probe of the search or a step of the adjustment
    that lands inside goes to b (up; to a when b is not below the search's too-slow end) or
    to a (the adjustment going down); the drift trigger measures r with the intervals
    taken out. Empty: every r in the range runs (the paper)."""
    adjust_window: int = 5
    """Tasks in the running average of the minor adjustment (0 = every task since the
    adjustment began, as in the paper; a short window oscillates less, see OPTIMIZER.md)."""
    adjust_target: float = 1.0
    """The adjustment steers the running average to adjust_target * Δt (1.0 = the paper;
    e.g. 0.9 trades some quality for fewer deadline misses under noisy timings)."""
    late_share: float | None = None
    """Beyond the paper (None: off, the average is steered to ``adjust_target`` x Δt and,
    with the tasks' times spread around it, a third of them can run late). About this
    share of the adjusted tasks may run past Δt (e.g. 0.1): the adjustment steers the
    average to Δt / (1 + z s) instead, s the spread of the adjusted tasks' times around the
    running average each of them met (1.4826 x the median absolute deviation of t / avg - 1
    over the last ``late_window``; 0.12 until ``_LATE_MIN`` are measured), z the standard
    normal quantile of 1 - late_share; never above ``adjust_target`` x Δt. The average then
    sits below Δt by what the spread asks (a deadline for every task rather than for their
    mean); a change of workload still makes late tasks while the adjustment follows it."""
    late_window: int = 30
    """Adjusted tasks whose spread ``late_share`` measures."""
    research_window: int = 5
    """Tasks in the median the jump trigger looks at, and the count the saturation trigger
    needs (see ``docs/OPTIMIZER.md``)."""
    research_jump: float = 0.5
    """Re-search when the median of the last ``research_window`` times is above
    (1 + research_jump) Δt or below (1 - research_jump) Δt (0 disables)."""
    research_drift: float = 0.1
    """Re-search when the mean r of the last 2 x ``research_window`` adjusted tasks has moved
    this far from its settled value (the mean r of the earlier adjusted tasks, leaving out the
    first 2 x ``research_window`` that catch up with the searched r*): the time per task
    changed for good (0 disables)."""
    research_saturation: bool = True
    """Re-search when the adjustment wants to leave [r_min, r_max] for ``research_window``
    tasks in a row and a different N' could help."""
    guided_probes: bool = True
    """Beyond the paper (False: its bisection). Within a camera count, the next probe
    solves the level's own measured times for the accepted time (T = a + b r^2 through its
    two latest probes, or through the origin from one) instead of halving [lo, hi]; it stays
    at least ``guide_margin`` of the interval inside it, and a guided probe that did not at
    least halve the interval is followed by a plain bisection step (so a level never takes
    more than twice the paper's probes). When the level's times (its last two probes too
    slow) put that r within tau of lo, the level ends there: lo is already a solution. On 7
    cameras at 1080p the paper's search probed each camera count about seven times at tau =
    0.01 (27 tasks to search 5 counts)."""
    guide_margin: float = 0.1
    """Least distance of a guided probe from the interval's ends, as a share of it."""
    start_from_measurement: float | None = 0.95
    """Beyond the paper (None: off, the paper's search from r_min). A search whose first
    level (every available camera) starts with nothing known feasible but with a measured
    time T at some r with those cameras (the golden task's that was too slow, or the recent
    adjusted tasks' before a re-search) first probes r min(L / T, sqrt(L / T)) x this
    factor, at most r_max (L: the accepted time). Time grows as a fixed part plus about r^2
    (r^1.4-2.2 measured): the square root overshoots what fits when T > L and the ratio
    when T < L, the smaller of the two stays under it. When the probe meets the deadline the
    bisection goes on from it; a probe that misses is followed by one more from its own
    time, then by r_min with rule 1 as before. A golden task
    10 % too slow (caliscope_charuco at 1080x1920, 40 %) started a bisection from r = 0.3
    that took 6 tasks at r 0.3-0.96 back to 1."""

    def __post_init__(self) -> None:
        def positive(name: str) -> None:
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number, got {v!r}")

        def non_negative(name: str) -> None:
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be a non-negative number, got {v!r}")

        for name in ("deadline_s", "r_min", "r_max", "tau", "adjust_step", "adjust_max_step"):
            positive(name)
        if self.adjust_max_step < self.adjust_step:
            raise ValueError(
                f"adjust_max_step ({self.adjust_max_step}) must be >= adjust_step "
                f"({self.adjust_step})"
            )
        for name in (
            "margin_s",
            "margin_rel",
            "research_jump",
            "research_drift",
            "baseline_confirm",
        ):
            non_negative(name)
        if self.r_min >= self.r_max:
            raise ValueError(f"r_min ({self.r_min}) must be < r_max ({self.r_max})")
        if self.r_max > 1.0:
            raise ValueError(f"r_max must be <= 1 (full resolution), got {self.r_max}")
        if self.r_fine is not None and not (
            math.isfinite(self.r_fine) and self.r_fine >= self.r_max
        ):
            raise ValueError(f"r_fine ({self.r_fine}) must be None or >= r_max ({self.r_max})")
        if self.tau >= self.r_max - self.r_min:
            raise ValueError(
                f"tau ({self.tau}) must be smaller than r_max - r_min ({self.r_max - self.r_min})"
            )
        if self.min_cameras < 2:
            raise ValueError(f"min_cameras must be >= 2, got {self.min_cameras}")
        if self.adjust_window < 0:
            raise ValueError(f"adjust_window must be >= 0, got {self.adjust_window}")
        if self.research_window < 1:
            raise ValueError(f"research_window must be >= 1, got {self.research_window}")
        if self.start_from_measurement is not None and not (0 < self.start_from_measurement <= 1):
            raise ValueError(
                f"start_from_measurement must be None or in (0, 1], got "
                f"{self.start_from_measurement}"
            )
        if not 0 < self.adjust_target <= 1.5:
            raise ValueError(f"adjust_target must be in (0, 1.5], got {self.adjust_target}")
        if not 0 < self.guide_margin <= 0.5:
            raise ValueError(f"guide_margin must be in (0, 0.5], got {self.guide_margin}")
        if self.late_share is not None and not 0 < self.late_share < 0.5:
            raise ValueError(f"late_share must be None or in (0, 0.5), got {self.late_share}")
        if self.late_window < _LATE_MIN:
            raise ValueError(f"late_window must be >= {_LATE_MIN}, got {self.late_window}")
        if self.research_jump >= 1.0:
            raise ValueError(f"research_jump must be < 1, got {self.research_jump}")
        try:
            skip = tuple(sorted((float(a), float(b)) for a, b in self.skip_scales))
        except (TypeError, ValueError):
            raise ValueError(
                f"skip_scales must be pairs (a, b) of numbers, got {self.skip_scales!r}"
            ) from None
        for i, (a, b) in enumerate(skip):
            if not (math.isfinite(a) and math.isfinite(b) and 0 < a < b):
                raise ValueError(f"skip_scales: need 0 < a < b, got ({a}, {b})")
            if i and a < skip[i - 1][1]:
                raise ValueError(f"skip_scales: intervals overlap at ({a}, {b})")
        object.__setattr__(self, "skip_scales", skip)  # JSON's lists back to tuples

    @property
    def accept_limit_s(self) -> float:
        """Largest time accepted as meeting the deadline during the search."""
        return self.deadline_s * (1.0 + self.margin_rel) + self.margin_s


@dataclass(frozen=True, kw_only=True)
class TaskConfig:
    """What the next task runs with."""

    scale: float
    """Image scale r in [r_min, r_max] (up to ``r_fine`` in the adjustment with every
    available camera)."""
    camera_ids: tuple[int, ...]
    """Rig camera ids pi(N'), ascending."""
    num_cameras: int
    """N' = len(camera_ids)."""
    phase: Phase
    """``golden``, ``search`` or ``adjust``."""

    def to_dict(self) -> dict[str, Any]:
        return {
            "scale": self.scale,
            "camera_ids": list(self.camera_ids),
            "num_cameras": self.num_cameras,
            "phase": self.phase,
        }


@dataclass(frozen=True, kw_only=True)
class Solution:
    """A configuration observed to meet the deadline during the search."""

    scale: float
    num_cameras: int
    quality: float
    """Observed online quality (NaN when unknown)."""
    time_s: float

    def rank(self) -> tuple[float, int, float]:
        q = self.quality if math.isfinite(self.quality) else -math.inf
        return (q, self.num_cameras, self.scale)


def _solve_time(probes: Sequence[Sequence[float]], limit: float) -> float | None:
    """The r at which T(r) = a + b r^2, through the two latest probes (r, seconds) of
    different r, reaches ``limit`` (through the origin, a = 0, from one probe); None
    without a usable probe."""
    pts = [(float(r), float(t)) for r, t in probes if r > 0 and t > 0]
    if not pts:
        return None
    r1, t1 = pts[-1]
    second = next(((r, t) for r, t in reversed(pts[:-1]) if abs(r - r1) > _EPS), None)
    if second is not None:
        r2, t2 = second
        b = (t1 - t2) / (r1 * r1 - r2 * r2)
        if b > 0:
            a = t1 - b * r1 * r1
            return math.sqrt(max(limit - a, 0.0) / b)
    return r1 * math.sqrt(limit / t1)


@dataclass
class _State:
    phase: Phase = "golden"
    level: int = 0
    probe: Literal["golden", "baseline", "predicted", "top", "bisect"] = "golden"
    r: float = 1.0
    lo: float = 0.0
    hi: float = 1.0
    solutions: list[Solution] = field(default_factory=list)
    chosen: Solution | None = None
    feasible: bool = True
    infeasible_reported: bool = False
    """The user was told once that no configuration meets the deadline."""
    slack_reported: bool = False
    """The user was told once that the finest configuration leaves the deadline unused."""
    r_star: float = 1.0
    n_star: int = 0
    r_searched: float = 1.0
    r_history: list[float] = field(default_factory=list)
    adjust_times: list[float] = field(default_factory=list)
    adjust_sum: float = 0.0
    adjust_count: int = 0
    late_residuals: list[float] = field(default_factory=list)
    """t / avg - 1 of the last ``late_window`` adjusted tasks, avg the running average
    before each (``late_share``)."""
    recent: list[float] = field(default_factory=list)
    recent_scales: list[float] = field(default_factory=list)
    """The r of each of the ``recent`` adjusted tasks (``start_from_measurement``)."""
    saturation_low: int = 0
    saturation_high: int = 0
    suppress_faster: bool = False
    last_trigger: str | None = None
    baseline_misses: int = 0
    """Too-slow measurements of r_min at the current N' (rule 1, ``baseline_confirm``)."""
    golden_misses: int = 0
    """Too-slow golden tasks in this search (``baseline_confirm``)."""
    predicted_misses: int = 0
    """Too-slow predicted probes at the current level (``start_from_measurement``)."""
    level_probes: list[list[float]] = field(default_factory=list)
    """(r, seconds) of the current level's probes (``guided_probes``)."""
    guided: bool = False
    """The probe being measured was a guided one (``guided_probes``)."""
    search_steps: int = 0
    total_search_steps: int = 0
    num_searches: int = 1
    tasks: int = 0
    pending: bool = False
    events: list[dict[str, Any]] = field(default_factory=list)


class BisectionController:
    """Algorithm 1 with pruning rules, minor adjustment and re-search triggers (see module
    docstring). Configurations it returns always satisfy r in [r_min, r_max] (up to r_fine
    in the adjustment with every available camera) and min_cameras <= N' <= number of
    available cameras."""

    def __init__(
        self,
        config: ControllerConfig,
        camera_mapping: CameraMappingLike | None,
        num_cameras: int,
        *,
        available: Sequence[int] | None = None,
    ) -> None:
        if num_cameras < config.min_cameras:
            raise ValueError(
                f"num_cameras ({num_cameras}) must be >= min_cameras ({config.min_cameras})"
            )
        self.config = config
        self.num_cameras = int(num_cameras)
        self.available: tuple[int, ...] = self._check_available(available)
        self._mapping: CameraMappingLike | None = camera_mapping
        self._pi_cache: dict[int, tuple[int, ...]] = {}
        self.s = _State()
        self._begin_search(golden=config.golden_first, reason="start")

    # ------------------------------------------------------------------ public API

    @property
    def phase(self) -> Phase:
        return self.s.phase

    @property
    def target_s(self) -> float:
        """The average time the adjustment steers to: ``adjust_target`` x Δt, or with
        ``late_share`` Δt / (1 + z s) from the adjusted tasks' spread, whichever is less."""
        c = self.config
        base = c.deadline_s * c.adjust_target
        res = self.s.late_residuals
        if c.late_share is None:
            return base
        if len(res) < _LATE_MIN:
            spread = _LATE_PRIOR
        else:
            r = np.asarray(res[-c.late_window :], np.float64)
            spread = 1.4826 * float(np.median(np.abs(r - np.median(r))))
        over = statistics.NormalDist().inv_cdf(1.0 - c.late_share) * spread
        return min(base, c.deadline_s / (1.0 + max(over, 0.0)))

    @property
    def search_steps(self) -> int:
        """Tasks spent in the golden and search phases of the current (or last) search."""
        return self.s.search_steps

    @property
    def total_search_steps(self) -> int:
        """Tasks spent searching since the controller started (all searches)."""
        return self.s.total_search_steps

    @property
    def num_searches(self) -> int:
        """Searches started (1 + re-searches)."""
        return self.s.num_searches

    @property
    def solutions(self) -> list[Solution]:
        """Feasible configurations observed in the current search."""
        return list(self.s.solutions)

    @property
    def chosen(self) -> Solution | None:
        """The search's argmax (None while searching, or when nothing met the deadline)."""
        return self.s.chosen

    @property
    def feasible(self) -> bool:
        """False when the last search found no configuration meeting the deadline (the
        controller then runs the fastest one: r_min with min_cameras)."""
        return self.s.feasible

    @property
    def events(self) -> list[dict[str, Any]]:
        """Re-searches so far: ``{"task": index, "reason": ...}``."""
        return list(self.s.events)

    @property
    def num_available(self) -> int:
        return len(self.available)

    def next_config(self) -> TaskConfig:
        """The configuration of the next task (the same one until :meth:`observe` is called)."""
        s = self.s
        s.pending = True
        if s.phase == "golden":
            return TaskConfig(
                scale=self.config.r_max,
                camera_ids=self.available,
                num_cameras=self.num_available,
                phase="golden",
            )
        if s.phase == "search":
            return self._task(s.r, s.level, "search")
        return self._task(s.r_star, s.n_star, "adjust")

    def observe(self, time_s: float, quality: float | None = None) -> None:
        """Report the processing time (seconds) and online quality of the task run with the
        last :meth:`next_config` (``quality`` None or NaN = unknown: the time still counts, the
        quality rules do not fire)."""
        if not self.s.pending:
            raise RuntimeError("observe() called without a preceding next_config()")
        t = float(time_s)
        if not (math.isfinite(t) and t >= 0):
            raise ValueError(f"time_s must be a finite number >= 0, got {time_s!r}")
        q = math.nan if quality is None else float(quality)
        if math.isinf(q):
            raise ValueError(f"quality must be finite or None, got {quality!r}")
        s = self.s
        s.pending = False
        s.tasks += 1
        if s.phase == "golden":
            self._observe_golden(t, 1.0 if math.isnan(q) else q)
        elif s.phase == "search":
            self._observe_search(t, q)
        else:
            self._observe_adjust(t)

    def set_deadline(self, deadline_s: float) -> None:
        """Change Δt; re-enters the search (the camera mapping is kept)."""
        if deadline_s == self.config.deadline_s:
            return
        self.config = dataclasses.replace(self.config, deadline_s=float(deadline_s))
        self.restart("deadline", golden=False)

    def set_cameras(
        self, available: Sequence[int], camera_mapping: CameraMappingLike | None = None
    ) -> None:
        """The set of usable cameras changed (a node was lost or came back): re-search over
        ``available`` with the new mapping (which must choose among ``available``)."""
        new = self._check_available(available)
        if camera_mapping is not None:
            self._mapping = camera_mapping
            self._pi_cache.clear()
        if new == self.available and camera_mapping is None:
            return
        self.available = new
        self._pi_cache.clear()
        self.restart("cameras", golden=False)

    def set_camera_mapping(self, camera_mapping: CameraMappingLike, restart: bool = False) -> None:
        """Replace pi (e.g. once the golden task's sparse cloud is available); the current
        search continues unless ``restart``."""
        self._mapping = camera_mapping
        self._pi_cache.clear()
        if restart:
            self.restart("mapping", golden=False)

    def restart(self, reason: str = "manual", golden: bool = False) -> None:
        """Re-enter the search now (``golden``: start with a golden task)."""
        self._begin_search(golden=golden, reason=reason)

    def camera_ids(self, num_cameras: int) -> tuple[int, ...]:
        """pi(N') as the controller uses it (validated, cached)."""
        n = int(num_cameras)
        if n == self.num_available:
            return self.available
        if n in self._pi_cache:
            return self._pi_cache[n]
        m = self._mapping
        if m is None:
            raise RuntimeError(
                f"the controller needs pi({n}) but has no camera mapping: pass one to "
                "BisectionController(...) or set_camera_mapping() after the golden task"
            )
        if isinstance(m, Mapping):
            if n not in m:
                raise RuntimeError(f"the camera mapping has no subset of size {n}")
            ids_raw: Sequence[int] = m[n]
        else:
            ids_raw = m(n)
        ids = tuple(sorted(int(i) for i in ids_raw))
        if len(ids) != n or len(set(ids)) != n or not set(ids) <= set(self.available):
            raise RuntimeError(
                f"camera mapping returned {list(ids_raw)} for N' = {n}: expected {n} distinct "
                f"ids among the available cameras {list(self.available)}"
            )
        self._pi_cache[n] = ids
        return ids

    # ------------------------------------------------------------------ search

    def _check_available(self, available: Sequence[int] | None) -> tuple[int, ...]:
        if available is None:
            return tuple(range(self.num_cameras))
        ids = tuple(sorted({int(i) for i in available}))
        bad = [i for i in ids if not 0 <= i < self.num_cameras]
        if bad:
            raise ValueError(f"camera ids {bad} out of range 0..{self.num_cameras - 1}")
        if len(ids) < self.config.min_cameras:
            raise ValueError(
                f"{len(ids)} available cameras {list(ids)}: the controller needs at least "
                f"{self.config.min_cameras}"
            )
        return ids

    def scale_range(self, num_cameras: int) -> tuple[float, float]:
        """The r an adjusted task with ``num_cameras`` cameras may run at: [r_min, r_max],
        up to ``r_fine`` with every available camera (where a caller that scales the
        controller's r per task, ``optimize.workload``, keeps it)."""
        return self.config.r_min, self._r_ceiling(num_cameras)

    def _skipped(self, r: float) -> tuple[float, float] | None:
        """The interval of ``skip_scales`` that ``r`` lies inside, if any."""
        for a, b in self.config.skip_scales:
            if a + _EPS < r < b - _EPS:
                return a, b
        return None

    def undominated(self, r: float, up: bool = True) -> float:
        """``r``, or where ``r`` lies inside one of ``skip_scales``, that interval's upper end
        (``up``: as fast or faster, and finer) or its lower end."""
        inside = self._skipped(r)
        if inside is None:
            return r
        return inside[1] if up else inside[0]

    def _probe_between(self, r: float, lo: float, hi: float) -> float | None:
        """A search probe ``r`` in (lo, hi) moved out of a skipped interval: to its upper end
        when that is below hi, else to its lower end when that is above lo; None when (lo,
        hi) lies inside the interval (no scale worth measuring is left)."""
        inside = self._skipped(r)
        if inside is None:
            return r
        a, b = inside
        if b < hi - _EPS:
            return b
        return a if a > lo + _EPS else None

    def _collapsed(self, r: float) -> float:
        """``r`` with the skipped intervals below it taken out: a step across one is not a
        change of the workload (the drift trigger)."""
        out = r
        for a, b in self.config.skip_scales:
            if r >= b - _EPS:
                out -= b - a
            elif r > a:
                out -= r - a
        return out

    def _r_ceiling(self, n: int) -> float:
        """The largest r with N' = ``n`` outside the search: ``r_fine`` with every available
        camera, else ``r_max``."""
        c = self.config
        if c.r_fine is None or n < self.num_available:
            return c.r_max
        return c.r_fine

    def _task(self, r: float, n: int, phase: Phase) -> TaskConfig:
        c = self.config
        n = min(max(n, c.min_cameras), self.num_available)
        r = min(max(r, c.r_min), self._r_ceiling(n) if phase == "adjust" else c.r_max)
        r = self.undominated(r)  # a state saved before skip_scales were set
        ids = self.camera_ids(n)
        return TaskConfig(scale=round(r, 6), camera_ids=ids, num_cameras=n, phase=phase)

    def _begin_search(self, golden: bool, reason: str) -> None:
        s = self.s
        if reason != "start":
            s.events.append({"task": s.tasks, "reason": reason})
            s.num_searches += 1
            logger.info("re-entering the search after %d tasks: %s", s.tasks, reason)
        if reason not in ("faster", "saturation_high"):
            s.suppress_faster = False  # something else changed: spare time is worth a look again
        measured = None
        c = self.config
        # A floor that misses on average (or whose median jumped above the deadline while r
        # sat at r_min): r_min with N'* cameras is too slow, and so is every larger camera
        # count (T grows with N'), the paper's rule 1 from the adjusted tasks' own times; the
        # search starts below it instead of measuring them again (arc7 at a third of its
        # golden task: two more tasks at r_min with all 7 cameras, one per larger count).
        floor = reason == "saturation_low" or (reason == "slower" and s.r_star <= c.r_min + _EPS)
        top = self.num_available
        if floor and s.phase == "adjust" and s.n_star > c.min_cameras:
            top = s.n_star - 1
        pairs = list(zip(s.recent_scales, s.recent, strict=False))  # (none from old states)
        if s.phase == "adjust" and s.n_star == self.num_available and len(pairs) >= 3:
            # What the recent adjusted tasks (every camera) say fits: the median over them
            # (start_from_measurement's guess without its factor).
            fits = [
                r * min(c.accept_limit_s / t, math.sqrt(c.accept_limit_s / t))
                for r, t in pairs
                if t > 0
            ]
            if fits:
                measured = (float(np.median(fits)), c.accept_limit_s)
        s.solutions = []
        s.chosen = None
        s.feasible = True
        s.search_steps = 0
        s.last_trigger = reason
        s.recent = []
        s.recent_scales = []
        s.saturation_low = s.saturation_high = 0
        if golden:
            s.phase = "golden"
            s.probe = "golden"
            s.golden_misses = 0
            s.r = self.config.r_max
            s.level = self.num_available
        else:
            s.phase = "search"
            self._start_level(top, top_known_infeasible=False, measured=measured)

    def _observe_golden(self, t: float, q: float) -> None:
        s = self.s
        c = self.config
        s.search_steps += 1
        s.total_search_steps += 1
        n = self.num_available
        if t <= c.accept_limit_s:
            s.solutions.append(Solution(scale=c.r_max, num_cameras=n, quality=q, time_s=t))
            self._finish_search("golden configuration meets the deadline")
            return
        s.golden_misses += 1
        if s.golden_misses == 1 and t <= c.baseline_confirm * c.accept_limit_s:
            logger.debug("golden configuration too slow (%.3fs), again", t)
            return  # measure the golden configuration once more before searching
        s.phase = "search"
        self._start_level(n, top_known_infeasible=True, measured=(c.r_max, t))

    def _implied_feasible(self, level: int) -> float | None:
        """Largest r observed feasible with at least ``level`` cameras (feasible at ``level``
        too, since T grows with N')."""
        rs = [x.scale for x in self.s.solutions if x.num_cameras >= level]
        return max(rs) if rs else None

    def _best(self) -> Solution | None:
        """The argmax over the camera counts searched of each one's largest feasible r,
        ranked by the best quality observed with that many cameras. Within a camera count
        the quality grows with r (the bisection's own premise), but the qualities of
        different tasks also follow their content: an argmax over every feasible task chose
        r 0.55 over 0.79 with the same 4 cameras (caliscope_charuco at 40 %: the board
        raised during the larger r's tasks, online F .17-.26 against .52), and the
        adjustment then spent the stretch climbing back."""
        if not self.s.solutions:
            return None
        levels: dict[int, list[Solution]] = {}
        for x in self.s.solutions:
            levels.setdefault(x.num_cameras, []).append(x)
        candidates = []
        for xs in levels.values():
            top = max(xs, key=lambda x: x.scale)
            known = [x.quality for x in xs if math.isfinite(x.quality)]
            quality = max(known) if known else math.nan
            candidates.append(dataclasses.replace(top, quality=quality))
        return max(candidates, key=Solution.rank)

    def _start_level(
        self,
        level: int,
        top_known_infeasible: bool = False,
        measured: tuple[float, float] | None = None,
    ) -> None:
        """Begin the bisection over r with ``level`` cameras; ``measured``: (r, seconds) of
        a task with that many cameras (``start_from_measurement``)."""
        s = self.s
        c = self.config
        if level < c.min_cameras:
            self._finish_search("all camera counts searched")
            return
        s.level = level
        s.hi = c.r_max
        s.baseline_misses = 0
        s.level_probes = []
        s.guided = False
        lo = self._implied_feasible(level)
        if lo is None:
            # Nothing known feasible: start at r_min (paper, line 3); the baseline check skips
            # the level when even r_min is too slow.
            s.lo = c.r_min
            s.probe = "baseline"
            s.r = c.r_min
            guess = self._predicted_scale(measured)
            if guess is not None:
                s.probe = "predicted"
                s.predicted_misses = 0
                s.r = guess
            return
        s.lo = lo
        if s.hi - s.lo <= c.tau + _EPS:
            # a larger N' already meets the deadline within tau of r_max: fewer cameras at
            # r <= r_max cannot be better
            self._finish_search("a larger N' is feasible at r_max")
            return
        if c.prune_fewer_cameras and not top_known_infeasible:
            s.probe = "top"
            s.r = c.r_max
            return
        mid = self._probe_between(0.5 * (s.lo + s.hi), s.lo, s.hi)
        if mid is None:
            self._start_level(level - 1)
            return
        s.probe = "bisect"
        s.r = mid

    def _predicted_scale(self, measured: tuple[float, float] | None) -> float | None:
        """The first probe of a level from a measured (r, seconds) of its cameras (at most
        r_max), or None (off, nothing measured, or a guess within tau of r_min: the
        paper's start there)."""
        c = self.config
        if c.start_from_measurement is None or measured is None:
            return None
        r, t = measured
        if not (r > 0 and t > 0):
            return None
        ratio = c.accept_limit_s / t
        guess = r * min(ratio, math.sqrt(ratio)) * c.start_from_measurement
        if guess <= c.r_min + c.tau:
            return None
        return round(self.undominated(min(guess, c.r_max)), 6)

    def _observe_search(self, t: float, q: float) -> None:
        s = self.s
        c = self.config
        s.search_steps += 1
        s.total_search_steps += 1
        r = s.r
        ok = t <= c.accept_limit_s
        best = self._best()
        width = s.hi - s.lo
        s.level_probes = [*s.level_probes[-3:], [r, t]]
        if ok:
            s.solutions.append(Solution(scale=r, num_cameras=s.level, quality=q, time_s=t))
        probe = s.probe
        if probe == "baseline":
            if not ok:  # rule 1: r_min is too slow for this N'
                s.baseline_misses += 1
                if s.baseline_misses == 1 and t <= c.baseline_confirm * c.accept_limit_s:
                    logger.debug("N'=%d: baseline r=%.3f too slow (%.3fs), again", s.level, r, t)
                    return  # measure r_min once more before skipping the level
                logger.debug("N'=%d: baseline r=%.3f too slow (%.3fs)", s.level, r, t)
                self._start_level(s.level - 1)
                return
            s.lo = r
        elif probe == "predicted":
            if not ok:
                s.hi = r
                s.predicted_misses += 1
                again = self._predicted_scale((r, t)) if s.predicted_misses < 2 else None
                if again is not None and again < r - c.tau:
                    # Once more from this probe's own time (the fixed part of a task's time
                    # makes it fall slower than r^2: caliscope_charuco at 40 %, 0.80 took
                    # 1.03 x the deadline).
                    s.r = again
                    return
                # Too slow after all: the level's paper start, r_min with rule 1.
                s.probe = "baseline"
                s.r = c.r_min
                return
            s.lo = r
        elif probe == "top":
            if best is not None and q <= best.quality:
                # rule 2: even r_max with this N' is no better: fewer cameras cannot be either
                self._finish_search(f"rule 2 at N'={s.level}")
                return
            if ok:
                self._finish_search(f"N'={s.level} meets the deadline at r_max")
                return
            s.hi = r
        else:
            if ok:
                s.lo = r
            else:
                s.hi = r
                if c.prune_bisection and best is not None and q <= best.quality:
                    # rule 3: every feasible r for this N' is below r, so no better
                    logger.debug("N'=%d abandoned at r=%.3f (rule 3)", s.level, r)
                    self._start_level(s.level - 1)
                    return
        nxt = None if s.hi - s.lo <= c.tau + _EPS else self._next_probe(width)
        if nxt is not None:
            nxt = self._probe_between(nxt, s.lo, s.hi)
        if nxt is None:
            self._start_level(s.level - 1)
        else:
            s.probe = "bisect"
            s.r = nxt

    def _next_probe(self, width_before: float) -> float | None:
        """The next r in (lo, hi): the midpoint (the paper), or with ``guided_probes`` the
        r at which this level's measured times reach the accepted time, kept
        ``guide_margin`` inside the interval; after a guided probe that did not halve the
        interval, the midpoint. None: the level's times (its last two probes too slow) put
        that r within tau of lo, the level ends."""
        s = self.s
        c = self.config
        lo, hi = s.lo, s.hi
        mid = 0.5 * (lo + hi)
        was_guided, s.guided = s.guided, False
        if not c.guided_probes:
            return mid
        guess = _solve_time(s.level_probes, c.accept_limit_s)
        if (
            guess is not None
            and guess <= lo + c.tau
            and len(s.level_probes) >= 2
            and min(t for _, t in s.level_probes[-2:]) > c.accept_limit_s
        ):
            # The level's own times, the last two too slow, say nothing above lo fits: lo is
            # already a solution (of this or a larger camera count); the level ends.
            return None
        if guess is None or (was_guided and hi - lo > 0.5 * width_before + _EPS):
            return mid
        s.guided = True
        margin = c.guide_margin * (hi - lo)
        return round(min(max(guess, lo + margin), hi - margin), 6)

    def _finish_search(self, why: str) -> None:
        s = self.s
        c = self.config
        best = self._best()
        if best is None:
            s.feasible = False
            s.chosen = None
            s.r_star, s.n_star = c.r_min, c.min_cameras
            # Once per run (re-searches find the same): the deadline is below what this
            # device can do; the fastest configuration is the one closest to it.
            logger.log(
                logging.INFO if s.infeasible_reported else logging.WARNING,
                "no configuration met the deadline of %.3fs: running the fastest one "
                "(r=%.2f, N'=%d)",
                c.deadline_s,
                s.r_star,
                s.n_star,
            )
            s.infeasible_reported = True
        else:
            s.feasible = True
            s.chosen = best
            s.r_star, s.n_star = best.scale, best.num_cameras
        logger.info(
            "search done after %d steps (%s): r*=%.3f N'=%d",
            s.search_steps,
            why,
            s.r_star,
            s.n_star,
        )
        if s.last_trigger in ("faster", "saturation_high"):
            # a re-search looking for spare time found nothing better: do not ask again until
            # something else changes
            s.suppress_faster = True
        s.phase = "adjust"
        s.r_searched = s.r_star
        s.r_history = []
        s.adjust_times = []
        s.adjust_sum = 0.0
        s.adjust_count = 0
        s.recent = []
        s.recent_scales = []
        s.saturation_low = s.saturation_high = 0
        if best is not None:
            self._seed_climb(best)

    def _seed_climb(self, best: Solution) -> None:
        """A search that ends at r_max with every camera and time to spare starts the climb
        into finer configurations from its own measurement, not a task later (each task of
        the climb leaves part of the deadline unused: hd4p at 60 %, 4 of 19 adjusted tasks
        at 0.64-1.5 s against 2.14)."""
        s = self.s
        c = self.config
        dl = self.target_s
        ceiling = self._r_ceiling(best.num_cameras)
        if (
            best.scale >= c.r_max - _EPS
            and best.num_cameras >= self.num_available
            and ceiling > c.r_max
            and 0 < best.time_s < dl
        ):
            climb = min(self._climb(c.r_max, best.time_s, dl), ceiling)
            s.r_star = round(self.undominated(climb), 6)

    @staticmethod
    def _climb(r: float, t: float, dl: float) -> float:
        """The next r of a climb above r_max from a task of t seconds at r."""
        return r * min(math.sqrt(dl / t), 1.0 + _FINE_CLIMB)

    # ------------------------------------------------------------------ adjustment

    def _observe_adjust(self, t: float) -> None:
        s = self.s
        c = self.config
        dl = self.target_s
        if c.late_share is not None and s.adjust_count:
            # The task's time against the running average it was steered by.
            mean = (
                float(np.mean(s.adjust_times)) if c.adjust_window else s.adjust_sum / s.adjust_count
            )
            if mean > 0:
                s.late_residuals.append(t / mean - 1.0)
                del s.late_residuals[: -c.late_window]
        s.adjust_count += 1
        s.adjust_sum += t
        if c.adjust_window:
            s.adjust_times.append(t)
            del s.adjust_times[: -c.adjust_window]
            avg = float(np.mean(s.adjust_times))
        else:
            avg = s.adjust_sum / s.adjust_count
        s.recent.append(t)
        del s.recent[: -c.research_window]
        s.recent_scales.append(s.r_star)
        del s.recent_scales[: -c.research_window]
        want = 0
        last_two = max(s.recent[-2:]) if len(s.recent) >= 2 else math.inf
        if (avg < dl and t < dl) or last_two < _CLEARLY_UNDER * dl:
            # Up when the window's mean and the last task agree, or when the last two tasks
            # both left a fifth of the target unused: the window's mean still holds a slow
            # stretch that is over (hd3 at 30 %: four slow first tasks held r for 3 tasks at
            # 0.4-0.6 of the deadline).
            want = 1
        elif avg > dl and t > dl:
            want = -1
        r_old = s.r_star
        ceiling = self._r_ceiling(s.n_star)
        step = c.adjust_step
        if want > 0 and r_old >= c.r_max - _EPS and ceiling > c.r_max and t > 0:
            # Climbing above r_max into the time the golden configuration leaves: from the
            # last task's time (measured at r_old; the window's mean lags behind a climb and
            # would overshoot), r sqrt(dl / t) within ``_FINE_CLIMB`` (``_climb``).
            step = max(step, self._climb(r_old, t, dl) - r_old)
        elif want and c.adjust_max_step > c.adjust_step and avg > 0:
            # T ~ a + b r^2: r sqrt(dl / avg) would be right if a were 0 (with a > 0 it
            # undershoots, never overshoots). Above r = 1 the steps grow with r (the same
            # relative change).
            proportional = abs(r_old * (math.sqrt(dl / avg) - 1.0))
            step = min(max(step, proportional), c.adjust_max_step * max(1.0, r_old))
            if want > 0 and len(s.recent) >= 2 and min(s.recent[-2:]) > 0:
                # Up, also from the last two tasks' times as the climb above r_max does
                # (the window's mean lags behind: hd3 at 30 %, four slow first tasks held
                # the steps at 0.02-0.1 for 7 tasks at 0.4-0.6 of the deadline).
                step = max(step, self._climb(r_old, max(s.recent[-2:]), dl) - r_old)
        s.r_star = min(max(r_old + want * step, c.r_min), ceiling)
        s.r_star = round(self.undominated(s.r_star, up=want >= 0), 6)
        at_min = r_old <= c.r_min + _EPS
        at_max = r_old >= ceiling - _EPS
        # At r_min the count goes on while the window's average misses: a task that meets
        # the deadline by chance (its time swings with the load) does not reset it, or a
        # floor that misses on average could wait for a search with fewer cameras for ever
        # (caliscope_charuco at 30 %: one met task in nine put it off to the run's end).
        s.saturation_low = s.saturation_low + 1 if (at_min and avg > dl) else 0
        # Likewise at the ceiling while the average leaves time: one heavy task in a light
        # stretch does not reset it (hd4 at 60 %: r = 2 on 14 of 19 tasks, 18 % of the
        # deadline unused, never five light tasks in a row).
        s.saturation_high = s.saturation_high + 1 if (at_max and avg < dl) else 0
        s.r_history.append(s.r_star)
        del s.r_history[:-_R_HISTORY]
        if (
            s.saturation_low >= c.research_window
            and s.n_star <= c.min_cameras
            and not s.infeasible_reported
        ):
            # The workload grew after the search (more foreground, more people): the fastest
            # configuration itself misses now. Said once per run, as after a search.
            logger.warning(
                "no configuration met the deadline of %.3fs: the fastest one (r=%.2f, N'=%d) "
                "averaged %.3fs over the last %d tasks",
                c.deadline_s,
                s.r_star,
                s.n_star,
                avg,
                len(s.adjust_times) if c.adjust_window else s.adjust_count,
            )
            s.infeasible_reported = True
        if (
            s.saturation_high >= c.research_window
            and s.n_star >= self.num_available
            and not s.slack_reported
        ):
            # Nothing finer to run: the deadline is above the slowest configuration. Said
            # once per run, as an infeasible one.
            logger.warning(
                "the deadline of %.3fs is above the finest configuration (r=%.2f with all %d "
                "cameras averaged %.3fs over the last %d tasks): %.0f %% of it stays unused",
                c.deadline_s,
                s.r_star,
                s.n_star,
                avg,
                len(s.adjust_times) if c.adjust_window else s.adjust_count,
                100.0 * (1.0 - avg / c.deadline_s),
            )
            s.slack_reported = True
        reason = self._research_reason()
        if reason is not None:
            self._begin_search(golden=False, reason=reason)

    def _research_reason(self) -> str | None:
        s = self.s
        c = self.config
        dl = c.deadline_s
        can_fewer = s.n_star > c.min_cameras or s.r_star > c.r_min + _EPS
        can_more = s.n_star < self.num_available or s.r_star < c.r_max - _EPS
        if c.research_jump > 0 and len(s.recent) >= c.research_window:
            med = float(np.median(s.recent))
            if med > dl * (1 + c.research_jump) and can_fewer and s.feasible:
                return "slower"
            if med < dl * (1 - c.research_jump) and can_more and not s.suppress_faster:
                return "faster"
        w = c.research_window
        hist = [self._collapsed(r) for r in s.r_history]
        if c.research_drift > 0 and len(hist) >= 6 * w:
            # settled r: every adjusted task after the first 2w (catching up with a noisy r*)
            # and before the recent 2w; a sustained change moves the recent mean away from it
            reference = float(np.mean(hist[2 * w : -2 * w]))
            recent = float(np.mean(hist[-2 * w :]))
            # Above r_max (every camera, finer than golden) r follows the workload: no search
            # can do better than what it would start from, r_max with every camera.
            finer = min(reference, recent) >= self._collapsed(c.r_max) - _EPS
            if abs(recent - reference) >= c.research_drift - _EPS and not finer:
                return "drift"
        if c.research_saturation:
            if s.saturation_low >= c.research_window and s.n_star > c.min_cameras and s.feasible:
                return "saturation_low"
            if (
                s.saturation_high >= c.research_window
                and s.n_star < self.num_available
                and not s.suppress_faster
            ):
                return "saturation_high"
        return None

    # ------------------------------------------------------------------ persistence

    def to_dict(self) -> dict[str, Any]:
        """The controller's full state as JSON-able data (see :meth:`from_dict`)."""
        s = self.s
        state = dataclasses.asdict(s)
        state["solutions"] = [dataclasses.asdict(x) for x in s.solutions]
        state["chosen"] = None if s.chosen is None else dataclasses.asdict(s.chosen)
        for x in state["solutions"] + ([state["chosen"]] if state["chosen"] else []):
            if not math.isfinite(x["quality"]):
                x["quality"] = None
        mapping: Any = None
        if isinstance(self._mapping, CameraMapping):
            mapping = {"kind": "camera_mapping", "data": self._mapping.to_dict()}
        elif isinstance(self._mapping, Mapping):
            mapping = {
                "kind": "dict",
                "data": {str(k): [int(i) for i in v] for k, v in self._mapping.items()},
            }
        return {
            "format": "edgerecon-controller",
            "version": 1,
            "config": dataclasses.asdict(self.config),
            "num_cameras": self.num_cameras,
            "available": list(self.available),
            "pi": {str(k): list(v) for k, v in sorted(self._pi_cache.items())},
            "mapping": mapping,
            "state": state,
        }

    @classmethod
    def from_dict(
        cls, d: Mapping[str, Any], camera_mapping: CameraMappingLike | None = None
    ) -> BisectionController:
        """Restore a controller saved with :meth:`to_dict`. Without ``camera_mapping`` the
        saved pi serves: complete when it was a :class:`CameraMapping` or a dict, else only
        the subsets used so far (pass the callable or selector again to go on)."""
        if d.get("format") != "edgerecon-controller":
            raise ValueError("not a saved edgerecon controller state")
        config = ControllerConfig(**d["config"])
        mapping: CameraMappingLike | None = camera_mapping
        saved_pi = {int(k): tuple(int(i) for i in v) for k, v in d.get("pi", {}).items()}
        if mapping is None:
            m = d.get("mapping")
            if m and m.get("kind") == "camera_mapping":
                mapping = CameraMapping.from_dict(m["data"])
            elif m and m.get("kind") == "dict":
                mapping = {int(k): tuple(int(i) for i in v) for k, v in m["data"].items()}
            elif saved_pi:
                mapping = dict(saved_pi)
        ctrl = cls(config, mapping, int(d["num_cameras"]), available=d["available"])
        ctrl._pi_cache = {} if camera_mapping is not None else dict(saved_pi)
        st = copy.deepcopy(dict(d["state"]))  # never share lists with the caller's dict

        def sol(x: Mapping[str, Any]) -> Solution:
            q = x.get("quality")
            return Solution(
                scale=float(x["scale"]),
                num_cameras=int(x["num_cameras"]),
                quality=math.nan if q is None else float(q),
                time_s=float(x["time_s"]),
            )

        st["solutions"] = [sol(x) for x in st["solutions"]]
        st["chosen"] = None if st["chosen"] is None else sol(st["chosen"])
        ctrl.s = _State(**st)
        return ctrl
