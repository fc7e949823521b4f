"""``edgerecon reconstruct``: one timestamp of a dataset -> sparse.ply, dense.ply, timings.json."""

from __future__ import annotations

import argparse
from pathlib import Path

from edgerecon.cli._common import add_json_flag, console, emit_json, print_table, to_json
from edgerecon.config import ReconstructionConfig
from edgerecon.geometry.camera import Rig
from edgerecon.io.dataset import Dataset, open_dataset
from edgerecon.io.ply import atomic_write_text, write_ply
from edgerecon.pipeline import reconstruct, reconstruct_split, warm_up
from edgerecon.runtime.engine import learn_scene_model
from edgerecon.scene.foreground import RigForeground
from edgerecon.scene.merge import write_merged


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
        "--cameras", default=None, help="comma-separated camera ids or names (default: all cameras)"
    )


def parse_cameras(text: str | None, rig: Rig) -> tuple[int, ...] | None:
    if text is None:
        return None
    return tuple(rig.index(tok.strip()) for tok in text.split(",") if tok.strip())


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "reconstruct",
        help="reconstruct one timestamp (sparse + dense point clouds)",
        description="Structure from known poses and multi-view stereo for one timestamp; writes "
        "sparse.ply, dense.ply and timings.json to --out.",
    )
    add_task_arguments(p)
    p.add_argument("--out", "-o", required=True, help="output folder")
    p.add_argument("--no-dense", action="store_true", help="stop after the sparse stage")
    p.add_argument(
        "--split",
        action="store_true",
        help="foreground/background pipeline: learn the background model (background "
        "clip or first frames), split the sparse cloud, densify foreground and "
        "background separately; writes merged.ply, fg.ply and bg.ply too",
    )
    add_json_flag(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    dataset = open_dataset(args.dataset)
    rig = dataset.rig
    config = ReconstructionConfig(
        scale=args.scale, camera_ids=parse_cameras(args.cameras, rig), dense=not args.no_dense
    )
    if args.split:
        return _run_split(args, dataset, config)
    with dataset.open_frames() as source:
        frames = source.read(args.time)
    warm_up()  # timings.json reports the pipeline, not the kernels' loading
    result = reconstruct(frames, rig, config)
    out = Path(args.out)
    write_ply(out / "sparse.ply", result.sparse.cloud, unit=rig.unit, up=rig.up)
    if result.dense is not None:
        write_ply(out / "dense.ply", result.dense.cloud, unit=rig.unit, up=rig.up)
    summary = {
        "dataset": str(dataset.root),
        "unit": rig.unit,
        "cameras": [rig[i].name for i in result.camera_ids],
        **result.summary(),
    }
    atomic_write_text(out / "timings.json", to_json(summary) + "\n")
    if args.json:
        emit_json(summary)
        return 0
    print_table(
        f"{dataset.name} t={args.time} r={config.scale:g} cameras={summary['cameras']}",
        ["stage", "seconds"],
        [*result.timings.seconds.items(), ("total", result.timings.total)],
    )
    dense_n = "-" if result.dense is None else f"{result.dense.num_points:,}"
    console.print(
        f"sparse points: {result.sparse.num_points:,}   dense points: {dense_n}   -> {out}"
    )
    return 0


__all__ = ["add_task_arguments", "parse_cameras", "register", "run"]


def _run_split(args: argparse.Namespace, dataset: Dataset, config: ReconstructionConfig) -> int:
    rig = dataset.rig
    scene = learn_scene_model(dataset)
    model = RigForeground.from_states(rig, scene.states)
    with dataset.open_frames() as source:
        # Let the model see a few frames before T (it adapts, as it would online).
        for t in range(max(0, args.time - 5), args.time):
            model.segment(source.read(t))
        frames = source.read(args.time)
    foreground = model.segment(frames)
    result = reconstruct_split(frames, rig, foreground, config)
    out = Path(args.out)
    write_merged(out, result.merged, unit=rig.unit, up=rig.up)
    write_ply(out / "sparse.ply", result.sparse.cloud, unit=rig.unit, up=rig.up)
    summary = {
        "dataset": str(dataset.root),
        "unit": rig.unit,
        "cameras": [rig[i].name for i in result.camera_ids],
        "background_model": scene.learned_from,
        "foreground_area": foreground.areas(),
        **result.summary(),
    }
    atomic_write_text(out / "timings.json", to_json(summary) + "\n")
    if args.json:
        emit_json(summary)
        return 0
    print_table(
        f"{dataset.name} t={args.time} r={config.scale:g} foreground/background split",
        ["stage", "seconds"],
        [*result.timings.seconds.items(), ("total", result.timings.total)],
    )
    console.print(
        f"sparse: {result.sparse.num_points:,} ({summary['num_sparse_foreground']:,} foreground)"
        f"   foreground: {len(result.foreground.cloud):,}   background: "
        f"{len(result.background):,}   merged: {len(result.merged):,}   -> {out}"
    )
    return 0
