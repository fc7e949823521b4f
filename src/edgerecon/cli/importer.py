"""``edgerecon import``: a calibration + per-camera videos or image folders -> a dataset folder."""

from __future__ import annotations

import argparse

from edgerecon.cli._common import add_json_flag, console, emit_json, print_table
from edgerecon.cli.calib import calibration_check, repair_hint
from edgerecon.io.crs import crs_name
from edgerecon.io.importer import import_dataset, parse_offsets, parse_up


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "import",
        help="make a dataset from a calibration and per-camera videos or image folders",
        description="Read a calibration (edgerecon rig JSON, COLMAP text or binary model, "
        "anipose / Pose2Sim / caliscope TOML, EasyMocap intri.yml + extri.yml, CMU Panoptic "
        "calibration_*.json, LLFF poses_bounds.npy, nerfstudio / Instant-NGP transforms.json, "
        "Kalibr camchain.yaml, Ego-Exo4D gopro_calibs.csv, multical calibration.json, "
        "openMVG sfm_data, OpenCV XML, Middlebury), find "
        "each camera's "
        "frames, check every camera (frames readable, counts, sizes) and write "
        "OUT/dataset.json + OUT/rig.json. Frames are referenced where they are, not copied. "
        "A calibration of more cameras than were filmed (a dome's) keeps the cameras whose "
        "frames are named after them. Fisheye cameras become the pinhole cameras their frames "
        "are rectified to as they are read.",
        epilog="examples:\n"
        "  edgerecon import camera_array.toml videos/ --out data/session1\n"
        "  edgerecon import Calib.toml cam1=v/c1.mp4 cam2=v/c2.mp4 cam3=v/c3.mp4 --out d\n"
        "  edgerecon import colmap/sparse/0 --images colmap/images --out data/scene\n"
        "  edgerecon import zju/ zju/videos --out d                  # EasyMocap layout\n"
        "  edgerecon import calibration_seq.json seq/hdVideos --out d  # Panoptic HD cameras\n"
        "  edgerecon import capture/transforms.json videos/ --out d     # nerfstudio\n"
        "  edgerecon import camchain-kalibr.yaml videos/ --out d        # Kalibr\n"
        "  edgerecon import take/trajectory/gopro_calibs.csv take/frame_aligned_videos --out d\n"
        "  edgerecon import calibration.toml videos/ --offset B=2 --unit mm --out d\n"
        "  edgerecon import calibration.toml videos/ --offset auto --out d  # phones started by hand",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("calibration", help="calibration file or folder (format detected)")
    p.add_argument(
        "frames",
        nargs="*",
        metavar="SOURCE",
        help="per-camera video files, image folders or {index} patterns, as NAME=PATH or "
        "matched to the cameras by name; or one folder holding them",
    )
    p.add_argument("--out", "-o", required=True, metavar="DIR", help="dataset folder to write")
    p.add_argument(
        "--images",
        metavar="DIR",
        help="COLMAP model: the image folder its image names are relative to (the frames)",
    )
    p.add_argument(
        "--background",
        nargs="+",
        default=[],
        metavar="SOURCE",
        help="clips of the empty scene, given like the frames",
    )
    p.add_argument(
        "--offset",
        action="append",
        default=[],
        metavar="CAMERA=FRAMES|auto",
        help="synchronisation: time index t is that camera's frame t + FRAMES (negative: the "
        "others are shifted); repeatable or comma-separated; auto: estimated from what the "
        "cameras see move (cameras started at different moments)",
    )
    p.add_argument(
        "--unit", help="length unit of the calibration (m, mm, ...) when it does not say"
    )
    p.add_argument(
        "--up",
        default="auto",
        help="world up: auto (the calibration's, else estimated from the cameras' level "
        "horizons), keep, +z / -y / ..., or X,Y,Z (default auto)",
    )
    p.add_argument("--fps", type=float, help="frame rate (images have none; videos: override)")
    p.add_argument("--name", help="dataset name (default: the folder name)")
    p.add_argument(
        "--crs",
        metavar="CRS",
        help="the calibration's world frame is georeferenced in this coordinate reference "
        "system (EPSG:32633, WKT; projected or geocentric, in metres): recorded in rig.json "
        "and written into LAS exports, for QGIS / PDAL",
    )
    p.add_argument("--force", action="store_true", help="replace an existing dataset.json")
    p.add_argument(
        "--no-calib-check",
        action="store_true",
        help="do not check the calibration against the frames afterwards (`edgerecon calib`: "
        "a camera that moved, videos given to the wrong cameras)",
    )
    add_json_flag(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    report = import_dataset(
        args.out,
        calibration=args.calibration,
        frames=args.frames,
        images=args.images,
        background=args.background,
        offsets=parse_offsets(args.offset),
        unit=args.unit,
        up=parse_up(args.up),
        fps=args.fps,
        name=args.name,
        crs=args.crs,
        overwrite=args.force,
    )
    calib = None if args.no_calib_check else calibration_check(report.dataset)
    hint = repair_hint(calib, report.dataset.rig)
    if args.json:
        cal = None if calib is None else {**calib.to_dict(), "repair": hint}
        emit_json({**report.to_dict(), "calibration": cal})
        return 0
    ds = report.dataset
    rig = ds.rig
    console.print(
        f"[bold]{ds.name}[/]: {len(rig)} cameras from {report.calibration} "
        f"({report.calibration_format}), {ds.num_frames} frames ({ds.frames.kind})"
        + ("" if ds.fps is None else f" at {ds.fps:g} fps"),
        soft_wrap=True,
    )
    console.print(f"unit: {report.unit_note}", soft_wrap=True)
    console.print(f"up: {report.up_note}", soft_wrap=True)
    if rig.crs:
        console.print(f"coordinate reference system: {crs_name(rig.crs)} ({rig.crs})")
    console.print(f"scene scale (median camera distance apart): {rig.scene_scale():.4g} {rig.unit}")
    print_table(
        "cameras (id = index for --cameras)",
        ["id", "name", "frames", "size", "fps", "offset", "matched", "source"],
        [
            [
                i,
                c.name,
                c.num_frames,
                f"{c.size[0]}x{c.size[1]}",
                "-" if c.fps is None else f"{c.fps:g}",
                c.offset,
                c.matched_by,
                c.source,
            ]
            for i, c in enumerate(report.cameras)
        ],
    )
    for note in report.notes:
        console.print(f"[yellow]note:[/] {note}", soft_wrap=True)
    if ds.background is not None:
        console.print("background clip: yes")
    if calib is not None:
        if calib.fits is False:
            console.print(
                f"[yellow]{calib.message}[/]"
                + ("" if hint is None else f"; from these frames: {hint}")
                + f"; `edgerecon calib --dataset {ds.root}` tells more (--write re-aims a "
                "camera that turned or places again one that moved)",
                soft_wrap=True,
            )
        else:
            console.print(calib.message, soft_wrap=True)
    console.print(f"wrote {ds.root / 'dataset.json'} and {ds.root / 'rig.json'}")
    return 0
