"""``edgerecon info``: what a dataset holds (rig, baselines, frames); ``--check`` decodes every
frame and reports the unusable ones."""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np
from numpy.typing import NDArray

from edgerecon.cli._common import add_json_flag, console, emit_json, print_table
from edgerecon.cli.calib import calibration_check, repair_hint
from edgerecon.config import MIN_CAMERAS
from edgerecon.geometry.camera import Rig
from edgerecon.io.crs import crs_name
from edgerecon.io.dataset import Dataset, open_dataset
from edgerecon.progress import track
from edgerecon.quality.frames import (
    FrameCheckConfig,
    FrozenCameras,
    MovedCameras,
    frame_defects,
    without_defective,
)
from edgerecon.scene.people import is_measured_model, person_model_path
from edgerecon.scene.stream import DEFAULT_FPS


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "info",
        help="describe a dataset: cameras, baselines, frames",
        description="Print a dataset's rig (size, focal, principal point, centre, distortion "
        "per camera), the baseline angle between every pair of cameras, the frame count and "
        "rate, the unit, and whether a background clip and ground truth exist.",
    )
    p.add_argument("--dataset", required=True, metavar="DIR", help="dataset folder")
    p.add_argument(
        "--check",
        action="store_true",
        help="decode every frame of every camera and report the unusable ones (missing, "
        "zero-byte, truncated, does not decode, wrong size, black, saturated, textureless); "
        "exit code 3 when there are any; also the stretches where a camera sent the same "
        "frame while the others' changed (frozen), the moments a camera's whole view moved "
        "(knocked), and whether the calibration fits the frames "
        "(edgerecon calib; exit code 3 when it does not)",
    )
    add_json_flag(p)
    p.set_defaults(func=run)


def convergence_point(rig: Rig) -> NDArray[np.float64] | None:
    """(3,) point closest (least squares) to all optical axes, or None when the axes are
    (nearly) parallel and no such point is well defined."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for cam in rig:
        d = cam.R[2]
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ cam.center
    if np.linalg.cond(A) > 1e6:
        return None
    return np.asarray(np.linalg.solve(A, b), dtype=np.float64)


def baseline_angles_deg(rig: Rig) -> NDArray[np.float64]:
    """(N, N) angle in degrees between cameras i and j as seen from the point their optical
    axes converge on (the triangulation angle of the scene centre); where there is no such
    point (parallel axes), the angle between the optical axes."""
    target = convergence_point(rig)
    if target is None:
        dirs = np.array([cam.R[2] for cam in rig])
    else:
        dirs = target - rig.centers
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    cos = np.clip(dirs @ dirs.T, -1.0, 1.0)
    return np.asarray(np.degrees(np.arccos(cos)), dtype=np.float64)


def _person_model(has_clip: bool) -> str:
    """Whether the scene stage will use the person model (``scene.people``, the default
    ``person_model = "auto"``) on this dataset."""
    if has_clip:
        return "not used: the clip of the empty scene teaches the background models"
    path = person_model_path("auto")
    if path is None:
        return (
            "not fetched: people who stay still from the first frame stay background "
            "(`edgerecon models fetch`)"
        )
    if not is_measured_model(path):
        return f"left out: {path} is not the measured model (`edgerecon models fetch` again)"
    return f"used: models learned from the stream miss people who stay still ({path})"


def image_scales(ds: Dataset) -> dict[str, Any]:
    """The image scales r an online run chooses from on this rig with the default
    settings (``runtime.online.make_controller``): the smallest, the golden one, the
    finest (above 1: the foreground finer than the golden task's) and the intervals it
    skips because a larger r costs less (``pipeline.dominated_scales``)."""
    from edgerecon.optimize import BisectionController
    from edgerecon.runtime.config import RuntimeConfig
    from edgerecon.runtime.online import make_controller

    ctrl = make_controller(ds, RuntimeConfig(deadline_s=1.0))
    assert isinstance(ctrl, BisectionController)
    c = ctrl.config
    return {
        "min": c.r_min,
        "golden": c.r_max,
        "finest": c.r_max if c.r_fine is None else c.r_fine,
        "skipped": [list(x) for x in c.skip_scales],
    }


def describe(ds: Dataset) -> dict[str, Any]:
    """Everything ``info`` prints, as JSON-safe data."""
    rig = ds.rig
    background_frames = None
    if ds.background is not None:
        with ds.background.open(rig) as bg:
            background_frames = bg.num_frames
    target = convergence_point(rig)
    o = np.asarray(rig.origin)  # world coordinates below (a localised rig works near zero)
    return {
        **ds.to_dict(),
        "up": list(rig.up),
        "origin": list(rig.origin),
        "scene_scale": rig.scene_scale(),
        "duration_s": None if ds.fps is None or ds.is_live else ds.num_frames / ds.fps,
        "background_frames": background_frames,
        "person_model": _person_model(background_frames is not None),
        "cameras": [
            {
                "id": i,
                "name": cam.name,
                "width": cam.width,
                "height": cam.height,
                "fx": float(cam.K[0, 0]),
                "fy": float(cam.K[1, 1]),
                "cx": float(cam.K[0, 2]),
                "cy": float(cam.K[1, 2]),
                "center": (cam.center + o).tolist(),
                "dist": cam.dist.tolist(),
            }
            for i, cam in enumerate(rig)
        ],
        "lenses": {
            name: {"K": r.lens.K.tolist(), "D": r.lens.D.tolist(), "size": list(r.lens.size)}
            for name, r in ds.frames.rectify
        },
        "offsets": dict(ds.frames.offsets),
        "convergence_point": None if target is None else (target + o).tolist(),
        "baseline_angles_deg": np.round(baseline_angles_deg(rig), 3).tolist(),
        "image_scales": image_scales(ds),
    }


def check_frames(ds: Dataset, config: FrameCheckConfig | None = None) -> dict[str, Any]:
    """Decode every frame of every camera: per camera, the unusable frames and why (what
    ``run`` would leave out), how many timestamps keep at least 3 usable cameras, and the
    stretches where a camera's frames did not change while the others' did (``frozen``: from
    the time index of the repeated frame to that of its first new one, None when it never
    came; ``FrameCheckConfig.frozen_after_s`` or longer; ``run`` keeps such a camera), and the
    moments a camera's whole view moved (``moved``: ``MovedCameras``, a knock; the frames
    before and after it need not fit one calibration)."""
    names = ds.rig.names
    bad: dict[str, list[dict[str, Any]]] = {n: [] for n in names}
    usable_times = 0
    watch = FrozenCameras(config, fps=ds.fps or DEFAULT_FPS)
    frozen: dict[str, list[dict[str, int | None]]] = {}
    moves = MovedCameras(config)
    moved: list[dict[str, Any]] = []
    with ds.open_frames(missing="skip_camera") as source:
        counts = source.frame_counts
        for t in track(range(source.num_frames), "checking frames"):
            frames, problems = source.check(t)
            defects = frame_defects(frames, config)
            usable = without_defective(frames, defects)
            froze, thawed = watch.update(usable)
            for move in moves.update(usable):
                moved.append(
                    {
                        "camera": names[move.camera],
                        "time": move.time_index,
                        "shift_px": list(move.shift_px),
                        "roll_deg": move.roll_deg,
                    }
                )
            for i in froze:
                frozen.setdefault(names[i], []).append({"from": watch.since(i), "to": None})
            for i in thawed:
                frozen[names[i]][-1]["to"] = t
            for name, defect in zip(names, defects, strict=True):
                problem = problems.get(name) or defect
                if problem:
                    bad[name].append({"time": t, "problem": problem})
            usable_times += (
                sum(
                    d is None and name not in problems
                    for name, d in zip(names, defects, strict=True)
                )
                >= MIN_CAMERAS
            )
    longest = max(counts.values())
    for name, n in counts.items():
        if n < longest:  # a truncated video (or fewer image files): frames past its end
            bad[name].append(
                {"time": n, "problem": f"only {n} frames decode ({longest} for another camera)"}
            )
    return {
        "frames": ds.num_frames,
        "frame_counts": counts,
        "usable_timestamps": usable_times,
        "unusable": {n: v for n, v in bad.items() if v},
        "num_unusable": sum(len(v) for v in bad.values()),
        "frozen": frozen,
        "moved": moved,
    }


def run(args: argparse.Namespace) -> int:
    ds = open_dataset(args.dataset)
    info = describe(ds)
    calib = None
    if args.check:
        info["check"] = check_frames(ds)
        calib = calibration_check(ds)
        hint = repair_hint(calib, ds.rig)
        info["check"]["calibration"] = (
            None if calib is None else {**calib.to_dict(), "repair": hint}
        )
    code = (
        3
        if args.check
        and (info["check"]["num_unusable"] or (calib is not None and calib.fits is False))
        else 0
    )
    if args.json:
        emit_json(info)
        return code
    unit = ds.rig.unit
    fps = "unknown" if ds.fps is None else f"{ds.fps:g}"
    console.print(f"[bold]{ds.name}[/] ({ds.layout}) at {ds.root}")
    console.print(
        f"{len(ds.rig)} cameras, {'live' if ds.is_live else ds.num_frames} frames "
        f"({ds.frames.kind}), fps {fps}, "
        f"unit {unit}, up {tuple(ds.rig.up)}, scene scale {info['scene_scale']:.4g} {unit}"
    )
    if any(ds.rig.origin):
        console.print(
            f"far from the world's origin: computed in a frame at {tuple(ds.rig.origin)}, "
            "clouds written in world coordinates (float64)"
        )
    if ds.rig.crs:
        console.print(
            f"coordinate reference system: {crs_name(ds.rig.crs)} ({ds.rig.crs}; LAS exports "
            "carry it)",
            soft_wrap=True,
        )
    bg = info["background_frames"]
    console.print(
        "background clip: "
        + ("no" if bg is None else f"yes ({bg} frames)")
        + "; ground truth: "
        + ("no" if ds.ground_truth is None else str(ds.ground_truth))
    )
    console.print(f"person model: {info['person_model']}", soft_wrap=True)
    sc = info["image_scales"]
    skipped = ", ".join(f"{a:g}-{b:g}" for a, b in sc["skipped"]) or "none"
    console.print(
        f"image scales of an online run: r {sc['min']:g}-{sc['finest']:g} (golden {sc['golden']:g}"
        + (
            "; above it the foreground finer than the golden task's"
            if sc["finest"] > sc["golden"]
            else ""
        )
        + f"); skipped, where a larger r costs less: {skipped}",
        soft_wrap=True,
    )
    print_table(
        "cameras",
        ["id", "name", "size", "fx", "fy", "cx", "cy", f"x ({unit})", "y", "z"],
        [
            [
                c["id"],
                c["name"],
                f"{c['width']}x{c['height']}",
                c["fx"],
                c["fy"],
                c["cx"],
                c["cy"],
                *[float(v) for v in c["center"]],
            ]
            for c in info["cameras"]
        ],
    )
    if any(any(c["dist"]) for c in info["cameras"]):
        print_table(
            "distortion (OpenCV)",
            ["name", "k1", "k2", "p1", "p2", "k3"],
            [[c["name"], *[float(v) for v in c["dist"]]] for c in info["cameras"]],
        )
    else:
        console.print("distortion: none (ideal pinhole cameras)")
    if info["lenses"]:
        print_table(
            "fisheye lenses (frames rectified to the pinhole cameras above as they are read)",
            ["name", "fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4"],
            [
                [n, lens["K"][0][0], lens["K"][1][1], lens["K"][0][2], lens["K"][1][2], *lens["D"]]
                for n, lens in info["lenses"].items()
            ],
        )
    if info["offsets"]:
        console.print(
            "synchronisation offsets (frames): "
            + ", ".join(f"{n} {k}" for n, k in info["offsets"].items()),
            soft_wrap=True,
        )
    angles = np.asarray(info["baseline_angles_deg"])
    names = ds.rig.names
    print_table(
        "baseline angles (degrees, seen from the point the optical axes converge on)",
        ["camera", *names],
        [[n, *[f"{a:.1f}" for a in row]] for n, row in zip(names, angles, strict=True)],
    )
    if args.check:
        _print_check(info["check"])
        if calib is not None:
            hint = info["check"]["calibration"]["repair"]
            console.print(
                calib.message
                + ("" if hint is None else f"; from these frames: {hint}")
                + (
                    "; `edgerecon calib` tells more (--write stores it)"
                    if calib.fits is False
                    else ""
                ),
                soft_wrap=True,
            )
    return code


def _print_check(check: dict[str, Any]) -> None:
    rows = []
    for name, problems in check["unusable"].items():
        kinds: dict[str, list[int]] = {}
        for p in problems:
            kind = str(p["problem"])
            kinds.setdefault(kind if len(kind) < 20 else _kind(kind), []).append(p["time"])
        for kind, times in kinds.items():
            shown = ", ".join(str(t) for t in times[:8]) + (" ..." if len(times) > 8 else "")
            rows.append([name, kind, len(times), shown])
    if rows:
        print_table("unusable frames", ["camera", "problem", "frames", "times"], rows)
    for name, stretches in check.get("frozen", {}).items():
        shown = ", ".join(
            f"{s['from']}-{'end' if s['to'] is None else s['to'] - 1}" for s in stretches
        )
        console.print(
            f"camera {name}: the same frame while the others' changed at times {shown} "
            "(a stuck camera? run keeps it)"
        )
    for move in check.get("moved", []):
        dx, dy = move["shift_px"]
        console.print(
            f"camera {move['camera']}: its whole view moved at time {move['time']} (the image "
            f"centre {dx:+.1f}, {dy:+.1f} px, rolled {move['roll_deg']:+.2f} degrees: knocked?); "
            "the frames before and after it need not fit one calibration (`edgerecon calib "
            "--times` on each side)"
        )
    console.print(
        f"frame check: {check['num_unusable']} unusable frames; "
        f"{check['usable_timestamps']} of {check['frames']} timestamps keep >= 3 usable cameras"
    )


def _kind(problem: str) -> str:
    """A short name for a frame problem message."""
    for key, name in (
        ("missing", "missing"),
        ("cannot be decoded", "does not decode"),
        ("does not decode", "does not decode"),
        ("ends or is corrupt", "truncated video"),
        ("only", "truncated"),
        ("calibration says", "wrong size"),
    ):
        if key in problem:
            return name
    return problem[:40]
