"""``edgerecon demo``: the whole system on a synthetic scene with exact ground truth.

Generates a small scene (5 cameras, 640x480, 40 timestamps, 2 actors) in the work folder
(reused when it is already there), measures the original pipeline (golden configuration,
whole scene) on one timestamp, then runs the online system — optimizer, front-end and
back-end — with a deadline (by default 40% of that golden time), printing per-task latency
and the foreground F-score against ground truth, and writing the merged clouds.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from edgerecon.cli._common import add_json_flag, console, emit_json, print_table
from edgerecon.cli._config import (
    DeadlineShare,
    load_config,
    online_configs,
    run_options_table,
    write_effective,
)
from edgerecon.cli.run import (
    EXIT_OK,
    EXIT_TASKS_FAILED,
    add_online_arguments,
    build_options,
    live_printer,
    num_tasks,
    parse_fixed,
    print_summary,
)
from edgerecon.cli.view import live_viewer
from edgerecon.configfile import section
from edgerecon.io.dataset import open_dataset
from edgerecon.pipeline import reconstruct, reconstruct_task, warm_up
from edgerecon.quality import evaluate_clouds
from edgerecon.report import write_report
from edgerecon.runtime import RuntimeConfig
from edgerecon.runtime.online import run_online
from edgerecon.runtime.state import OriginalTiming
from edgerecon.scene.stream import dataset_scene_at
from edgerecon.synth import GroundTruth, preset_config, write_dataset
from edgerecon.types import PointCloud


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="generate a synthetic scene and run the online system on it (no data needed)",
        description=__doc__.split("\n\n")[1] if __doc__ else None,
    )
    p.add_argument("--out", "-o", default="work/demo", help="work folder (default work/demo)")
    p.add_argument("--preset", default="demo", help="scene preset (default demo)")
    p.add_argument("--seed", type=int, default=0, help="scene seed")
    p.add_argument("--num-frames", type=int, default=None, help="timestamps to generate")
    p.add_argument(
        "--size",
        default=None,
        metavar="WxH",
        help="image size of the generated scene (keeps the field of view)",
    )
    p.add_argument(
        "--deadline-fraction",
        type=float,
        default=0.4,
        help="deadline as a share of the measured golden time when --deadline is "
        "not given (default 0.4)",
    )
    add_online_arguments(p)
    add_json_flag(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    scene_dir = out / "scene"
    t0 = time.perf_counter()
    overrides = {"seed": args.seed}
    if args.num_frames is not None:
        overrides["num_frames"] = args.num_frames
    if args.size:
        try:
            w, h = (int(v) for v in args.size.lower().split("x"))
        except ValueError:
            raise ValueError(f"--size must look like 640x480, got {args.size!r}") from None
        overrides.update(width=w, height=h)
    config = preset_config(args.preset, **overrides)
    if _scene_matches(scene_dir, config.to_dict()):
        generated = False
    else:
        if not args.json:
            console.print(f"generating the {args.preset!r} scene in {scene_dir} ...")
        write_dataset(config, scene_dir, overwrite=True)
        generated = True
    gen_s = time.perf_counter() - t0
    dataset = open_dataset(scene_dir)
    gt = GroundTruth.open(scene_dir)

    # The original pipeline: golden configuration, whole scene, on the middle timestamp.
    t_mid = dataset.num_frames // 2
    with dataset.open_frames() as source:
        frames = source.read(t_mid)
    warm_up()  # the kernels load (or compile, on a first run) before anything is timed
    golden = reconstruct(frames, dataset.rig)
    threshold = RuntimeConfig(deadline_s=1.0).eval_threshold_for(dataset.rig)
    ref_all = gt.reference_cloud(t_mid, "all", min_views=2)
    golden_score = evaluate_clouds(
        golden.dense.cloud if golden.dense else golden.sparse.cloud, ref_all, threshold
    )[0]
    cfg = load_config(args)
    if args.deadline is None and not {"deadline_s", "deadline_share"} & set(
        section(cfg, "runtime")
    ):
        args.deadline = DeadlineShare(args.deadline_fraction)
    rt, controller_config = online_configs(args, cfg)
    original = OriginalTiming.of(t_mid, golden.timings)
    # Like for like with the online tasks: the golden configuration's foreground at t_mid
    # as the online system runs it (r = 1, every camera, the masks it has at that time, its
    # sparse scope: with the visual hull's depth ranges, no SfM on the critical path).
    tracker = dataset_scene_at(dataset, t_mid, rt.foreground)
    fg = tracker.segment(frames)
    fg_config, split_config = rt.task_configs(1.0, dataset.rig)
    golden_fg = reconstruct_task(
        frames,
        dataset.rig,
        fg,
        fg_config,
        background=PointCloud.empty(),
        split_config=split_config,
        sparse_scope=rt.sparse_scope,
    )
    ref_fg = gt.reference_cloud(t_mid, "foreground", min_views=2)
    golden_fg_score = evaluate_clouds(golden_fg.foreground.cloud, ref_fg, threshold)[0]
    golden_fg_s = fg.timings.total + golden_fg.timings.total
    rt = rt.with_original(original.seconds)
    deadline = rt.deadline_s
    if not args.json:
        console.print(
            f"original pipeline (r=1, all {len(dataset.rig)} cameras, whole scene) at t={t_mid}: "
            f"{golden.timings.total:.2f} s, F({threshold * 100:.1f} cm) of the whole scene vs "
            "ground truth = "
            f"{golden_score.fscore:.3f}; online deadline {deadline:.2f} s"
        )
    if args.frames is None:
        args.frames = f"0:{dataset.num_frames}"
    # The run folder is the demo's own work folder: a new demo replaces the last one.
    options = build_options(args, dataset, threshold, overwrite=True)
    fixed = parse_fixed(args, dataset)
    with (
        live_viewer(args, out / "run"),
        live_printer(not args.json, num_tasks(args, dataset)) as on_task,
    ):
        summary, metrics = run_online(
            dataset,
            rt,
            options,
            out / "run",
            engine=args.engine,
            address=args.address,
            fixed=fixed,
            controller_config=controller_config,
            on_task=on_task,
            original=original,
        )
    effective = {"runtime": rt, "controller": controller_config, "run": run_options_table(args)}
    write_effective(out / "run", "demo", effective)
    figures = write_report([out / "run"], out / "run" / "report")
    result = {
        "scene": str(scene_dir),
        "generated": generated,
        "generation_s": round(gen_s, 2),
        "threshold": threshold,
        "golden": {
            "time_index": t_mid,
            "seconds": round(golden.timings.total, 3),
            "fscore": golden_score.fscore,
            "stages": golden.timings.to_dict(),
        },
        "golden_foreground": {
            "time_index": t_mid,
            "seconds": round(golden_fg_s, 3),
            "fscore": golden_fg_score.fscore,
            "points": len(golden_fg.foreground.cloud),
        },
        "deadline_s": deadline,
        "summary": summary.to_dict(),
        "tasks": [m.to_dict() for m in metrics],
        "figures": {k: str(v) for k, v in figures.items()},
        "total_s": round(time.perf_counter() - t0, 2),
    }
    (out / "demo.json").write_text(json.dumps(result, indent=2) + "\n")
    code = EXIT_TASKS_FAILED if summary.failed else EXIT_OK
    if args.json:
        emit_json(result)
        return code
    print_summary(f"demo: {dataset.name}, deadline {deadline:.2f} s", summary)
    at_mid = next((m for m in metrics if m.time_index == t_mid and m.status == "ok"), None)
    rows: list[tuple[object, ...]] = [
        (
            "original (golden, whole scene)",
            golden.timings.total,
            golden_score.fscore,
            f"whole scene (t={t_mid})",
        ),
        (
            "golden foreground (r=1, all cameras)",
            golden_fg_s,
            golden_fg_score.fscore,
            f"foreground (t={t_mid})",
        ),
    ]
    if at_mid is not None:
        rows.append(
            (
                f"optimized (online, the task of t={t_mid})",
                at_mid.critical_path_s,
                "-" if at_mid.offline_fscore is None else at_mid.offline_fscore,
                f"foreground (t={t_mid})",
            )
        )
    rows.append(
        (
            "optimized (online, average)",
            summary.avg_time_s,
            "-" if summary.avg_offline_fscore is None else summary.avg_offline_fscore,
            "foreground (each task)",
        )
    )
    columns = ["pipeline", "seconds", "F vs ground truth", "of"]
    print_table("original vs optimized pipeline (per task)", columns, rows)
    console.print(
        f"task clouds in {out / 'run' / 'tasks'} (one task's merged cloud: edgerecon export "
        f"{out / 'run' / 'tasks' / '<time>'} --to ply -o FILE.ply); metrics in "
        f"{out / 'run' / 'metrics.jsonl'}; figures in {out / 'run' / 'report'}; "
        f"total {result['total_s']:.0f} s"
    )
    return code


def _scene_matches(scene_dir: Path, config: dict[str, object]) -> bool:
    """Whether ``scene_dir`` already holds a complete scene generated from ``config``."""
    meta = scene_dir / "gt" / "scene.json"
    if not (scene_dir / "dataset.json").exists() or not meta.exists():
        return False
    try:
        saved = json.loads(meta.read_text())
    except json.JSONDecodeError:
        return False
    return saved.get("config") == json.loads(json.dumps(config))
