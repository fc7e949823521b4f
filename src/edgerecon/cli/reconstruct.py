"""``edgerecon reconstruct``: one timestamp of a dataset -> sparse.ply, dense.ply (or, with
``--split``, merged.ply + fg.ply + bg.ply), timings.json and config.toml.

Every phase of the command is timed (start-up, opening the dataset, learning the background,
decoding up to T, masks, loading the compiled kernels, the stages, writing) and printed with
the wall time, so that the time a user waits is accounted for.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path
from typing import Any

from edgerecon import progress
from edgerecon.cli._common import add_json_flag, console, emit_json, print_table, to_json
from edgerecon.cli._config import add_config_flag, given, load_config, write_effective
from edgerecon.config import MIN_CAMERAS, ReconstructionConfig
from edgerecon.configfile import build, section
from edgerecon.geometry.camera import Rig
from edgerecon.io.dataset import Dataset, open_dataset
from edgerecon.io.ply import atomic_write_text, ply_frame, write_ply
from edgerecon.types import DataError


def add_task_arguments(p: argparse.ArgumentParser) -> None:
    """Options shared by the subcommands that reconstruct a timestamp."""
    p.add_argument(
        "--dataset", required=True, help="dataset folder (dataset.json or a known layout)"
    )
    p.add_argument("--time", "-t", type=int, default=0, help="frame index of the task (default 0)")
    p.add_argument(
        "--scale",
        "-r",
        type=float,
        default=1.0,
        help="image scale r in (0, 1] (default 1: the golden configuration)",
    )
    p.add_argument(
        "--cameras",
        default=None,
        help="comma-separated camera ids (0-based, the order of `edgerecon info`) or names "
        f"(default: all cameras; at least {MIN_CAMERAS})",
    )


def parse_cameras(text: str | None, rig: Rig, option: str = "--cameras") -> tuple[int, ...] | None:
    """Camera ids from ``0,2,3`` or names; errors name the option, the rig's ids and names."""
    if text is None:
        return None
    hint = f"this rig has ids 0-{len(rig) - 1} = {', '.join(rig.names)}"
    ids = []
    for tok in (t.strip() for t in text.split(",")):
        if not tok:
            continue
        try:
            ids.append(rig.index(tok))
        except ValueError:
            raise DataError(f"{option}: unknown camera {tok!r} ({hint})") from None
    dup = sorted({rig[i].name for i in ids if ids.count(i) > 1})
    if dup:
        raise DataError(
            f"{option} must name at least {MIN_CAMERAS} distinct cameras: "
            f"{', '.join(dup)} given twice ({text}); {hint}"
        )
    if len(ids) < MIN_CAMERAS:
        raise DataError(
            f"{option} must name at least {MIN_CAMERAS} distinct cameras, got {len(ids)} "
            f"({text}); {hint}"
        )
    return tuple(ids)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "reconstruct",
        help="reconstruct one timestamp (sparse + dense point clouds)",
        description="Structure from known poses and multi-view stereo for one timestamp; writes "
        "sparse.ply, dense.ply, timings.json and config.toml (the effective settings) to --out.",
    )
    add_task_arguments(p)
    p.add_argument("--out", "-o", required=True, help="output folder")
    p.add_argument("--no-dense", action="store_true", help="stop after the sparse stage")
    p.add_argument(
        "--split",
        action="store_true",
        help="foreground/background pipeline: learn the background model (background "
        "clip or first frames), split the sparse cloud, densify foreground and "
        "background separately; writes sparse.ply, merged.ply (the dense cloud, labelled), "
        "fg.ply and bg.ply instead of dense.ply",
    )
    add_config_flag(p)
    add_json_flag(p)
    p.set_defaults(func=run)


def task_config(args: argparse.Namespace, rig: Rig, cfg: dict[str, Any]) -> ReconstructionConfig:
    """[reconstruction] of --config with the options typed on the command line on top."""
    config = build(ReconstructionConfig, section(cfg, "reconstruction"), where="reconstruction")
    changes: dict[str, Any] = {}
    if given(args, "scale") or "scale" not in section(cfg, "reconstruction"):
        changes["scale"] = args.scale
    if args.cameras is not None:
        changes["camera_ids"] = parse_cameras(args.cameras, rig)
    elif config.camera_ids is not None:
        parse_cameras(",".join(map(str, config.camera_ids)), rig, "[reconstruction] camera_ids")
    if getattr(args, "no_dense", False):
        changes["dense"] = False
    return dataclasses.replace(config, **changes)


def process_age_s() -> float:
    """Seconds since this process started (Linux; 0 elsewhere): interpreter start-up and
    imports happen before any timer of ours."""
    try:
        import os

        ticks = os.sysconf("SC_CLK_TCK")
        with open("/proc/self/stat") as f:
            start = int(f.read().rsplit(")", 1)[1].split()[19]) / ticks
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        return max(0.0, uptime - start)
    except (OSError, ValueError, IndexError):
        return 0.0


def run(args: argparse.Namespace) -> int:
    startup = process_age_s()
    t0 = time.perf_counter()
    cfg = load_config(args)
    with progress.collect() as phases:
        with progress.phase("open the dataset"):
            dataset = open_dataset(args.dataset)
        rig = dataset.rig
        config = task_config(args, rig, cfg)
        if not 0 <= args.time < dataset.num_frames:
            raise DataError(
                f"--time {args.time} is out of range: {dataset.name} has frames "
                f"0..{dataset.num_frames - 1}"
            )
        if args.split:
            summary, rows = _run_split(args, dataset, config, cfg)
        else:
            summary, rows = _run_whole(args, dataset, config)
    wall = startup + time.perf_counter() - t0
    phase_rows = [("start-up (interpreter, imports)", startup), *phases.to_dict().items()]
    accounted = sum(s for _, s in phase_rows)
    summary["phases"] = dict(phase_rows)
    summary["wall_s"] = round(wall, 3)
    out = Path(args.out)
    atomic_write_text(out / "timings.json", to_json(summary) + "\n")
    if args.json:
        emit_json(summary)
        return 0
    title, stage_rows, line = rows
    print_table(title, ["stage", "seconds"], stage_rows)
    print_table(
        "where the time went (the stages above are inside 'reconstruct')",
        ["stage", "seconds"],
        [*phase_rows, ("sum of the phases", accounted), ("wall time", wall)],
    )
    console.print(line, soft_wrap=True)
    return 0


def _run_whole(
    args: argparse.Namespace, dataset: Dataset, config: ReconstructionConfig
) -> tuple[dict[str, Any], Any]:
    from edgerecon.pipeline import reconstruct, warm_up

    rig = dataset.rig
    with progress.phase(f"decode the frames of time {args.time}"), dataset.open_frames() as src:
        frames = src.read(args.time)
    warm_up()  # timings.json reports the pipeline, not the kernels' loading (a phase)
    with progress.phase("reconstruct"):
        result = reconstruct(frames, rig, config)
    out = Path(args.out)
    with progress.phase("write the outputs"):
        write_ply(
            out / "sparse.ply",
            result.sparse.cloud,
            **ply_frame(rig),
        )
        if result.dense is not None:
            write_ply(
                out / "dense.ply",
                result.dense.cloud,
                **ply_frame(rig),
            )
        write_effective(out, "reconstruct", {"reconstruction": config})
    summary = {
        "dataset": str(dataset.root),
        "unit": rig.unit,
        "cameras": [rig[i].name for i in result.camera_ids],
        **result.summary(),
    }
    dense_n = "-"
    if result.dense is not None:
        dense_n = f"{result.dense.num_points:,} ({result.dense.cloud.num_inferred:,} inferred)"
    return summary, (
        f"{dataset.name} t={args.time} r={config.scale:g} cameras={summary['cameras']}",
        [*result.timings.seconds.items(), ("total", result.timings.total)],
        f"sparse points: {result.sparse.num_points:,}   dense points: {dense_n}   -> {out}",
    )


__all__ = ["add_task_arguments", "parse_cameras", "register", "run"]


def _run_split(
    args: argparse.Namespace,
    dataset: Dataset,
    config: ReconstructionConfig,
    cfg: dict[str, Any],
) -> tuple[dict[str, Any], Any]:
    from edgerecon.pipeline import SplitPipelineConfig, reconstruct_task, warm_up
    from edgerecon.scene.foreground import ForegroundConfig
    from edgerecon.scene.merge import write_merged
    from edgerecon.scene.stream import dataset_scene_at

    rig = dataset.rig
    rt = section(cfg, "runtime")
    fg_config = build(ForegroundConfig, section(rt, "foreground"), where="runtime.foreground")
    split_config = build(SplitPipelineConfig, section(rt, "split"), where="runtime.split")
    with progress.phase(f"learn the background model up to time {args.time}"):
        # The background models as the online system has them at T (edgerecon.scene.stream).
        tracker = dataset_scene_at(dataset, args.time, fg_config, progress=not args.json)
    with progress.phase(f"decode the frames of time {args.time}"), dataset.open_frames() as src:
        frames = src.read(args.time)
    with progress.phase("foreground masks"):
        foreground = tracker.segment(frames)
    warm_up()
    with progress.phase("reconstruct"):
        # Whole-frame SfM: the background is densified here from the points labelled
        # background.
        result = reconstruct_task(
            frames, rig, foreground, config, split_config=split_config, sparse_scope="scene"
        )
    out = Path(args.out)
    with progress.phase("write the outputs"):
        write_merged(out, result.merged, **ply_frame(rig))
        write_ply(
            out / "sparse.ply",
            result.sparse.cloud,
            **ply_frame(rig),
        )
        write_effective(
            out,
            "reconstruct --split",
            {"reconstruction": config, "runtime": {"foreground": fg_config, "split": split_config}},
        )
    summary = {
        "dataset": str(dataset.root),
        "unit": rig.unit,
        "cameras": [rig[i].name for i in result.camera_ids],
        "background_model": tracker.learned_from,
        "background_updates": tracker.updates,
        "static_scene_from": tracker.static_from,
        "foreground_area": foreground.areas(),
        **result.summary(),
    }
    return summary, (
        f"{dataset.name} t={args.time} r={config.scale:g} foreground/background split "
        f"(background model: {tracker.learned_from})",
        [*result.timings.seconds.items(), ("total", result.timings.total)],
        f"sparse: {result.sparse.num_points:,} ({summary['num_sparse_foreground']:,} foreground)"
        f"   foreground: {len(result.foreground.cloud):,}   background: "
        f"{len(result.background):,}   merged: {len(result.merged):,} "
        f"({result.merged.num_inferred:,} inferred)   -> {out}",
    )
