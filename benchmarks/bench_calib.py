"""The calibration check and its repair on rigs made wrong on purpose: one camera's entry
turned about its own axes or moved along them, then ``check_calibration`` on ``edgerecon
calib``'s default frame sets and ``repair``. Per case: what the check said, what the repair
did, and how far the camera it changed ends from its true (given) pose; on a dataset with
board corners (``checks/charuco_corners_2d.csv``, caliscope_charuco) also the corners'
median reprojection in the camera, knocked and repaired.

    python benchmarks/bench_calib.py                                  # caliscope_charuco, cam_2
    python benchmarks/bench_calib.py /tmp/hd4 --camera 1 --cases turn:2,0,0 move:1,0,0
    python benchmarks/bench_calib.py D1 D2 --json calib.json

A case is ``turn:TX,TY,TZ`` (degrees about the camera's x = tilt, y = pan, z = roll) or
``move:DX,DY,DZ`` (rig units along the camera's x right, y down, z forward), optionally
followed by ``/TX,TY,TZ`` (turned too). Moves are in the rig's unit: choose them for the rig
(caliscope_charuco's cameras are 0.4-1.4 m apart, the synthetic presets' 4-7 m).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from _report import SHARED, print_rows, report_header, write_report
from edgerecon.cli.calib import check_dataset
from edgerecon.geometry.camera import Rig, rotation_angle_deg
from edgerecon.io.dataset import open_dataset
from edgerecon.quality.board import read_corner_csv, triangulate_corners
from edgerecon.quality.calibration import knocked, recheck, repair

DEFAULT_CASES = [
    "turn:2,0,0",
    "turn:0,2,0",
    "move:0.05,0,0",
    "move:0.1,0,0.1",
    "move:0.05,0.05,0.05/1,1,0",
]


def parse_case(text: str) -> tuple[np.ndarray, np.ndarray]:
    """(shift along the camera's axes, turn in degrees about them) of a case."""
    kind, _, rest = text.partition(":")
    first, _, second = rest.partition("/")
    try:
        a = np.array([float(v) for v in first.split(",")])
        b = np.array([float(v) for v in second.split(",")]) if second else np.zeros(3)
    except ValueError:
        raise SystemExit(f"bad case {text!r}: turn:TX,TY,TZ or move:DX,DY,DZ[/TX,TY,TZ]") from None
    if kind not in ("turn", "move") or a.shape != (3,) or b.shape != (3,):
        raise SystemExit(f"bad case {text!r}: turn:TX,TY,TZ or move:DX,DY,DZ[/TX,TY,TZ]")
    return (np.zeros(3), a) if kind == "turn" else (a, b)


def board_px(root: Path, rig: Rig, camera: int) -> float | None:
    """Median reprojection (px) of the board corners, triangulated with ``rig``, in
    ``camera``; None without a corner file."""
    path = root / "checks" / "charuco_corners_2d.csv"
    if not path.exists():
        return None
    det = read_corner_csv(path, rig)
    errors = []
    for t in np.unique(det.time_index):
        corners = triangulate_corners(det, rig, int(t), min_views=3)
        at = (det.time_index == t) & (det.camera == camera)
        for cid, X in zip(corners.corner_id, corners.points3D, strict=True):
            for uv in det.points2D[at & (det.corner_id == cid)]:
                p, _ = rig[camera].project(X[None])
                errors.append(float(np.linalg.norm(p[0] - uv)))
    return float(np.median(errors)) if errors else None


def run_dataset(path: Path, camera: int, cases: list[str]) -> list[dict[str, Any]]:
    ds = open_dataset(path)
    rig = ds.rig
    first = check_dataset(ds)  # as `edgerecon calib`: 3 frame sets, 7 for a camera unchecked
    check_s = first.seconds
    names = rig.names
    calibrated_px = board_px(path, rig, camera)
    rows = []
    for text in cases:
        shift, degrees = parse_case(text)
        wrong = knocked(rig, camera, shift, degrees)
        t0 = time.perf_counter()
        check = recheck(first, wrong)
        fix = repair(check, wrong)
        seconds = time.perf_counter() - t0 + check_s
        if fix.applied:
            action = ", ".join(
                f"{names[e.camera]} placed ({e.moved:.3g} moved)"
                if e.moved
                else f"{names[e.camera]} turned {e.rotation_deg:.2f} deg"
                for e in fix.applied
            )
        elif fix.ambiguous:
            action = "which not told: " + " or ".join(names[c] for c in fix.ambiguous)
        else:
            action = "nothing"
        changed = fix.applied[-1].camera if fix.applied else camera
        row: dict[str, Any] = {
            "dataset": path.name,
            "camera": names[camera],
            "case": text,
            "frame_sets": first.frame_sets,
            "check": check.short,
            "repair": action,
            "after": "fits" if fix.check.fits else "does not fit",
            "centre_err": float(np.linalg.norm(fix.rig[changed].center - rig[changed].center)),
            "angle_err_deg": rotation_angle_deg(fix.rig[changed].R, rig[changed].R),
            "seconds": seconds,
        }
        if calibrated_px is not None:
            row["board_px_calibrated"] = calibrated_px
            row["board_px_knocked"] = board_px(path, wrong, camera)
            row["board_px_repaired"] = board_px(path, fix.rig, camera)
        rows.append(row)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("datasets", nargs="*", type=Path, default=[SHARED / "caliscope_charuco"])
    parser.add_argument("--camera", type=int, default=2, help="the camera knocked (index)")
    parser.add_argument("--cases", nargs="+", default=DEFAULT_CASES, metavar="CASE")
    parser.add_argument("--json", type=Path, default=None, help="write a JSON report")
    args = parser.parse_args()
    for case in args.cases:
        parse_case(case)
    head = report_header()
    print(f"commit {head['commit']} load {os.getloadavg()}")
    rows = []
    for path in args.datasets:
        rows += run_dataset(path, args.camera, args.cases)
    columns = ["dataset", "camera", "case", "frame_sets", "check", "repair", "after", "centre_err"]
    columns += ["angle_err_deg", "seconds"]
    if any("board_px_calibrated" in r for r in rows):
        columns += ["board_px_calibrated", "board_px_knocked", "board_px_repaired"]
    print_rows("a camera knocked, checked and repaired", columns, rows)
    if args.json:
        write_report(args.json, {**head, "rows": rows})


if __name__ == "__main__":
    main()
