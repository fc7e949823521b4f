"""``edgerecon run``: the online system on a dataset, task by task, within a deadline."""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import logging
import math
import shlex
import signal
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from edgerecon.cli._common import add_json_flag, console, emit_json, error_console, print_table
from edgerecon.cli._config import (
    DeadlineShare,
    add_config_flag,
    load_config,
    online_configs,
    parse_deadline,
    run_options_table,
    write_effective,
)
from edgerecon.cli._live import TaskDisplay
from edgerecon.cli.calib import adopt_rig
from edgerecon.cli.reconstruct import parse_cameras
from edgerecon.cli.view import add_live_view_arguments, live_viewer
from edgerecon.io.dataset import open_dataset
from edgerecon.pipeline import SPARSE_SCOPES
from edgerecon.quality.calibration import verdict_row
from edgerecon.runtime import FrameRange, RunSummary, SessionOptions, TaskMetrics
from edgerecon.runtime.config import ONLINE_QUALITIES
from edgerecon.runtime.messages import AFTER_CRITICAL_PATH
from edgerecon.runtime.online import run_online
from edgerecon.runtime.retention import RetentionConfig
from edgerecon.runtime.session import (
    FAULT_KINDS,
    RepairDue,
    RunInterrupted,
    camera_moves_row,
    offline_fscore_label,
    stabilised_row,
)
from edgerecon.runtime.state import describe_changes, recalibrations_row
from edgerecon.types import DataError

logger = logging.getLogger(__name__)

#: Exit codes of ``run`` (and ``demo``), documented in the README and ``run --help``.
EXIT_OK = 0
EXIT_BAD_INPUT = 2
EXIT_TASKS_FAILED = 3
EXIT_INTERRUPTED = 130

EXIT_CODES_HELP = f"""exit codes:
  {EXIT_OK}    every task was recorded ok (degraded and empty tasks included)
  {EXIT_BAD_INPUT}    bad input or refused before any work (options, dataset, --out in use
       by another run, not empty without --resume/--overwrite, a different dataset),
       or the outputs could not be written (the committed tasks stay: --resume)
  {EXIT_TASKS_FAILED}    the run finished but some tasks failed (see metrics.jsonl; summary.json
       is written)
  {EXIT_INTERRUPTED}  interrupted (Ctrl-C or SIGTERM): summary.json is written and the command
       to continue (--resume) is printed"""


def add_online_arguments(p: argparse.ArgumentParser) -> None:
    """Options shared by ``run`` and ``demo``."""
    p.add_argument(
        "--deadline",
        type=parse_deadline,
        required=False,
        metavar="S|P%",
        help="deadline per task (the average critical path aims at it): seconds, or a share "
        "of the original pipeline's time (r = 1, every camera, the whole scene: the paper's "
        "baseline) such as 40%%, measured on the first timestamp before the first task; "
        "required by run unless --config's [runtime] sets deadline_s or deadline_share",
    )
    p.add_argument(
        "--late-share",
        type=float,
        default=None,
        metavar="P",
        help="about this share of the tasks may run past the deadline (e.g. 0.1): the "
        "controller steers the average below the deadline by what the tasks' measured spread "
        "asks, instead of to the deadline, where a third of them can run late ([controller] "
        "late_share)",
    )
    add_config_flag(p)
    p.add_argument("--frames", default=None, help="timestamps A:B:STEP (default: the whole stream)")
    p.add_argument(
        "--engine",
        choices=("embedded", "ray"),
        default="embedded",
        help="embedded: both roles in this process (default); ray: actors on a Ray cluster",
    )
    p.add_argument(
        "--address",
        default=None,
        help="Ray cluster address (e.g. 'auto' or HEAD_IP:6379); default: a private "
        "local Ray instance on 127.0.0.1",
    )
    p.add_argument(
        "--policy",
        choices=("all", "newest"),
        default=None,
        help="all: every listed timestamp is a task (default for recorded frames); newest: "
        "frames arrive in real time and each task takes the newest one (live streams)",
    )
    p.add_argument(
        "--duration",
        type=float,
        default=None,
        metavar="SECONDS",
        help="live streams: stop after this many seconds (default: until Ctrl-C)",
    )
    p.add_argument(
        "--fixed",
        type=float,
        default=None,
        metavar="SCALE",
        help="no optimizer: run every task at this scale (with --cameras)",
    )
    p.add_argument("--cameras", default=None, help="camera ids for --fixed (default: all)")
    p.add_argument(
        "--no-background-updates",
        action="store_true",
        help="the back-end never rebuilds the background",
    )
    p.add_argument(
        "--background-scale",
        type=float,
        default=1.0,
        metavar="R",
        help="image scale of the back-end's background rebuilds, in (0, 1] (default 1)",
    )
    p.add_argument(
        "--sparse-scope",
        choices=SPARSE_SCOPES,
        default="hull",
        help="hull: SfM of the foreground masks on golden-configuration tasks only, the "
        "others take their depth ranges from the visual hull (default); foreground: SfM of "
        "the foreground masks on every task; scene: the paper's SfM of the whole frames, "
        "then the split",
    )
    p.add_argument(
        "--online-quality",
        choices=ONLINE_QUALITIES,
        default="silhouette",
        help="the controller's quality estimate: silhouette (the task's dense foreground "
        "against every camera's masks, default) or golden (the paper's: foreground sparse "
        "points against the back-end's golden reference)",
    )
    p.add_argument("--no-clouds", action="store_true", help="do not write per-task clouds")
    p.add_argument(
        "--keep-clouds",
        type=int,
        default=None,
        metavar="N",
        help="keep only the newest N tasks' clouds on disk (older ones are removed as the "
        "run goes on; their metrics stay); default: all",
    )
    p.add_argument(
        "--min-free-mb",
        type=float,
        default=RetentionConfig.min_free_mb,
        metavar="MB",
        help="free space (MiB) the run leaves on the disk of --out: the oldest task clouds "
        "are removed, then new ones are not written, before it goes under (default "
        "%(default)g; 0: no check)",
    )
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue the run in --out after its last committed task (same dataset, same "
        "--frames start and step; a new --deadline restarts the configuration search; a "
        "calibration that placed some cameras again, `edgerecon calib --write`, is taken "
        "from the next task on)",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace the run files in a non-empty --out (refused otherwise)",
    )
    p.add_argument(
        "--inject-fault",
        action="append",
        default=None,
        metavar="TASK:KIND[:SECONDS]",
        help="drill (repeatable): before task TASK, make the back-end stall for SECONDS "
        "(KIND=stall, default 30 s), crash (crash) or, with Ray, kill its process (kill), "
        "or make the front-end's task loop for ever (hang: the watchdog abandons it and "
        "stops its thread)",
    )
    add_live_view_arguments(p)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run",
        help="run the online system (front-end + back-end) on a dataset",
        description="Reconstruct a stream task by task within a deadline: the optimizer picks "
        "the image scale and cameras, the front-end computes the masks, the back-end rebuilds "
        "the background. Writes metrics.jsonl, per-task merged clouds and summary.json. A task "
        "that fails (any stage raises, or it runs past the watchdog of max(10 x deadline, "
        "30 s)) is recorded and the run goes on.",
        epilog=EXIT_CODES_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--dataset", required=True, help="dataset folder")
    p.add_argument("--out", "-o", required=True, help="output folder")
    add_online_arguments(p)
    p.add_argument(
        "--adopt-repairs",
        action="store_true",
        help="when the back-end's calibration check finds a camera moved and a re-aim or "
        "placement that makes the calibration fit (two checks agree, or frame sets pooled), "
        "name that rig in the "
        "dataset (as `edgerecon calib --adopt`: the dataset's dataset.json changes) and go on "
        f"with it, as a --resume would (at most {MAX_ADOPTIONS} times a run)",
    )
    add_json_flag(p)
    p.set_defaults(func=run)


def parse_faults(texts: list[str] | None) -> tuple[tuple[int, str, float], ...]:
    return tuple(parse_fault(t) for t in texts or ())


def parse_fault(text: str) -> tuple[int, str, float]:
    parts = text.split(":")
    usage = f"--inject-fault must be TASK:{'|'.join(FAULT_KINDS)}[:SECONDS], got {text!r}"
    if len(parts) not in (2, 3) or parts[1] not in FAULT_KINDS:
        raise ValueError(usage)
    try:
        return int(parts[0]), parts[1], float(parts[2]) if len(parts) == 3 else 30.0
    except ValueError:
        raise ValueError(usage) from None


def task_row(m: TaskMetrics) -> list[Any]:
    if m.status != "ok":
        return [m.task, m.time_index, "FAILED", "", "", "", "", "", "", m.error[:40]]
    f_on = "-" if m.online_fscore is None else f"{m.online_fscore:.3f}"
    f_off = "-" if m.offline_fscore is None else f"{m.offline_fscore:.3f}"
    return [
        m.task,
        m.time_index,
        m.phase,
        f"{m.scale:.2f}",
        m.num_cameras,
        f"{m.critical_path_s:.2f}",
        "yes" if m.deadline_met else "NO",
        f_on,
        f_off,
        f"{m.background_version}"
        + (" degraded" if m.degraded else "")
        + (" empty" if m.frame_defects and m.num_cameras < 3 else "")
        + (f" frozen {','.join(m.frozen_cameras)}" if m.frozen_cameras else "")
        + (f" moved {','.join(c['camera'] for c in m.camera_moves)}" if m.camera_moves else "")
        + (f" steadied {','.join(m.stabilised)}" if m.stabilised else ""),
    ]


TASK_COLUMNS = [
    "task",
    "time",
    "phase",
    "r",
    "N'",
    "T (s)",
    "met",
    "F online",
    "F offline",
    "background",
]


def live_printer(enabled: bool, total: int | None = None) -> TaskDisplay:
    """The task rows and the status line (task i/N, ETA) of a run: a context manager and
    the ``on_task`` callback (see ``cli._live``)."""
    widths = [4, 6, 7, 5, 3, 7, 4, 8, 9, 20]
    return TaskDisplay(columns=TASK_COLUMNS, widths=widths, row=task_row, total=total, rows=enabled)


def num_tasks(args: argparse.Namespace, dataset: Any) -> int | None:
    """How many tasks ``--frames`` makes (at most, with --policy newest; None for a live
    stream, which goes on until --duration or Ctrl-C)."""
    if getattr(dataset, "is_live", False):
        return None
    try:
        frames = FrameRange.parse(args.frames) if args.frames else FrameRange()
    except ValueError:
        return None
    return len(frames.indices(dataset.num_frames)) or None


def print_summary(title: str, s: RunSummary) -> None:
    def f(x: float | None, fmt: str = ".3f") -> str:
        return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, fmt)

    rows = [
        ("deadline (s)", f(s.deadline_s, ".3g")),
        ("avg. resolution scale", f(s.avg_scale, ".2f")),
        ("# cameras (avg / last subset)", f"{f(s.avg_cameras, '.1f')} / {s.cameras_used}"),
        ("avg. processing time (s)", f(s.avg_time_s, ".2f")),
        ("avg. time after convergence (s)", f(s.avg_time_converged_s, ".2f")),
        ("deadline misses after convergence", s.deadline_misses_converged),
        ("avg. F-score of FG (online)", f(s.avg_online_fscore)),
        (offline_fscore_label(s.offline_threshold, s.unit), f(s.avg_offline_fscore)),
        ("# backgrounds pushed", s.backgrounds_pushed),
        ("# configuration search steps", s.search_steps),
        (
            "tasks that kept the still foreground (share still) / snapshots",
            f"{s.still_tasks} ({f(s.avg_still_share, '.2f')}) / {s.snapshots_pushed}",
        ),
        ("tasks / failed / degraded / empty", f"{s.tasks} / {s.failed} / {s.degraded} / {s.empty}"),
        ("background at the end (epoch.counter)", f"v{s.bg_version[0]}.{s.bg_version[1]}"),
        ("frames dropped (newest policy)", s.frames_dropped),
        (
            "task clouds written / kept / not written (disk)",
            f"{s.clouds_written} / {s.clouds_kept} / {s.clouds_skipped}",
        ),
        ("wall time (s)", f(s.wall_s, ".1f")),
    ]
    if s.camera_moves:
        rows.append(camera_moves_row(s.camera_moves))
    if s.stabilised:
        rows.append(stabilised_row(s.stabilised))
    if s.recalibrations:
        rows.append(recalibrations_row(s.recalibrations, s.unit))
    if s.calibration is not None:
        rows.append(verdict_row(s.calibration))
    mem = s.memory_mb
    if mem.get("last") is not None:
        rows.append(
            (
                "memory, this process: first / last task, peak (MB)",
                f"{mem['first']:,.0f} / {mem['last']:,.0f}, "
                + ("-" if mem.get("peak") is None else f"{mem['peak']:,.0f}"),
            )
        )
    if s.original_s is not None:  # measured by the run (--deadline P%)
        share = "" if s.deadline_share is None else f" ({100 * s.deadline_share:g} % of it)"
        if s.original_node is not None:  # a Ray cluster: timed where the front-end runs
            share += f", on the front-end's node {s.original_node[:12]}"
        rows[1:1] = [
            (f"original pipeline, r = 1, whole scene (s){share}", f(s.original_s, ".2f")),
            ("online / original (avg. processing time)", f(s.online_over_original)),
        ]
    if s.stream:
        st = s.stream
        spread = (
            "-"
            if st.get("sync_spread_mean_s") is None
            else f"{st['sync_spread_mean_s'] * 1000:.1f} / {st['sync_spread_max_s'] * 1000:.1f}"
        )
        rows += [
            ("sync spread mean / max (ms)", spread),
            ("camera stalls / returns", f"{st['stalls']} / {st['returns']}"),
            ("reads without 3 synchronized cameras", st["no_set"]),
            (
                "sets that waited for sync / cameras left out of sync",
                f"{st['waited']} / {st['left_out_of_sync']}",
            ),
        ]
    print_table(title, ["metric", "value"], rows)
    if s.stage_means_s:
        print_table(
            "stages per task (mean seconds)",
            ["stage", "seconds", "when"],
            [
                (k, v, "after the cloud" if k in AFTER_CRITICAL_PATH else "critical path")
                for k, v in sorted(s.stage_means_s.items(), key=lambda kv: -kv[1])
            ],
        )


#: Task records a live stream's run keeps in memory (``SessionOptions.keep_metrics``) and
#: prints with ``--json``: the newest.
LIVE_RECORDS = 1000


def build_options(
    args: argparse.Namespace, dataset: Any, gt_threshold: float | None, *, overwrite: bool = False
) -> SessionOptions:
    return SessionOptions(
        frames=FrameRange.parse(args.frames) if args.frames else FrameRange(),
        policy=args.policy or ("newest" if dataset.is_live else "all"),
        duration_s=args.duration,
        # A live stream runs for hours: its records stay in metrics.jsonl, not in memory.
        keep_metrics=LIVE_RECORDS if dataset.is_live else None,
        write_clouds=not args.no_clouds,
        retention=RetentionConfig(keep_clouds=args.keep_clouds, min_free_mb=args.min_free_mb),
        ground_truth_threshold=gt_threshold if dataset.ground_truth is not None else None,
        resume=args.resume,
        overwrite=args.overwrite or (overwrite and not args.resume),
        faults=parse_faults(args.inject_fault),
        adopt_repairs=getattr(args, "adopt_repairs", False),
    )


def parse_fixed(
    args: argparse.Namespace, dataset: Any
) -> tuple[float, tuple[int, ...] | None] | None:
    """``--fixed`` and ``--cameras`` (checked against the rig by ``run_online``)."""
    if args.fixed is None:
        if args.cameras is not None:
            raise ValueError("--cameras chooses the cameras of --fixed: give --fixed SCALE too")
        return None
    return args.fixed, parse_cameras(args.cameras, dataset.rig)


def resume_command(args: argparse.Namespace) -> str:
    """The command line that continues this run."""
    words = ["edgerecon", "run", "--dataset", args.dataset, "--out", args.out]
    deadline = args.deadline
    words += [
        "--deadline",
        str(deadline) if isinstance(deadline, DeadlineShare) else f"{deadline:g}",
    ]
    for flag, value in (
        ("--frames", args.frames),
        ("--engine", None if args.engine == "embedded" else args.engine),
        ("--address", args.address),
        ("--policy", None if args.policy == "all" else args.policy),
        ("--fixed", None if args.fixed is None else f"{args.fixed:g}"),
        ("--cameras", args.cameras),
        ("--sparse-scope", None if args.sparse_scope == "hull" else args.sparse_scope),
        ("--late-share", None if args.late_share is None else f"{args.late_share:g}"),
    ):
        if value is not None:
            words += [flag, str(value)]
    if args.background_scale != 1.0:
        words += ["--background-scale", f"{args.background_scale:g}"]
    words += ["--no-background-updates"] if args.no_background_updates else []
    words += ["--no-clouds"] if args.no_clouds else []
    words += ["--adopt-repairs"] if getattr(args, "adopt_repairs", False) else []
    if args.keep_clouds is not None:
        words += ["--keep-clouds", str(args.keep_clouds)]
    if args.min_free_mb != RetentionConfig.min_free_mb:
        words += ["--min-free-mb", f"{args.min_free_mb:g}"]
    return shlex.join([*words, "--resume"])


@contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """SIGTERM stops a run as Ctrl-C does (summary written, --resume printed)."""

    def handler(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    try:
        previous = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread: leave signals alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


#: ``--adopt-repairs``: repaired calibrations a run takes at most (a rig whose repair
#: keeps coming back needs a calibration).
MAX_ADOPTIONS = 3


def run(args: argparse.Namespace) -> int:
    dataset = open_dataset(args.dataset)
    config, controller_config = online_configs(args, load_config(args))
    # (from --config too) the resume command repeats it
    share = config.deadline_share
    args.deadline = config.deadline_s if share is None else DeadlineShare(share)
    fixed = parse_fixed(args, dataset)
    options = build_options(args, dataset, config.eval_threshold_for(dataset.rig))
    if options.adopt_repairs and dataset.layout != "descriptor":
        raise DataError(
            f"--adopt-repairs: {dataset.root} has no dataset.json to name a repaired rig in "
            "(make one with edgerecon import)"
        )

    def start(on_task: Callable[[TaskMetrics], None]) -> tuple[RunSummary, list[TaskMetrics]]:
        ds, opts, scene = dataset, options, None
        began = time.monotonic()
        for adoptions in itertools.count(1):
            try:
                return run_online(
                    ds,
                    config,
                    opts,
                    args.out,
                    engine=args.engine,
                    address=args.address,
                    fixed=fixed,
                    controller_config=controller_config,
                    on_task=on_task,
                    command=resume_command(args).removesuffix(" --resume"),
                    scene=scene,
                )
            except RepairDue as due:
                more = adoptions < MAX_ADOPTIONS
                try:
                    changes, written, _ = adopt_rig(ds, due.rig)
                except DataError as exc:  # not adopted: the run goes on as it was
                    logger.warning("--adopt-repairs: the repaired rig is %s: not adopted", exc)
                    more = False
                else:
                    logger.warning(
                        "--adopt-repairs: %s after %d tasks: %s named in the dataset; the run "
                        "goes on with it%s",
                        describe_changes(changes, ds.rig.unit) or "nothing changed",
                        due.summary.tasks,
                        written,
                        "" if more else f" (the last of {MAX_ADOPTIONS} a run takes)",
                    )
                ds = open_dataset(args.dataset)
                duration = options.duration_s
                if duration is not None:  # --duration is the whole run's, restarts included
                    duration = max(duration - (time.monotonic() - began), 1e-3)
                opts = dataclasses.replace(
                    opts, resume=True, overwrite=False, adopt_repairs=more, duration_s=duration
                )
                scene = due.scene  # the models go on (not learned again from the stream)
        raise AssertionError("unreachable")

    code = run_and_report(
        args,
        start,
        title=f"{dataset.name}: online run, deadline "
        + (f"{config.deadline_s:g} s" if share is None else f"{args.deadline} of the original"),
        total=num_tasks(args, dataset),
    )
    effective = {"runtime": config, "controller": controller_config, "run": run_options_table(args)}
    write_effective(args.out, "run", effective)
    return code


def say_repaired_rig(args: argparse.Namespace, summary: RunSummary) -> None:
    """When the run wrote ``rig.repaired.json`` (its calibration check found a camera moved
    and the rig that fits): the commands that take it (on stderr: ``--json`` keeps stdout)."""
    cal = summary.calibration or {}
    name = cal.get("repaired_rig_file")
    if not name or not getattr(args, "dataset", None):
        return
    path = Path(args.out) / str(name)
    adopt = shlex.join(["edgerecon", "calib", "--dataset", str(args.dataset), "--adopt", str(path)])
    why = (
        "a camera moved and its frames were turned back"  # the turned-back frames fit
        if cal.get("fits") is not False
        else "the calibration does not fit the frames"
    )
    error_console.print(
        f"[yellow]{why}[/]: {path} holds the rig that "
        f"fits ({cal.get('repair')}); take it with:\n  {adopt}\nthen go on "
        f"with:\n  {resume_command(args)}",
        highlight=False,
        soft_wrap=True,
    )


def run_and_report(
    args: argparse.Namespace, start: Any, *, title: str, total: int | None = None
) -> int:
    """Run ``start(on_task)`` (-> summary, metrics) inside the live display, print or emit
    the result and return the exit code (see ``EXIT_CODES_HELP``)."""
    try:
        with (
            sigterm_as_interrupt(),
            live_viewer(args, args.out),
            live_printer(not args.json, total) as on_task,
        ):
            summary, metrics = start(on_task)
    except RunInterrupted as stop:
        error_console.print(
            f"[yellow]interrupted after {stop.summary.tasks} tasks[/] (summary.json written); "
            f"continue with:\n  {resume_command(args)}",
            highlight=False,
            soft_wrap=True,
        )
        say_repaired_rig(args, stop.summary)
        if args.json:
            emit_json(
                {"summary": stop.summary.to_dict(), "tasks": [m.to_dict() for m in stop.metrics]}
            )
        return EXIT_INTERRUPTED
    if args.json:
        emit_json({"summary": summary.to_dict(), "tasks": [m.to_dict() for m in metrics]})
    else:
        print_summary(title, summary)
        console.print(f"outputs in {args.out}")
    say_repaired_rig(args, summary)
    if summary.failed:
        error_console.print(
            f"[red]{summary.failed} of {summary.tasks} tasks failed[/] (reasons in "
            f"{args.out}/metrics.jsonl)",
            highlight=False,
            soft_wrap=True,
        )
        return EXIT_TASKS_FAILED
    return EXIT_OK
