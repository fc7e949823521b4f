"""Figures of online runs (``edgerecon report``), in the shape of the paper's Section V.

From one or more run folders (``metrics.jsonl`` [+ ``summary.json``]) :func:`write_report`
writes, atomically, PNG figures and a one-page summary:

* ``latency.png``: critical path per task against the deadline (the paper's processing time
  per task), missed deadlines marked, failed tasks as ticks on the axis, degraded tasks
  hollow, and the original pipeline's time where the run measured it (``--deadline P%``);
* ``configuration.png``: image scale r and number of cameras N' over tasks (the paper's
  resolution adaptation), the controller's phase as a background band;
* ``quality.png``: online F-score (against the golden sparse reference) and, on synthetic
  scenes, offline F-score against ground truth, over tasks;
* ``background.png``: background version merged into each task, against the run's wall
  clock, with the tasks' timeline;
* ``stages.png``: mean critical-path seconds per stage;
* ``summary.png``: one page with the run's summary table (the paper's Table III) and the
  four main plots.

Several runs (e.g. the same scene at deadlines 5, 7.5 and 10 s) share each figure, one
colour per run, as the paper compares deadlines. Matplotlib renders off-screen (Agg): no
display is needed.
"""

from __future__ import annotations

import dataclasses
import io
import math
import os
import textwrap
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from edgerecon.io.ply import atomic_write_bytes
from edgerecon.quality.calibration import verdict_row
from edgerecon.runtime.messages import AFTER_CRITICAL_PATH, TaskMetrics
from edgerecon.runtime.session import camera_moves_row, offline_fscore_label, stabilised_row
from edgerecon.runtime.state import recalibrations_row
from edgerecon.types import EdgereconError
from edgerecon.viewer.rundir import read_run

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

#: Files :func:`write_report` writes, in order.
FIGURES = (
    "latency",
    "configuration",
    "quality",
    "background",
    "stages",
    "memory",
    "summary",
)
_COLORS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#17becf")
_PHASE_SHADE = {"golden": "#f2f2f2", "search": "#fff3e0", "adjust": "#e8f5e9"}


@dataclass(frozen=True, kw_only=True)
class RunData:
    """One run's records, as the figures need them."""

    path: Path
    label: str
    tasks: list[TaskMetrics]
    summary: dict[str, Any] | None
    """``summary.json`` (None while the run is in progress)."""
    original_s: float | None = None
    """The original pipeline's time the run measured (``run --deadline P%``), else None."""

    @property
    def ok(self) -> list[TaskMetrics]:
        return [m for m in self.tasks if m.status == "ok"]

    @property
    def deadline_s(self) -> float:
        values = [m.deadline_s for m in self.tasks if m.deadline_s]
        return float(values[-1]) if values else math.nan


def load_runs(paths: Sequence[str | os.PathLike[str]]) -> list[RunData]:
    """Read run folders (``EdgereconError`` for a folder that is not a run or has no task)."""
    runs = []
    for p in paths:
        folder = read_run(p)
        if not folder.tasks:
            raise EdgereconError(f"{folder.path}: the run has no task yet")
        runs.append(
            RunData(
                path=folder.path,
                label="",
                tasks=folder.tasks,
                summary=folder.summary(),
                original_s=folder.original_s(),
            )
        )
    deadlines = [r.deadline_s for r in runs]
    distinct = len({round(d, 3) for d in deadlines}) == len(runs)
    out = []
    for r in runs:
        name = r.path.name if r.path.name not in ("run", "") else r.path.parent.name
        label = f"deadline {r.deadline_s:g} s" if distinct and len(runs) > 1 else name
        if len(runs) == 1:
            label = f"{name} (deadline {r.deadline_s:g} s)"
        out.append(dataclasses.replace(r, label=label))
    return out


# ============================================================================== figures
def _new_figure(width: float = 8.0, height: float = 4.0) -> Figure:
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), dpi=110, layout="constrained")


def plot_latency(ax: Axes, runs: Sequence[RunData]) -> None:
    """Critical path per task against each run's deadline."""
    for run, color in zip(runs, _COLORS, strict=False):
        ok = run.ok
        x = np.array([m.task for m in ok])
        y = np.array([m.critical_path_s for m in ok])
        # The line breaks at failed tasks (NaN).
        ax.plot(
            [m.task for m in run.tasks],
            [m.critical_path_s if m.status == "ok" else np.nan for m in run.tasks],
            "-",
            color=color,
            lw=1.2,
            label=run.label,
        )
        full = np.array([not m.degraded for m in ok], bool)
        ax.plot(x[full], y[full], "o", color=color, ms=3.5)
        ax.plot(x[~full], y[~full], "o", mfc="none", color=color, ms=5, label=None)
        miss = np.array([not m.deadline_met for m in ok], bool)
        ax.plot(x[miss], y[miss], "x", color="black", ms=5)
        ax.axhline(run.deadline_s, color=color, ls="--", lw=1)
        if run.original_s is not None:
            ax.axhline(run.original_s, color=color, ls=":", lw=1)
        failed = [m.task for m in run.tasks if m.status != "ok"]
        if failed:
            ax.plot(failed, np.zeros(len(failed)), "|", color=color, ms=12, mew=2)
    ax.set_xlabel("task")
    ax.set_ylabel("critical path (s)")
    ax.set_ylim(bottom=0)
    original = any(r.original_s is not None for r in runs)
    ax.set_title(
        "processing time per task (dashed: deadline, "
        + ("dotted: original pipeline,\n" if original else "")
        + "x: missed, o: degraded)",
        fontsize=10 if original else None,
    )
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)


def _shade_phases(ax: Axes, run: RunData) -> None:
    ok = run.ok
    if not ok:
        return
    start = ok[0].task
    phase = ok[0].phase
    for prev, m in zip(ok, [*ok[1:], None], strict=True):
        if m is None or m.phase != phase:
            end = prev.task + 0.5
            ax.axvspan(start - 0.5, end, color=_PHASE_SHADE.get(phase, "white"), lw=0, zorder=0)
            if m is not None:
                start, phase = m.task, m.phase


def plot_configuration(ax_r: Axes, ax_n: Axes, runs: Sequence[RunData]) -> None:
    """Image scale r and N' over tasks (step plots)."""
    if len(runs) == 1:
        _shade_phases(ax_r, runs[0])
        _shade_phases(ax_n, runs[0])
    for run, color in zip(runs, _COLORS, strict=False):
        ok = run.ok
        x = [m.task for m in ok]
        ax_r.step(x, [m.scale for m in ok], where="mid", color=color, label=run.label)
        ax_n.step(x, [m.num_cameras for m in ok], where="mid", color=color)
    scales = [m.scale for run in runs for m in run.ok]
    top = max([1.0, *scales])
    if top > 1.0:
        # Above 1: the golden camera set with a finer foreground than the golden task's.
        ax_r.axhline(1.0, color="0.6", linewidth=0.8, linestyle=":")
        ax_r.set_ylabel("r (> 1: finer than golden)")
    else:
        ax_r.set_ylabel("image scale r")
    ax_r.set_ylim(0, top + 0.05)
    ax_n.set_ylabel("cameras N'")
    ax_n.set_xlabel("task")
    from matplotlib.ticker import MaxNLocator

    ax_n.yaxis.set_major_locator(MaxNLocator(integer=True))
    counts = [m.num_cameras for run in runs for m in run.ok]
    if counts:  # a constant N' would get ticks at fractions of a camera
        ax_n.set_ylim(min(counts) - 1, max(counts) + 1)
    title = "configuration per task"
    if len(runs) == 1:
        title += " (grey: golden, orange: search, green: adjust)"
    ax_r.set_title(title)
    for ax in (ax_r, ax_n):
        ax.grid(alpha=0.3)
    ax_r.legend(loc="best", fontsize=8)


def plot_quality(ax: Axes, runs: Sequence[RunData]) -> None:
    """Online (solid) and offline (dotted) F-scores over tasks."""
    for run, color in zip(runs, _COLORS, strict=False):
        ok = run.ok
        on = [(m.task, m.online_fscore) for m in ok if m.online_fscore is not None]
        off = [(m.task, m.offline_fscore) for m in ok if m.offline_fscore is not None]
        if on:
            ax.plot(*zip(*on, strict=True), "-o", color=color, ms=3, label=f"{run.label}: online")
        if off:
            ax.plot(*zip(*off, strict=True), ":s", color=color, ms=3, label=f"{run.label}: offline")
    ax.set_ylim(0, 1.02)
    moved = False
    for run, color in zip(runs, _COLORS, strict=False):
        for task, names in camera_moves_at(run):
            moved = True
            ax.axvline(task, color=color, ls="-.", lw=0.9)
            ax.text(task, 0.03, " " + ", ".join(names) + " moved", color=color, fontsize=7)
    ax.set_xlabel("task")
    ax.set_ylabel("F-score (foreground)")
    ax.set_title(
        "quality per task (online: the estimate; offline: vs ground truth"
        + ("; dash-dot: a camera's view moved)" if moved else ")")
    )
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)


def camera_moves_at(run: RunData) -> list[tuple[int, list[str]]]:
    """The tasks that saw a camera's view move (``TaskMetrics.camera_moves``), with the
    cameras: each camera's first 3 moves (one that keeps moving, a swaying mount, is marked
    where it started)."""
    seen: dict[str, int] = {}
    marks = []
    for m in run.tasks:
        names = []
        for move in m.camera_moves:
            name = move["camera"]
            seen[name] = seen.get(name, 0) + 1
            if seen[name] <= 3 and name not in names:
                names.append(name)
        if names:
            marks.append((m.task, names))
    return marks


def plot_background(ax: Axes, runs: Sequence[RunData]) -> None:
    """Background version merged into each task, over the run's wall clock."""
    # A version is (back-end epoch, counter) where the run records epochs (a restarted
    # back-end counts from 1 again): plotted in order, labelled "v<epoch>.<counter>".
    versions = sorted({_version(m) for r in runs for m in r.ok})
    with_epochs = any(e for e, _ in versions)
    for run, color in zip(runs, _COLORS, strict=False):
        ok = [m for m in run.ok if m.wall_time]
        if not ok:
            continue
        t0 = ok[0].wall_time - ok[0].critical_path_s
        t = [m.wall_time - t0 for m in ok]
        v = [versions.index(_version(m)) if with_epochs else m.bg_version for m in ok]
        ax.step(t, v, where="post", color=color, label=run.label)
        ax.plot(t, v, ".", color=color, ms=3)
    ax.set_xlabel("wall time since the first task started (s)")
    ax.set_ylabel("background version")
    if with_epochs:
        ax.set_yticks(range(len(versions)), [f"v{e}.{c}" for e, c in versions])
    else:
        from matplotlib.ticker import MaxNLocator

        ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_title("background versions merged (points: tasks)")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)


def plot_memory(ax: Axes, runs: Sequence[RunData]) -> None:
    """The run's main process's resident memory at each task's commit, over the wall clock
    (a long live run on a small device: does it level off?)."""
    for run, color in zip(runs, _COLORS, strict=False):
        tasks = [m for m in run.tasks if m.wall_time and m.rss_mb is not None]
        if not tasks:
            continue
        t0 = tasks[0].wall_time
        minutes = [(m.wall_time - t0) / 60.0 for m in tasks]
        rss = [float(m.rss_mb or 0.0) for m in tasks]
        ax.plot(minutes, rss, "-", color=color, lw=1, label=run.label)
    if not ax.lines:
        ax.text(0.5, 0.5, "no memory recorded", ha="center", va="center", transform=ax.transAxes)
    ax.set_xlabel("minutes since the first task")
    ax.set_ylabel("resident memory (MB)")
    ax.set_title("the run's main process's memory (each task's)")
    ax.grid(alpha=0.3)
    if ax.lines:
        ax.legend(loc="best", fontsize=8)


def _version(m: TaskMetrics) -> tuple[int, int]:
    return int(getattr(m, "bg_epoch", 0)), int(m.bg_version)


def stage_means(run: RunData) -> dict[str, float]:
    """Mean seconds per critical-path stage over the run's successful tasks (tasks that
    skipped a stage count 0 for it; the stages after the path, ``AFTER_CRITICAL_PATH``,
    left out)."""
    ok = run.ok
    sums: dict[str, float] = {}
    for m in ok:
        for k, v in m.stages.items():
            if k not in AFTER_CRITICAL_PATH:
                sums[k] = sums.get(k, 0.0) + float(v)
    return {k: v / len(ok) for k, v in sums.items()} if ok else {}


def plot_stages(ax: Axes, runs: Sequence[RunData]) -> None:
    """Mean critical-path seconds per stage (horizontal bars, one group per run)."""
    means = [stage_means(r) for r in runs]
    names = sorted({k for m in means for k in m}, key=lambda k: -max(m.get(k, 0) for m in means))
    y = np.arange(len(names))
    h = 0.8 / max(len(runs), 1)
    for i, (run, m, color) in enumerate(zip(runs, means, _COLORS, strict=False)):
        ax.barh(y + i * h, [m.get(k, 0.0) for k in names], h, color=color, label=run.label)
    ax.set_yticks(y + h * (len(runs) - 1) / 2, names, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("mean seconds per task")
    ax.set_title("critical path by stage")
    ax.grid(axis="x", alpha=0.3)
    ax.legend(loc="best", fontsize=8)


def summary_rows(run: RunData) -> list[tuple[str, str]]:
    """The run's summary (Table III's rows) from ``summary.json``, or computed from the
    tasks while the run is in progress."""
    s = run.summary
    ok = run.ok

    def fmt(v: Any, spec: str = ".3f") -> str:
        if v is None or (isinstance(v, float) and not math.isfinite(v)):
            return "-"
        return format(v, spec)

    def mean(values: list[float]) -> float | None:
        return float(np.mean(values)) if values else None

    if s is None:
        on = [m.online_fscore for m in ok if m.online_fscore is not None]
        off = [m.offline_fscore for m in ok if m.offline_fscore is not None]
        s = {
            "avg_scale": mean([m.scale for m in ok]),
            "avg_cameras": mean([m.num_cameras for m in ok]),
            "cameras_used": ok[-1].camera_ids if ok else [],
            "avg_time_s": mean([m.critical_path_s for m in ok]),
            "avg_online_fscore": mean(on),
            "avg_offline_fscore": mean(off),
            "backgrounds_pushed": max((m.bg_version for m in ok), default=0),
            "search_steps": max((m.search_steps for m in ok), default=0),
            "still_tasks": sum(m.still_share is not None for m in ok),
            "avg_still_share": mean([m.still_share for m in ok if m.still_share is not None]),
            "degraded": sum(m.degraded for m in ok),
            "frames_dropped": None,
            "wall_s": None,
        }
    misses = sum(not m.deadline_met for m in ok)
    rss = [m.rss_mb for m in run.tasks if m.rss_mb is not None]
    memory = (
        [
            (
                "memory: first / last / largest task (MB)",
                f"{rss[0]:.0f} / {rss[-1]:.0f} / {max(rss):.0f}",
            )
        ]
        if rss
        else []
    )
    original = []
    if run.original_s is not None:
        avg = mean([m.critical_path_s for m in ok])
        original = [
            ("original pipeline, r = 1, whole scene (s)", fmt(run.original_s, ".2f")),
            ("online / original", fmt(None if avg is None else avg / run.original_s)),
        ]
    return [
        ("run", f"{run.path}" + ("" if run.summary is not None else " (in progress)")),
        ("deadline (s)", fmt(run.deadline_s, ".3g")),
        *original,
        ("avg. resolution scale r", fmt(s.get("avg_scale"), ".2f")),
        (
            "# cameras (avg / last subset)",
            f"{fmt(s.get('avg_cameras'), '.1f')} / {s.get('cameras_used')}",
        ),
        ("avg. processing time (s)", fmt(s.get("avg_time_s"), ".2f")),
        ("avg. time after convergence (s)", fmt(s.get("avg_time_converged_s"), ".2f")),
        (
            "deadline misses (all / after convergence)",
            f"{misses} / {s.get('deadline_misses_converged', '-')}",
        ),
        ("avg. F-score of FG (online)", fmt(s.get("avg_online_fscore"))),
        (
            offline_fscore_label(s.get("offline_threshold"), s.get("unit") or ""),
            fmt(s.get("avg_offline_fscore")),
        ),
        ("# backgrounds pushed", str(s.get("backgrounds_pushed"))),
        ("# configuration search steps", str(s.get("search_steps"))),
        (
            "tasks that kept the still foreground (share still) / snapshots",
            f"{s.get('still_tasks', '-')} ({fmt(s.get('avg_still_share'), '.2f')})"
            f" / {s.get('snapshots_pushed', '-')}",
        ),
        (
            "tasks / failed / degraded",
            f"{len(run.tasks)} / {len(run.tasks) - len(ok)} / {s.get('degraded')}",
        ),
        ("frames dropped", str(s.get("frames_dropped", "-"))),
        ("wall time (s)", fmt(s.get("wall_s"), ".1f")),
        *memory,
        *([camera_moves_row(mv)] if (mv := s.get("camera_moves")) else []),
        *([stabilised_row(st)] if (st := s.get("stabilised")) else []),
        *([recalibrations_row(rc, s.get("unit"))] if (rc := s.get("recalibrations")) else []),
        *([verdict_row(cal)] if isinstance(cal := s.get("calibration"), dict) else []),
    ]


def figure(name: str, runs: Sequence[RunData]) -> Figure:
    """The figure ``name`` (one of ``FIGURES``) of ``runs``."""
    if name == "latency":
        fig = _new_figure()
        plot_latency(fig.add_subplot(), runs)
    elif name == "configuration":
        fig = _new_figure(8.0, 5.0)
        ax_r, ax_n = fig.subplots(2, 1, sharex=True)
        plot_configuration(ax_r, ax_n, runs)
    elif name == "quality":
        fig = _new_figure()
        plot_quality(fig.add_subplot(), runs)
    elif name == "background":
        fig = _new_figure()
        plot_background(fig.add_subplot(), runs)
    elif name == "stages":
        fig = _new_figure(8.0, 0.6 + 0.32 * max(4, len(stage_means(runs[0]))))
        plot_stages(fig.add_subplot(), runs)
    elif name == "memory":
        fig = _new_figure()
        plot_memory(fig.add_subplot(), runs)
    elif name == "summary":
        fig = _summary_page(runs)
    else:
        raise ValueError(f"figure must be one of {FIGURES}, got {name!r}")
    return fig


_TABLE_COLUMNS = (0.55, 0.45)
"""The summary page's table: the two columns' shares of its width."""


def _wrapped(row: tuple[str, str], width_pt: float, font_pt: float) -> tuple[str, str]:
    """A summary row's two texts wrapped to the page table's columns (a table ``width_pt``
    wide, about 0.6 of the font size per character, a cell's padding left free)."""
    per_char = 0.6 * font_pt
    return tuple(  # type: ignore[return-value]
        "\n".join(textwrap.wrap(text, max(12, int(width_pt * share / per_char) - 3)) or [""])
        for text, share in zip(row, _TABLE_COLUMNS, strict=True)
    )


def _num_lines(row: tuple[str, str]) -> int:
    return max(text.count("\n") for text in row) + 1


def _summary_page(runs: Sequence[RunData]) -> Figure:
    """One A4 page: a summary table per run, then latency, configuration, quality and
    background plots."""
    from matplotlib.transforms import Bbox

    fig = _new_figure(8.27, 11.69)
    # Each run's table in two columns of text wrapped to the column (a calibration verdict,
    # the cameras that moved: a line of text can be longer than the page is wide); the
    # tables take the height their lines need from the plots below them.
    font = 8.0 if len(runs) < 2 else 7.0
    width_pt = 8.27 * 72 * (0.85 if len(runs) < 2 else 0.42)
    tables = [[_wrapped(row, width_pt, font) for row in summary_rows(run)[1:]] for run in runs[:2]]
    heads = [_wrapped((run.label, ""), width_pt, font) for run in runs[:2]]
    lines = [sum(_num_lines(row) for row in [h, *t]) for h, t in zip(heads, tables, strict=True)]
    table_in = max(lines) * font / 72 * 1.5  # inches: a line and its cell's padding
    plots = 3.25  # the height ratios of the plots below (1, 1, 0.55, 0.55)
    grid = fig.add_gridspec(
        6,
        2,
        height_ratios=[0.15, plots * table_in / max(9.0 - table_in, 3.0), 1, 1, 0.55, 0.55],
    )
    head = fig.add_subplot(grid[0, :])
    head.axis("off")
    head.text(
        0,
        0.5,
        "edgerecon online run" + ("s" if len(runs) > 1 else ""),
        fontsize=15,
        weight="bold",
        va="center",
    )
    for i, (rows, head_row, n) in enumerate(zip(tables, heads, lines, strict=True)):
        ax = fig.add_subplot(grid[1, i] if len(runs) > 1 else grid[1, :])
        ax.axis("off")
        share = n / max(lines)  # a shorter table keeps the line height of the longer one
        table = ax.table(
            cellText=[[k, v] for k, v in rows],
            colLabels=list(head_row),
            cellLoc="left",
            colWidths=list(_TABLE_COLUMNS),
            bbox=Bbox.from_bounds(0.0, 1.0 - share, 1.0, share),
        )
        table.auto_set_font_size(False)
        table.set_fontsize(font)
        for (r, _), cell in table.get_celld().items():
            # A row's share of the table: its lines (a wrapped row is as many lines high as
            # its longer cell; the table scales the rows to its box).
            cell.set_height(_num_lines(head_row if r == 0 else rows[r - 1]) / n)
    plot_latency(fig.add_subplot(grid[2, :]), runs)
    plot_quality(fig.add_subplot(grid[3, :]), runs)
    ax_r = fig.add_subplot(grid[4, 0])
    ax_n = fig.add_subplot(grid[5, 0], sharex=ax_r)
    plot_configuration(ax_r, ax_n, runs)
    ax_r.set_title("configuration per task", fontsize=10)
    plot_background(fig.add_subplot(grid[4:, 1]), runs)
    for ax in fig.axes:
        ax.title.set_fontsize(9)
    return fig


def write_report(
    run_dirs: Sequence[str | os.PathLike[str]], out_dir: str | os.PathLike[str]
) -> dict[str, Path]:
    """Write every figure of ``FIGURES`` as ``out_dir/<name>.png`` (atomically); returns
    their paths by name."""
    runs = load_runs(run_dirs)
    out = Path(out_dir)
    paths = {}
    for name in FIGURES:
        fig = figure(name, runs)
        buf = io.BytesIO()
        fig.savefig(buf, format="png")
        paths[name] = atomic_write_bytes(
            out / f"{name}.png", lambda f, b=buf: f.write(b.getvalue())
        )
    return paths


def matplotlib_available() -> bool:
    import importlib.util

    return importlib.util.find_spec("matplotlib") is not None
