"""Simulation harness for the controller: a latency / quality model T(r, N'), Q(r, N') with
multiplicative noise and optional drift, a driver that runs a controller for I tasks, a
Table III-like summary, the true optimum by dense grid search on the noise-free model, and a
generator of realistic visibility matrices for camera-selection tests and benchmarks.

The default model resembles the paper's Dance1 setting (7 cameras; Table III):
``T = base_s + per_camera_s * r^2 * N'^camera_exponent`` (pixels grow with r^2; the
constant covers I/O and set-up) and ``Q = r^quality_scale_exponent * c(N')`` with
``c(N') = (N'/N)^quality_camera_exponent`` or a coverage table from camera selection. Both
are monotone in r and N'.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from edgerecon.optimize.controller import BisectionController, ControllerConfig, TaskConfig


@dataclass(frozen=True, kw_only=True)
class SimulatorConfig:
    """Latency / quality model of the simulated pipeline."""

    num_cameras: int = 7
    """N, cameras of the simulated rig."""
    base_s: float = 3.0
    """Seconds per task independent of r and N' (I/O, set-up, merging)."""
    per_camera_s: float = 1.1
    """Seconds per camera at full resolution (r = 1), scaled by r^2."""
    camera_exponent: float = 1.0
    """T grows like N'^camera_exponent (above 1: pairwise matching dominates)."""
    quality_scale_exponent: float = 0.67
    """Q grows like r^quality_scale_exponent (fitted to the paper's Table III)."""
    quality_camera_exponent: float = 0.4
    """Q grows like (N'/N)^quality_camera_exponent, unless ``quality_by_cameras`` is given."""
    quality_by_cameras: Mapping[int, float] | None = None
    """Optional c(N') per subset size (e.g. a camera mapping's coverage fractions); must be
    non-decreasing in N'."""
    time_noise: float = 0.15
    """Multiplicative timing noise: T * U(1 - time_noise, 1 + time_noise)."""
    quality_noise: float = 0.02
    """Multiplicative quality noise, uniform like the timing noise (Q clipped to [0, 1])."""
    noise_kind: Literal["uniform", "lognormal"] = "uniform"
    """``uniform`` as above; ``lognormal``: factor exp(N(0, noise))."""
    drift_per_task: float = 0.0
    """Relative growth of the processing time per task (e.g. 0.005: a foreground growing by
    0.5% a task); compounds."""
    load_steps: tuple[tuple[int, float], ...] = ()
    """Step changes of the load: (first task index, time factor from then on)."""

    def __post_init__(self) -> None:
        if self.num_cameras < 3:
            raise ValueError(f"num_cameras must be >= 3, got {self.num_cameras}")
        for name in ("base_s", "time_noise", "quality_noise", "camera_exponent"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be a non-negative number, got {v!r}")
        for name in ("per_camera_s", "quality_scale_exponent"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number, got {v!r}")
        if not (math.isfinite(self.quality_camera_exponent) and self.quality_camera_exponent >= 0):
            raise ValueError(
                f"quality_camera_exponent must be >= 0, got {self.quality_camera_exponent!r}"
            )
        if self.noise_kind == "uniform" and (self.time_noise >= 1 or self.quality_noise >= 1):
            raise ValueError("uniform noise amplitudes must be < 1")
        if self.noise_kind not in ("uniform", "lognormal"):
            raise ValueError(
                f"noise_kind must be 'uniform' or 'lognormal', got {self.noise_kind!r}"
            )
        if self.drift_per_task <= -1:
            raise ValueError(f"drift_per_task must be > -1, got {self.drift_per_task}")
        for task, factor in self.load_steps:
            if task < 0 or not factor > 0:
                raise ValueError(
                    f"load_steps entries must be (task >= 0, factor > 0), got {(task, factor)}"
                )
        if self.quality_by_cameras is not None:
            keys = sorted(self.quality_by_cameras)
            vals = [self.quality_by_cameras[k] for k in keys]
            if any(b < a for a, b in itertools.pairwise(vals)):
                raise ValueError("quality_by_cameras must be non-decreasing in N'")


class PipelineModel:
    """T(r, N') and Q(r, N') of the simulated pipeline (noise-free and sampled)."""

    def __init__(self, config: SimulatorConfig | None = None) -> None:
        self.config = config or SimulatorConfig()

    def load(self, task: int) -> float:
        """Time factor of task ``task`` (drift and step changes)."""
        c = self.config
        step = 1.0
        for start, factor in sorted(c.load_steps):
            if task >= start:
                step = factor
        return step * (1.0 + c.drift_per_task) ** task

    def time_s(self, scale: float, num_cameras: int, task: int = 0) -> float:
        """Noise-free processing time."""
        c = self.config
        t = c.base_s + c.per_camera_s * scale**2 * num_cameras**c.camera_exponent
        return t * self.load(task)

    def camera_quality(self, num_cameras: int) -> float:
        c = self.config
        if c.quality_by_cameras is not None:
            return float(c.quality_by_cameras[num_cameras])
        return (num_cameras / c.num_cameras) ** c.quality_camera_exponent

    def quality(self, scale: float, num_cameras: int) -> float:
        """Noise-free quality in [0, 1] (1 at the golden configuration)."""
        c = self.config
        return float(scale**c.quality_scale_exponent * self.camera_quality(num_cameras))

    def _factor(self, rng: np.random.Generator, amp: float) -> float:
        if amp == 0:
            return 1.0
        if self.config.noise_kind == "uniform":
            return float(rng.uniform(1 - amp, 1 + amp))
        return float(math.exp(rng.normal(0.0, amp)))

    def sample(
        self, scale: float, num_cameras: int, task: int, rng: np.random.Generator
    ) -> tuple[float, float]:
        """One noisy observation (time_s, quality)."""
        t = self.time_s(scale, num_cameras, task) * self._factor(rng, self.config.time_noise)
        q = self.quality(scale, num_cameras) * self._factor(rng, self.config.quality_noise)
        return t, float(min(max(q, 0.0), 1.0))


@dataclass(frozen=True, kw_only=True)
class Optimum:
    """The best configuration of the noise-free model under a time limit."""

    scale: float
    num_cameras: int
    quality: float
    time_s: float
    feasible: bool
    """False when nothing meets the limit (then the fastest configuration is reported)."""


def true_optimum(
    model: PipelineModel,
    limit_s: float,
    r_min: float = 0.3,
    r_max: float = 1.0,
    min_cameras: int = 3,
    num_cameras: int | None = None,
    task: int = 0,
    step: float = 1e-4,
) -> Optimum:
    """Dense grid search of max Q(r, N') s.t. T(r, N') <= limit_s on the noise-free model."""
    n_max = model.config.num_cameras if num_cameras is None else num_cameras
    rs = np.arange(r_min, r_max + step / 2, step)
    best: Optimum | None = None
    for n in range(min_cameras, n_max + 1):
        t = np.array([model.time_s(float(r), n, task) for r in rs])
        ok = np.flatnonzero(t <= limit_s)
        if len(ok) == 0:
            continue
        r = float(rs[ok[-1]])
        q = model.quality(r, n)
        if best is None or q > best.quality:
            best = Optimum(
                scale=r, num_cameras=n, quality=q, time_s=float(t[ok[-1]]), feasible=True
            )
    if best is None:
        return Optimum(
            scale=r_min,
            num_cameras=min_cameras,
            quality=model.quality(r_min, min_cameras),
            time_s=model.time_s(r_min, min_cameras, task),
            feasible=False,
        )
    return best


@dataclass(frozen=True, kw_only=True)
class TaskRow:
    """One simulated task."""

    task: int
    phase: str
    scale: float
    num_cameras: int
    camera_ids: tuple[int, ...]
    time_s: float
    quality: float
    deadline_s: float
    search_steps: int
    """Controller's search-step count after this task."""

    @property
    def miss(self) -> bool:
        return self.time_s > self.deadline_s

    def to_dict(self) -> dict[str, Any]:
        return {
            "task": self.task,
            "phase": self.phase,
            "scale": self.scale,
            "num_cameras": self.num_cameras,
            "camera_ids": list(self.camera_ids),
            "time_s": round(self.time_s, 6),
            "quality": round(self.quality, 6),
            "deadline_s": self.deadline_s,
            "miss": self.miss,
        }


@dataclass(frozen=True, kw_only=True)
class SimulationSummary:
    """Table III-like statistics of one run (after convergence = tasks in the adjust phase
    after the last search ended)."""

    deadline_s: float
    tasks: int
    search_steps: int
    """Tasks of the first search (golden included), as the paper counts them."""
    total_search_steps: int
    num_searches: int
    converged_task: int | None
    """First task of the final adjust phase (None: never converged)."""
    num_cameras: int | None
    """N' used most after convergence."""
    avg_scale: float
    """Mean r after convergence."""
    avg_time_s: float
    """Mean time over all tasks."""
    avg_time_converged_s: float
    """Mean time after convergence."""
    avg_quality: float
    avg_quality_converged: float
    misses: int
    """Tasks over the deadline (all)."""
    misses_converged: int
    """Tasks over the deadline after convergence."""
    tasks_converged: int

    @property
    def time_error(self) -> float:
        """(mean time after convergence - Δt) / Δt."""
        return self.avg_time_converged_s / self.deadline_s - 1.0

    def to_dict(self) -> dict[str, Any]:
        d = dict(self.__dict__)
        d["time_error"] = self.time_error
        return d


@dataclass(frozen=True, kw_only=True)
class SimulationResult:
    rows: list[TaskRow]
    summary: SimulationSummary
    events: list[dict[str, Any]] = field(default_factory=list)
    """The controller's re-searches."""
    chosen: tuple[float, int] | None = None
    """(r*, N') the first search chose."""


def simulate(
    controller: BisectionController,
    model: PipelineModel,
    num_tasks: int,
    seed: int = 0,
    deadline_schedule: Mapping[int, float] | None = None,
    camera_schedule: Mapping[int, tuple[Sequence[int], Any]] | None = None,
    on_task: Callable[[TaskRow], None] | None = None,
) -> SimulationResult:
    """Drive ``controller`` for ``num_tasks`` tasks on ``model``.

    ``deadline_schedule`` maps a task index to a new deadline (``set_deadline`` before that
    task); ``camera_schedule`` maps a task index to ``(available ids, camera mapping)``
    (``set_cameras``). The model's time depends on N' only, not on which cameras.
    """
    if num_tasks < 1:
        raise ValueError(f"num_tasks must be >= 1, got {num_tasks}")
    rng = np.random.default_rng(seed)
    rows: list[TaskRow] = []
    first_search_steps: int | None = None
    chosen: tuple[float, int] | None = None
    for i in range(num_tasks):
        if deadline_schedule and i in deadline_schedule:
            controller.set_deadline(deadline_schedule[i])
        if camera_schedule and i in camera_schedule:
            ids, mapping = camera_schedule[i]
            controller.set_cameras(ids, mapping)
        cfg: TaskConfig = controller.next_config()
        t, q = model.sample(cfg.scale, cfg.num_cameras, i, rng)
        if cfg.phase == "golden":
            q = 1.0  # the golden result is its own reference
        controller.observe(t, q)
        if first_search_steps is None and controller.phase == "adjust":
            first_search_steps = controller.search_steps
            if controller.chosen is not None:
                chosen = (controller.chosen.scale, controller.chosen.num_cameras)
        row = TaskRow(
            task=i,
            phase=cfg.phase,
            scale=cfg.scale,
            num_cameras=cfg.num_cameras,
            camera_ids=cfg.camera_ids,
            time_s=t,
            quality=q,
            deadline_s=controller.config.deadline_s,
            search_steps=controller.search_steps,
        )
        rows.append(row)
        if on_task is not None:
            on_task(row)
    summary = summarize(
        rows,
        search_steps=first_search_steps if first_search_steps is not None else len(rows),
        total_search_steps=controller.total_search_steps,
        num_searches=controller.num_searches,
    )
    return SimulationResult(rows=rows, summary=summary, events=controller.events, chosen=chosen)


def summarize(
    rows: Sequence[TaskRow], search_steps: int, total_search_steps: int, num_searches: int
) -> SimulationSummary:
    """Table III-like statistics of per-task rows."""
    conv = len(rows)
    for i in range(len(rows) - 1, -1, -1):
        if rows[i].phase != "adjust":
            break
        conv = i
    after = rows[conv:]
    times = np.array([r.time_s for r in rows])
    quals = np.array([r.quality for r in rows])

    def mean(x: Sequence[float] | NDArray[np.float64]) -> float:
        return float(np.mean(x)) if len(x) else math.nan

    counts: dict[int, int] = {}
    for r in after:
        counts[r.num_cameras] = counts.get(r.num_cameras, 0) + 1
    return SimulationSummary(
        deadline_s=rows[-1].deadline_s,
        tasks=len(rows),
        search_steps=search_steps,
        total_search_steps=total_search_steps,
        num_searches=num_searches,
        converged_task=conv if after else None,
        num_cameras=max(counts, key=lambda k: (counts[k], k)) if counts else None,
        avg_scale=mean([r.scale for r in after]),
        avg_time_s=mean(times),
        avg_time_converged_s=mean([r.time_s for r in after]),
        avg_quality=mean(quals),
        avg_quality_converged=mean([r.quality for r in after]),
        misses=int(sum(r.miss for r in rows)),
        misses_converged=int(sum(r.miss for r in after)),
        tasks_converged=len(after),
    )


def run_simulation(
    deadline_s: float,
    num_tasks: int = 100,
    seed: int = 0,
    simulator: SimulatorConfig | None = None,
    controller: ControllerConfig | None = None,
    camera_mapping: Any = None,
) -> SimulationResult:
    """Convenience: build the model and a controller (pi(N') = the N' lowest ids unless a
    mapping is given) and simulate."""
    sim = simulator or SimulatorConfig()
    model = PipelineModel(sim)
    cfg = controller or ControllerConfig(deadline_s=deadline_s)
    if cfg.deadline_s != deadline_s:
        from dataclasses import replace

        cfg = replace(cfg, deadline_s=deadline_s)
    mapping = camera_mapping or {n: tuple(range(n)) for n in range(1, sim.num_cameras + 1)}
    ctrl = BisectionController(cfg, mapping, sim.num_cameras)
    return simulate(ctrl, model, num_tasks, seed=seed)


# --------------------------------------------------------------------------- visibility


def synthetic_visibility(
    num_cameras: int,
    num_points: int,
    seed: int = 0,
    detection_rate: float = 0.7,
    max_angle_deg: float = 70.0,
    fov_deg: float = 50.0,
    num_objects: int = 3,
) -> tuple[NDArray[np.bool_], NDArray[np.float64], NDArray[np.float64]]:
    """A realistic (structured) visibility matrix: cameras on a ring around a few spherical
    objects; a surface point is seen by a camera when it faces it within ``max_angle_deg``,
    lies in its field of view, and its feature is detected and matched (probability
    ``detection_rate``). Returns (visibility (P, N), camera centres (N, 3), viewing
    directions (N, 3))."""
    rng = np.random.default_rng(seed)
    a = 2 * np.pi * np.arange(num_cameras) / num_cameras + rng.normal(0, 0.05, num_cameras)
    centers = np.stack([4 * np.cos(a), 4 * np.sin(a), rng.uniform(1.0, 2.5, num_cameras)], 1)
    target = np.array([0.0, 0.0, 1.0])
    dirs = target - centers
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    obj_c = rng.uniform([-1, -1, 0.5], [1, 1, 1.5], (num_objects, 3))
    obj_r = rng.uniform(0.3, 0.7, num_objects)
    obj = rng.integers(0, num_objects, num_points)
    normals = rng.normal(size=(num_points, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    pts = obj_c[obj] + obj_r[obj, None] * normals
    rays = centers[None] - pts[:, None]
    rays /= np.linalg.norm(rays, axis=2, keepdims=True)
    facing = np.einsum("pj,pnj->pn", normals, rays) > math.cos(math.radians(max_angle_deg))
    in_fov = np.einsum("nj,pnj->pn", dirs, -rays) > math.cos(math.radians(fov_deg / 2))
    detected = rng.random((num_points, num_cameras)) < detection_rate
    return facing & in_fov & detected, centers, dirs


def random_visibility(
    num_cameras: int, num_points: int, density: float, seed: int = 0
) -> NDArray[np.bool_]:
    """Unstructured visibility (each entry True with probability ``density``): the hard case
    for the key-point reduction."""
    return np.random.default_rng(seed).random((num_points, num_cameras)) < density
