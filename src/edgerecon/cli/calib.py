"""``edgerecon calib``: does a dataset's calibration fit its frames? Matches every pair of
cameras without the calibration and measures how far the matches lie from the calibration's
epipolar lines (``quality.calibration``); a camera that turned or moved since it was
calibrated is named, its orientation (and place) found again, and with ``--write`` stored in
a new rig file. ``--adopt`` names instead the rig a run's back-end found from its frames
(``rig.repaired.json`` in the run folder: a live dataset's only way)."""

from __future__ import annotations

import argparse
import json
import logging
from typing import TYPE_CHECKING, Any

import numpy as np

from edgerecon.cli._common import (
    add_json_flag,
    console,
    dataset_to_check,
    emit_json,
    print_table,
)
from edgerecon.geometry.camera import Rig
from edgerecon.io.calibration import load_rig, save_rig
from edgerecon.io.dataset import DESCRIPTOR, Dataset
from edgerecon.io.ply import atomic_write_text
from edgerecon.progress import track
from edgerecon.quality.calibration import (
    POOLED_FRAME_SETS,
    CalibrationCheck,
    CalibrationCheckConfig,
    PoseEstimate,
    check_calibration,
    repair,
    repair_summary,
    try_repair,
)
from edgerecon.types import DataError, EdgereconError, FrameSet

if TYPE_CHECKING:
    from edgerecon.scene.stream import FrameReader

logger = logging.getLogger(__name__)

#: The rig file ``--write`` makes next to ``dataset.json`` (the one before is kept).
RECALIBRATED = "rig.recalibrated.json"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "calib",
        help="check the calibration against what the cameras see; --write re-aims a camera "
        "that turned or places again one that moved",
        description="Match every pair of cameras without the calibration (SIFT, ratio test, "
        "a fundamental matrix estimated from the matches), then measure how far those matches "
        "lie from the epipolar lines the calibration predicts. Names a camera that moved since "
        "it was calibrated (or frames given to the wrong camera, or another setup's "
        "calibration), finds the orientation of a camera that turned (its centre kept) or the "
        "pose of one that moved a little, and "
        "with --write stores it in a new rig file that dataset.json then names. Exit code 3 "
        "when a camera does not fit (and was not written) or no pair fits. --adopt FILE "
        "names instead a rig that a run's back-end found from its own frames "
        "(OUT/rig.repaired.json; a live dataset too), once it is the dataset's calibration "
        "with some cameras placed again.",
    )
    p.add_argument("--dataset", required=True, metavar="DIR", help="dataset folder")
    p.add_argument(
        "--times",
        default=None,
        metavar="T1,T2,...",
        help="time indices whose matches are pooled (default: 3 spread over the stream, "
        f"{POOLED_FRAME_SETS} when a camera shares too few features with the others in "
        "those)",
    )
    p.add_argument(
        "--max-error",
        type=float,
        default=CalibrationCheckConfig.max_error_px,
        metavar="PX",
        help="largest median distance of a fitting pair from the epipolar lines, in pixels "
        f"of a 1000-pixel-wide frame (default {CalibrationCheckConfig.max_error_px:g})",
    )
    p.add_argument(
        "--write",
        action="store_true",
        help=f"store the re-found poses of the cameras that turned or moved in {RECALIBRATED} "
        "and name it in dataset.json (the rig file before is kept)",
    )
    p.add_argument(
        "--adopt",
        metavar="RIG",
        help="name RIG (a run's rig.repaired.json: the calibration with the cameras its "
        f"back-end placed again) in dataset.json, copied to {RECALIBRATED}; refused unless "
        "RIG is the dataset's calibration with some cameras' poses changed",
    )
    add_json_flag(p)
    p.set_defaults(func=run)


def default_times(num_frames: int, count: int = 3) -> list[int]:
    """``count`` time indices spread over a stream (its 10 %, 50 %, 90 %)."""
    if num_frames < 1:
        raise DataError("the dataset has no frames")
    at = np.linspace(0.1, 0.9, count) * (num_frames - 1)
    return sorted({int(x) for x in np.rint(at)})


def _times(text: str | None, num_frames: int) -> list[int] | None:
    if text is None:
        return None
    try:
        times = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise DataError(f"--times: comma-separated time indices, got {text!r}") from None
    bad = [t for t in times if not 0 <= t < num_frames]
    if not times or bad:
        raise DataError(f"--times: indices in 0..{num_frames - 1}, got {text!r}")
    return times


def _name_rig(ds: Dataset, rig: Rig) -> tuple[str, str]:
    """``rig`` saved as ``RECALIBRATED`` next to ``dataset.json``, which then names it:
    (the file written, the rig file named before)."""
    written = str(save_rig(ds.root / RECALIBRATED, rig.in_world()))
    descriptor = ds.root / DESCRIPTOR
    data = json.loads(descriptor.read_text())
    before = str(data["rig"])
    data["rig"] = RECALIBRATED
    atomic_write_text(descriptor, json.dumps(data, indent=2) + "\n")
    return written, before


def adopt_rig(
    ds: Dataset, rig: Rig
) -> tuple[list[tuple[str, float, float]], str | None, str | None]:
    """Name ``rig`` in ``ds`` (``RECALIBRATED``) when it is the dataset's calibration with
    some cameras placed again (``runtime.state.pose_changes``; ``DataError`` otherwise):
    (the changes, the file written, the rig file named before; None, None when ``rig`` is
    the calibration already). ``calib --adopt`` and ``run --adopt-repairs``."""
    from edgerecon.runtime.state import pose_changes

    if ds.layout != "descriptor":
        raise DataError(f"{ds.root} has no {DESCRIPTOR} to name a rig in")
    try:
        changes = pose_changes(ds.rig.in_world(), rig.in_world())
    except EdgereconError as exc:
        raise DataError(
            f"not this dataset's calibration with cameras placed again ({exc})"
        ) from None
    if not changes:
        return changes, None, None
    written, before = _name_rig(ds, rig)
    return changes, written, before


def _adopt(args: argparse.Namespace) -> int:
    """``--adopt RIG``: a run's repaired rig named in the dataset (see ``register``)."""
    from edgerecon.io.dataset import open_dataset
    from edgerecon.runtime.state import describe_changes

    if args.write or args.times is not None:
        raise DataError("--adopt names a rig found before: not with --write or --times")
    ds = open_dataset(args.dataset)
    try:
        changes, written, before = adopt_rig(ds, load_rig(args.adopt))
    except DataError as exc:
        raise DataError(f"--adopt {args.adopt}: {exc}") from None
    cams = [{"name": n, "moved": round(m, 6), "turned_deg": round(a, 4)} for n, m, a in changes]
    if args.json:
        emit_json({"dataset": str(ds.root), "adopted": cams, "written": written, "before": before})
    elif not changes:
        console.print(f"{args.adopt} is the dataset's calibration already: nothing to adopt")
    else:
        said = describe_changes(changes, ds.rig.unit)
        console.print(
            f"adopted {args.adopt}: {said}; wrote {written} and named it in "
            f"{ds.root / DESCRIPTOR} (the rig before: {before}); a run's --resume goes on "
            "with it",
            soft_wrap=True,
        )
    return 0


def run(args: argparse.Namespace) -> int:
    if args.adopt is not None:
        return _adopt(args)
    ds = dataset_to_check(args.dataset, write=args.write, what="name a new rig in")
    config = CalibrationCheckConfig(max_error_px=args.max_error)
    check = check_dataset(ds, _times(args.times, ds.num_frames), config, progress=True)
    times = list(check.times)
    fix = repair(check, ds.rig, config)
    fixed, estimates, after = fix.rig, list(fix.applied), fix.check
    written = before = None
    if args.write and estimates:
        written, before = _name_rig(ds, fixed)
    report: dict[str, Any] = {
        "dataset": str(ds.root),
        **check.to_dict(),
        "times": times,
        "estimates": [_estimate_dict(e, ds.rig.names[e.camera]) for e in estimates],
        "ambiguous": [ds.rig.names[c] for c in fix.ambiguous],
        "after": None
        if not estimates
        else {"fits": after.fits, "off": after.off, "message": after.message},
        "written": written,
    }
    if args.json:
        emit_json(report)
    else:
        _print(check, estimates, after, ds.rig.names, config, ds.rig.unit)
        if fix.ambiguous:
            console.print(
                f"{repair_summary(fix, ds.rig)}: nothing changed; check with other --times, "
                "or calibrate again",
                soft_wrap=True,
            )
        elif check.fits is False and not estimates:
            console.print(repair_summary(fix, ds.rig), soft_wrap=True)
        if written:
            console.print(
                f"wrote {written} and named it in {ds.root / DESCRIPTOR} (the rig before: "
                f"{before})",
                soft_wrap=True,
            )
    final = after if written else check
    return 3 if final.fits is False else 0


def _estimate_dict(est: PoseEstimate, name: str) -> dict[str, Any]:
    return {
        "camera": est.camera,
        "name": name,
        "rotation_deg": round(est.rotation_deg, 3),
        "moved": round(est.moved, 4),
        "uncertainty": round(est.uncertainty, 4),
        "before_px": round(est.before_px, 2),
        "after_px": round(est.after_px, 2),
        "pairs": est.pairs,
        "matches": est.matches,
        "R": est.R.tolist(),
        "t": est.t.tolist(),
    }


def _print(
    check: CalibrationCheck,
    estimates: list[PoseEstimate],
    after: CalibrationCheck,
    names: list[str],
    config: CalibrationCheckConfig,
    unit: str,
) -> None:
    max_angle = config.max_angle_deg
    print_table(
        f"camera pairs (matches found without the calibration; {check.frame_sets} frame sets, "
        f"{check.seconds:.1f} s)",
        [
            "pair",
            "axes (deg)",
            "matches",
            "inliers",
            "by chance",
            "median (px)",
            "p90 (px)",
            "limit (px)",
            "fits",
        ],
        [
            [
                f"{names[p.a]}-{names[p.b]}",
                f"{p.angle_deg:.0f}",
                p.matches,
                p.inliers,
                "-" if p.chance is None else p.chance,
                "-" if p.median_px is None else f"{p.median_px:.2f}",
                "-" if p.p90_px is None else f"{p.p90_px:.2f}",
                f"{p.limit_px:.1f}",
                "facing"
                if p.angle_deg > max_angle
                else "-"
                if not p.checked
                else "yes"
                if p.fits
                else "no",
            ]
            for p in check.pairs
        ],
    )
    if any(p.chance is not None and not p.checked for p in check.pairs):
        console.print(
            f"(pairs whose inliers are fewer than {config.chance_ratio:g} times those of the "
            'same points paired at random, "by chance", are not judged: wrong matches)',
            soft_wrap=True,
        )
    print_table(
        "cameras",
        ["camera", "verdict", "px from the lines"],
        [
            [v.name, v.status, "-" if v.median_px is None else f"{v.median_px:.2f}"]
            for v in check.cameras
        ],
    )
    console.print(check.message, soft_wrap=True)
    for est in estimates:
        how = (
            f"moved by {est.moved:.3g} {unit} (+- {est.uncertainty:.2g}) and turned by "
            f"{est.rotation_deg:.2f} degrees"
            if est.moved
            else f"turned by {est.rotation_deg:.2f} degrees (its centre kept)"
        )
        # The verdict weighs pairs by their inliers; the repair tries each camera of the
        # pairs that miss: it can find another one than the verdict named.
        other = (
            f" (the check named {' and '.join(names[c] for c in check.off)}; changing "
            f"{names[est.camera]} instead is what makes the pairs fit)"
            if check.off and est.camera not in check.off
            else ""
        )
        console.print(
            f"{names[est.camera]} {how}: its {est.matches} matches with {est.pairs} cameras "
            f"that fit lie {est.before_px:.1f} -> {est.after_px:.1f} px from their epipolar "
            f"lines{other}",
            soft_wrap=True,
        )
    if estimates:
        done = "placed again" if any(e.moved for e in estimates) else "re-aimed"
        console.print(f"{done}: {after.message}", soft_wrap=True)
    for c in after.off if estimates else []:
        console.print(
            f"{names[c]}: no turn or move brings it back (it needs matches with two cameras "
            "that fit); calibrate it again",
            soft_wrap=True,
        )


def repair_hint(check: CalibrationCheck | None, rig: Rig) -> str | None:
    """What ``calib --write`` would do from ``check``'s frames (``repair_summary``) when the
    calibration does not fit them (``import``, ``info --check``); None when it fits, or when
    that cannot be worked out."""
    fix = None if check is None else try_repair(check, rig)
    return None if fix is None else repair_summary(fix, rig)


def check_dataset(
    ds: Dataset,
    times: list[int] | None = None,
    config: CalibrationCheckConfig | None = None,
    *,
    progress: bool = False,
) -> CalibrationCheck:
    """The calibration against frame sets of a recorded dataset, pooled: ``times``, or 3
    spread over the stream and, when a camera could not be checked on those (it shares too
    few features with the others there: caliscope_charuco's cam_1 while the person sits),
    those of ``POOLED_FRAME_SETS`` spread over it (the first 3 are not read again). A frame set
    that cannot be read is left out (said); none read is a ``DataError``."""
    auto = times is None
    first = default_times(ds.num_frames) if times is None else times
    with ds.open_frames(missing="skip_camera") as source:
        sets = _read_sets(source, first, progress)
        if not sets:
            raise DataError(f"the calibration check read no frame set (times {first})")
        check = check_calibration(sets, ds.rig, config)
        unchecked = [v.name for v in check.cameras if v.status == "unchecked"]
        more = [t for t in default_times(ds.num_frames, POOLED_FRAME_SETS) if t not in first]
        if auto and unchecked and more:
            logger.info(
                "calibration check: %s not checked on times %s (too few features shared with "
                "the others): %d more frame sets",
                ", ".join(unchecked),
                ", ".join(str(t) for t in first),
                len(more),
            )
            extra = _read_sets(source, more, progress)
            if extra:
                check = check_calibration(extra, ds.rig, config, previous=check)
    return check


def _read_sets(source: FrameReader, times: list[int], progress: bool) -> list[FrameSet]:
    sets = []
    for t in track(times, "reading frames") if progress else times:
        try:
            sets.append(source.read(t))
        except EdgereconError as exc:  # a frame that does not decode: the others serve
            logger.warning("calibration check: time %d left out: %s", t, exc)
    return sets


def calibration_check(ds: Dataset) -> CalibrationCheck | None:
    """The calibration against frame sets spread over a dataset (``check_dataset``;
    ``import``'s last step, ``info --check``; None where there are none to read: a live
    stream)."""
    if ds.is_live or ds.num_frames < 1:
        return None
    try:
        return check_dataset(ds)
    except EdgereconError as exc:  # the check is a check: what called it goes on
        logger.warning("the calibration could not be checked: %s", exc)
        return None
