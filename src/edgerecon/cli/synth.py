"""``edgerecon synth``: generate a synthetic multi-camera dataset with exact ground truth."""

from __future__ import annotations

import argparse
import logging
import time

from edgerecon.cli._common import add_json_flag, console, emit_json, print_table
from edgerecon.synth import PRESETS, preset_config, write_dataset
from edgerecon.types import EdgereconError


class SynthOptionError(EdgereconError, ValueError):
    """An invalid scene option on the command line."""


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, got {text!r}") from None
    return w, h


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "synth",
        help="render a synthetic scene (room + walking actors) with exact ground truth",
        description="Render a synthetic multi-camera sequence into a dataset folder "
        "(dataset.json, rig.json, frames, background clip) with ground-truth depth maps, "
        "object masks and point clouds under gt/. Deterministic from --seed.",
    )
    p.add_argument("--preset", choices=sorted(PRESETS), default="demo", help="scene preset")
    p.add_argument("--out", required=True, help="output dataset folder")
    p.add_argument("--num-frames", type=int, help="number of timestamps T")
    # Before 0.2: --frames, a count here but A:B:STEP in `run`; still accepted, with a warning.
    p.add_argument("--frames", dest="frames_count", type=int, help=argparse.SUPPRESS)
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--cameras", type=int, help="number of cameras N")
    p.add_argument("--actors", type=int, help="number of actors K")
    p.add_argument("--size", type=_size, help="image size WIDTHxHEIGHT (keeps the field of view)")
    p.add_argument("--background-frames", type=int, help="frames of the empty-scene clip")
    p.add_argument("--noise", type=float, help="sensor noise sigma, grey levels")
    p.add_argument(
        "--illumination-change",
        type=float,
        help="global light dims by this fraction over the sequence (e.g. 0.2)",
    )
    dist = p.add_mutually_exclusive_group()
    dist.add_argument(
        "--distortion", action="store_true", help="render through a studio lens's distortion"
    )
    dist.add_argument("--no-distortion", action="store_true", help="ideal pinhole cameras")
    p.add_argument("--video", action="store_true", help="one lossless video per camera (FFV1)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing synthetic dataset")
    p.add_argument("--threads", type=int, default=2, help="render threads (default 2)")
    add_json_flag(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from edgerecon.synth.scene import STUDIO_DISTORTION

    overrides: dict[str, object] = {"seed": args.seed}
    if args.frames_count is not None:
        logging.getLogger(__name__).warning(
            "synth --frames is deprecated (in `run` --frames is A:B:STEP): use --num-frames"
        )
        args.num_frames = args.num_frames if args.num_frames is not None else args.frames_count
    for opt, key in (
        ("num_frames", "num_frames"),
        ("cameras", "num_cameras"),
        ("actors", "num_actors"),
        ("background_frames", "background_frames"),
        ("noise", "noise_sigma"),
        ("illumination_change", "illumination_change"),
    ):
        if getattr(args, opt) is not None:
            overrides[key] = getattr(args, opt)
    if args.size is not None:
        overrides["width"], overrides["height"] = args.size
    if args.distortion:
        overrides["distortion"] = STUDIO_DISTORTION
    if args.no_distortion:
        overrides["distortion"] = (0.0, 0.0, 0.0, 0.0, 0.0)
    try:
        config = preset_config(args.preset, **overrides)
    except ValueError as exc:
        raise SynthOptionError(str(exc)) from None
    start = time.perf_counter()
    summary = write_dataset(
        config, args.out, video=args.video, overwrite=args.overwrite, threads=args.threads
    )
    seconds = time.perf_counter() - start
    if args.json:
        emit_json({**summary.to_dict(), "total_seconds": round(seconds, 3)})
        return 0
    w, h = summary.image_size
    fg = summary.num_foreground_points
    print_table(
        f"synthetic dataset {summary.name} -> {summary.path}",
        ["cameras", "size", "frames", "bg frames", "bg GT points", "fg GT points/frame", "seconds"],
        [
            [
                summary.num_cameras,
                f"{w}x{h}",
                summary.num_frames,
                summary.background_frames,
                summary.num_background_points,
                round(sum(fg) / max(len(fg), 1)),
                seconds,
            ]
        ],
    )
    print_table("time per stage", ["stage", "seconds"], summary.timings.seconds.items())
    rows = [
        [kind, item.get("actor", "-"), f"{item['start']}..{item['stop'] - 1}"]
        + ([item["min_level"]] if "min_level" in item else ["-"])
        for kind, items in summary.stretches.items()
        for item in items
    ]
    if rows:
        print_table("stretches (frames)", ["kind", "actor", "frames", "min light"], rows)
    console.print(
        f"read it with: GroundTruth.open({str(summary.path)!r}) or "
        f"edgerecon evaluate PRED.ply --gt {summary.path} --time T"
    )
    return 0
