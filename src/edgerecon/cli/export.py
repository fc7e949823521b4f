"""``edgerecon export``: a reconstruction as a COLMAP model (for openMVS and COLMAP), a
nerfstudio dataset (nerfstudio, Instant-NGP, Gaussian splatting) or a viewer-friendly PLY."""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np

from edgerecon import progress
from edgerecon.cli._common import add_json_flag, console, emit_json
from edgerecon.geometry.camera import Rig
from edgerecon.io.crs import check_crs, crs_name
from edgerecon.io.dataset import Dataset, open_dataset
from edgerecon.io.export import export_colmap, export_nerfstudio, z_up_metres
from edgerecon.io.las import write_las
from edgerecon.io.ply import PlyMeta, read_ply, read_ply_meta, write_ply
from edgerecon.runtime.state import TASK_DROPPED, TASK_FOREGROUND, task_dir
from edgerecon.types import DataError, PointCloud
from edgerecon.viewer.rundir import RunFolder, read_run

#: Clouds a reconstruction folder may hold, in the order ``--cloud auto`` picks them for
#: each format (COLMAP: the SfM points first, as COLMAP's own models hold).
_COLMAP_ORDER = ("sparse.ply", "merged.ply", "dense.ply")
_PLY_ORDER = ("merged.ply", "dense.ply", "sparse.ply")
#: The formats of one cloud per file, and their file extensions.
_CLOUD_FORMATS = {"ply": ".ply", "las": ".las", "laz": ".laz"}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export",
        help="export a reconstruction as a COLMAP model (openMVS, COLMAP), a nerfstudio "
        "dataset or a viewer PLY",
        description="SOURCE is the output folder of `reconstruct`, a task folder of `run` "
        "(RUN/tasks/<time>) or a PLY file. --to colmap writes OUT/images/<camera>.png (the "
        "timestamp's frames, undistorted) and OUT/sparse/ (cameras, images, points3D with "
        "tracks): openMVS reads it with `InterfaceCOLMAP -i OUT -o scene.mvs`. --to "
        "nerfstudio writes OUT/images/, OUT/transforms.json (pinhole cameras, OpenGL poses) "
        "and OUT/points3D.ply (the splats' start): `ns-train splatfacto --data OUT`. --to ply "
        "writes one PLY with its unit and up direction in the header, --to las / laz one LAS "
        "file (QGIS, PDAL, Potree, CloudCompare); from a run folder (RUN), one per task whose "
        "cloud the run kept, OUT/<time>.ply (a sequence for Blender, Houdini, Open3D) or "
        ".las / .laz.",
    )
    p.add_argument(
        "source", help="reconstruction folder, run folder or run task folder, or a PLY file"
    )
    p.add_argument(
        "--out",
        "-o",
        required=True,
        help="output folder (colmap, nerfstudio, a run's clouds) or file (ply, las, laz)",
    )
    p.add_argument(
        "--to",
        choices=("colmap", "nerfstudio", "ply", "las", "laz"),
        default="colmap",
        help="format (colmap); las / laz: ASPRS LAS 1.4 for GIS and survey tools (metres, "
        "RGB, foreground class 64, object label in user_data, inferred points synthetic)",
    )
    p.add_argument(
        "--cloud",
        default="auto",
        help="which cloud: sparse, dense, merged, fg, bg or a PLY path (default: colmap: "
        "sparse.ply, nerfstudio and ply: merged.ply or dense.ply)",
    )
    p.add_argument("--dataset", help="the dataset (default: recorded in the source folder)")
    p.add_argument("--time", "-t", type=int, help="the timestamp (default: recorded)")
    p.add_argument("--binary", action="store_true", help="colmap: .bin files instead of .txt")
    p.add_argument(
        "--distorted",
        action="store_true",
        help="colmap: original frames and OPENCV cameras (fisheye cameras: OPENCV_FISHEYE and "
        "their frames as filmed; default: undistorted, PINHOLE)",
    )
    p.add_argument("--no-images", action="store_true", help="colmap: write the model only")
    p.add_argument(
        "--model-dir",
        default="sparse",
        metavar="DIR",
        help="colmap: the model's folder inside OUT (default sparse, as openMVS and COLMAP "
        "read it; sparse/0 for 3D Gaussian Splatting and nerfstudio)",
    )
    p.add_argument(
        "--min-track", type=int, default=2, help="colmap: least images per point (default 2)"
    )
    p.add_argument(
        "--max-range",
        default="auto",
        metavar="auto|none|X",
        help="leave out points farther than X (the rig's unit) from the point the cameras look "
        "at; auto: 3 x the farthest camera's distance from it (stray SfM points tens of metres "
        "away make viewers zoom out and openMVS's scene bounds explode); needs the dataset",
    )
    p.add_argument(
        "--z-up-metres",
        "--z-up-meters",
        dest="z_up_metres",
        action="store_true",
        help="convert to metres with the rig's up along +Z (viewers' convention); the COLMAP "
        "poses follow",
    )
    p.add_argument(
        "--crs",
        metavar="CRS",
        help="ply / las / laz: the world frame's coordinate reference system (EPSG:32633, "
        "WKT; default: the rig's, set by `import --crs`): written into LAS as its WKT record "
        "for QGIS / PDAL, into PLY as a comment; projected or geocentric, in metres",
    )
    add_json_flag(p)
    p.set_defaults(func=run)


def _recorded(source: Path) -> dict[str, Any]:
    """Dataset and time recorded next to a reconstruction (reconstruct's timings.json, or a
    run's state.json for RUN/tasks/<time>)."""
    timings = source / "timings.json"
    if timings.is_file():
        data = json.loads(timings.read_text())
        return {"dataset": data.get("dataset"), "time": data.get("time_index")}
    state = source.parent.parent / "state.json"
    if source.parent.name == "tasks" and state.is_file() and source.name.isdigit():
        dataset = json.loads(state.read_text()).get("dataset")
        if isinstance(dataset, dict):  # the run state's dataset identity
            dataset = dataset.get("root")
        return {"dataset": dataset, "time": int(source.name)}
    return {}


def _cloud_path(source: Path, choice: str, order: tuple[str, ...]) -> Path:
    if source.is_file():
        return source
    if choice == "auto":
        for name in order:
            if _exists(source / name):
                return source / name
        raise DataError(f"{source}: no {', '.join(order)} to export")
    named = {"fg": "fg.ply", "bg": "bg.ply"}.get(choice, f"{choice}.ply")
    path = source / named if not choice.endswith(".ply") else Path(choice)
    if not _exists(path):
        raise DataError(f"cloud {choice!r} not found: {path}")
    return path


def _is_run_task(folder: Path) -> bool:
    """A task folder of ``run`` (RUN/tasks/<time>): the task's foreground and the background
    points it overrode; its merged cloud is composed with the run's background version."""
    return (folder / TASK_FOREGROUND).is_file() and (folder / TASK_DROPPED).is_file()


def _exists(path: Path) -> bool:
    return path.is_file() or (path.name == "merged.ply" and _is_run_task(path.parent))


def _read_cloud(path: Path) -> PointCloud:
    """The cloud at ``path``; a run task's ``merged.ply`` is composed from its parts."""
    if path.is_file():
        return read_ply(path)
    task = path.parent
    cloud = RunFolder(task.parent.parent).cloud(int(task.name))
    if cloud is None:
        raise DataError(f"{task}: the task's merged cloud cannot be composed (see the log)")
    return cloud


def _read_meta(path: Path) -> PlyMeta:
    return read_ply_meta(path if path.is_file() else path.parent / TASK_FOREGROUND)


def run(args: argparse.Namespace) -> int:
    source = Path(args.source)
    if not source.exists():
        raise DataError(f"not found: {source}")
    recorded = _recorded(source if source.is_dir() else source.parent)
    dataset_path = args.dataset or recorded.get("dataset")
    time_index = args.time if args.time is not None else recorded.get("time")
    if args.crs is not None:
        if args.to not in _CLOUD_FORMATS:
            raise DataError(f"--crs is for ply / las / laz exports, not --to {args.to}")
        check_crs(args.crs)
    if args.to in _CLOUD_FORMATS:
        if _is_run(source):
            return _run_cloud_sequence(args, source, args.dataset)
        return _run_cloud_file(args, source, dataset_path)
    if dataset_path is None:
        raise DataError(
            f"--to {args.to} needs the dataset (--dataset DIR): the cameras come from it"
        )
    dataset = open_dataset(dataset_path)
    if args.to == "nerfstudio":
        return _run_nerfstudio(args, source, dataset, time_index)
    cloud_path = _cloud_path(source, args.cloud, _COLMAP_ORDER)
    cloud, dropped = crop_range(_read_cloud(cloud_path), dataset.rig, args.max_range)
    occluders = _occluders(source, cloud_path)
    frames = None
    # --distorted: fisheye cameras as filmed (OPENCV_FISHEYE), their frames not rectified.
    lenses = {n: r.lens for n, r in dataset.frames.rectify} if args.distorted else {}
    if not args.no_images:
        if time_index is None:
            raise DataError("the images need the timestamp (--time T), or pass --no-images")
        spec = dataclasses.replace(dataset.frames, rectify=()) if lenses else dataset.frames
        with spec.open(dataset.rig) as src:
            frames = src.read(int(time_index))
    report = export_colmap(
        args.out,
        dataset.rig,
        cloud,
        frames=frames,
        occluders=occluders,
        distorted=args.distorted,
        binary=args.binary,
        min_track=args.min_track,
        transform=z_up_metres(dataset.rig.unit, dataset.rig.up) if args.z_up_metres else None,
        model_dir=args.model_dir,
        lenses=lenses,
    )
    if _said_json(args, report.to_dict(), cloud_path, time_index, dropped):
        return 0
    console.print(
        f"{cloud_path}: {report.num_points:,} of {report.num_points_in:,} points seen by >= "
        f"{args.min_track} images (mean track {report.mean_track_length:.2f}); "
        f"{len(dataset.rig)} cameras "
        + (
            "(original frames, OPENCV" + (", OPENCV_FISHEYE" if lenses else "") + ")"
            if args.distorted
            else "(undistorted, PINHOLE)"
        ),
        soft_wrap=True,
    )
    if report.transform:
        console.print(f"world frame {report.transform}", soft_wrap=True)
    console.print(
        f"wrote {report.model}" + (f" and {len(report.images)} images" if report.images else ""),
        soft_wrap=True,
    )
    console.print(f"openMVS: InterfaceCOLMAP -i {args.out} -o {Path(args.out) / 'scene.mvs'}")
    return 0


def _said_json(
    args: argparse.Namespace,
    report: dict[str, Any],
    cloud_path: Path,
    time_index: int | None,
    dropped: int,
) -> bool:
    """With --json, the export's report (True: nothing else to print); else the line on the
    points beyond --max-range, if any."""
    if args.json:
        emit_json({**report, "cloud": str(cloud_path), "time": time_index, "dropped": dropped})
        return True
    if dropped:
        console.print(f"left out {dropped:,} points beyond --max-range", soft_wrap=True)
    return False


def _run_nerfstudio(
    args: argparse.Namespace, source: Path, dataset: Dataset, time_index: int | None
) -> int:
    if time_index is None:
        raise DataError("--to nerfstudio needs the timestamp of the frames (--time T)")
    cloud_path = _cloud_path(source, args.cloud, _PLY_ORDER)
    cloud, dropped = crop_range(_read_cloud(cloud_path), dataset.rig, args.max_range)
    with dataset.open_frames() as src:
        frames = src.read(int(time_index))
    report = export_nerfstudio(
        args.out,
        dataset.rig,
        cloud,
        frames,
        transform=z_up_metres(dataset.rig.unit, dataset.rig.up) if args.z_up_metres else None,
    )
    if _said_json(args, report.to_dict(), cloud_path, time_index, dropped):
        return 0
    console.print(
        f"wrote {report.transforms}, {len(report.images)} undistorted images and {report.ply} "
        f"({report.num_points:,} points of {cloud_path.name})"
        + (f"; world frame {report.transform}" if report.transform else ""),
        soft_wrap=True,
    )
    console.print(f"nerfstudio: ns-train splatfacto --data {args.out}", soft_wrap=True)
    return 0


def crop_range(cloud: PointCloud, rig: Any, spec: str) -> tuple[PointCloud, int]:
    """``cloud`` without the points beyond ``--max-range`` (see its help), and how many."""
    import numpy as np

    from edgerecon.cli.info import convergence_point

    if spec == "none":
        return cloud, 0
    center = convergence_point(rig)
    if center is None:
        center = rig.centers.mean(axis=0)
    if spec == "auto":
        radius = 3.0 * float(np.linalg.norm(rig.centers - center, axis=1).max())
    else:
        try:
            radius = float(spec)
        except ValueError:
            raise DataError(f"--max-range must be auto, none or a length, got {spec!r}") from None
        if not radius > 0:
            raise DataError(f"--max-range must be positive, got {spec!r}")
    keep = np.linalg.norm(cloud.points3D - center, axis=1) <= radius
    return cloud.select(keep), int(np.count_nonzero(~keep))


def _occluders(source: Path, cloud_path: Path) -> PointCloud | None:
    """The densest cloud next to the exported one (hides what the cameras cannot see)."""
    folder = source if source.is_dir() else source.parent
    for name in ("merged.ply", "dense.ply"):
        path = folder / name
        if _exists(path) and path != cloud_path:
            return _read_cloud(path)
    return None


def _is_run(folder: Path) -> bool:
    """The output folder of ``run`` (its tasks' clouds under ``tasks/``)."""
    return folder.is_dir() and (folder / "metrics.jsonl").is_file() and (folder / "tasks").is_dir()


@dataclasses.dataclass(frozen=True)
class _Written:
    path: Path
    points: int
    dropped: int
    unit: str | None
    up: tuple[float, ...] | None
    note: str
    crs: str | None = None


def _write_cloud(
    args: argparse.Namespace,
    cloud: PointCloud,
    meta: PlyMeta,
    rig: Rig | None,
    out: Path,
    name: str,
) -> _Written:
    """``cloud`` (read from ``name``, its header ``meta``) cropped by ``--max-range`` with
    the ``rig``, converted by ``--z-up-metres``, written to ``out`` in ``--to``'s format
    with its unit, up direction and origin (the rig's, else the header's; LAS: metres)."""
    dropped = 0
    if rig is not None:
        cloud, dropped = crop_range(cloud, rig, args.max_range)
    unit = rig.unit if rig else meta.unit
    up = tuple(rig.up) if rig else meta.up
    origin = np.asarray(rig.origin if rig else meta.origin or (0.0, 0.0, 0.0))
    crs = args.crs or (rig.crs if rig else meta.crs)
    note = ""
    if args.z_up_metres:
        if unit is None or up is None:
            raise DataError(f"{name} does not record its unit and up direction: give --dataset")
        sim = z_up_metres(unit, up)
        cloud = sim.cloud(cloud)
        origin = sim.points(origin[None])[0]
        unit, up, note = sim.unit, sim.up, sim.describe()
        if crs and not np.allclose(sim.R, np.eye(3)):  # turned: the CRS no longer applies
            if args.crs:
                raise DataError(
                    "--z-up-metres turns this rig's world frame: --crs would not apply to it"
                )
            crs, note = None, note + "; its coordinate reference system left out (turned)"
    if args.to in ("las", "laz"):
        write_las(out, cloud, unit=unit, origin=tuple(origin), crs=crs)
        unit = "m"  # LAS coordinates are metres
    else:
        comments = [f"exported by edgerecon from {name}"]
        if note:
            comments.append(f"world frame {note}")
        write_ply(out, cloud, unit=unit, up=up, origin=tuple(origin), crs=crs, comments=comments)
    return _Written(
        path=out, points=len(cloud), dropped=dropped, unit=unit, up=up, note=note, crs=crs
    )


def _run_cloud_file(args: argparse.Namespace, source: Path, dataset_path: str | None) -> int:
    cloud_path = _cloud_path(source, args.cloud, _PLY_ORDER)
    dataset: Dataset | None = open_dataset(dataset_path) if dataset_path else None
    out = Path(args.out)
    ext = _CLOUD_FORMATS[args.to]
    if out.suffix.lower() != ext:
        out = out / (cloud_path.stem + ext)
    rig = dataset.rig if dataset is not None else None
    w = _write_cloud(
        args, _read_cloud(cloud_path), _read_meta(cloud_path), rig, out, cloud_path.name
    )
    if args.json:
        emit_json(
            {args.to: str(w.path), "points": w.points, "unit": w.unit, "up": w.up,
             "note": w.note, "dropped": w.dropped, "crs": crs_name(w.crs)}
        )  # fmt: skip
        return 0
    if w.dropped:
        console.print(f"left out {w.dropped:,} points beyond --max-range", soft_wrap=True)
    console.print(
        f"wrote {w.path}: {w.points:,} points, unit {w.unit or 'unknown'}, up "
        f"{w.up or 'unknown'}"
        + (f", {crs_name(w.crs)}" if w.crs else "")
        + (f" ({w.note})" if w.note else ""),
        soft_wrap=True,
    )
    return 0


def _run_cloud_sequence(args: argparse.Namespace, run_dir: Path, dataset_path: str | None) -> int:
    """Every task of a run whose cloud it kept, as ``OUT/<time>.ply`` (or ``.las`` /
    ``.laz``; ``--time T``: that task's alone): the merged cloud, or ``--cloud fg`` its
    foreground."""
    if args.cloud not in ("auto", "merged", "fg"):
        raise DataError(f"a run folder's tasks hold merged and fg clouds, not {args.cloud!r}")
    folder = read_run(run_dir)
    dataset: Dataset | None = open_dataset(dataset_path) if dataset_path else None
    rig = dataset.rig if dataset is not None else folder.rig()
    times = [m.time_index for m in folder.tasks if m.status == "ok" and m.cloud_written]
    if args.time is not None:
        times = [t for t in times if t == args.time]
    out = Path(args.out)
    written: list[_Written] = []
    missing = 0
    for t in progress.track(times, "export the task clouds"):
        if args.cloud == "fg":
            fg_path = task_dir(run_dir, t) / TASK_FOREGROUND
            cloud = read_ply(fg_path) if fg_path.is_file() else None
        else:
            cloud = folder.cloud(t)
        if cloud is None:  # removed by --keep-clouds or --min-free-mb
            missing += 1
            continue
        name = f"{run_dir.name}/tasks/{t:06d}"
        path = out / f"{t:06d}{_CLOUD_FORMATS[args.to]}"
        written.append(_write_cloud(args, cloud, PlyMeta(), rig, path, name))
    if not written:
        raise DataError(
            f"{run_dir}: no task cloud to export"
            + (f" at time {args.time}" if args.time is not None else "")
            + (f" ({missing} removed by the run's retention)" if missing else "")
        )
    dropped = sum(w.dropped for w in written)  # the points beyond --max-range
    if args.json:
        emit_json(
            {
                "folder": str(out),
                "clouds": [{args.to: str(w.path), "points": w.points} for w in written],
                "missing": missing,
                "unit": written[0].unit,
                "up": written[0].up,
                "note": written[0].note,
                "dropped": dropped,
                "crs": crs_name(written[0].crs),
            }
        )
        return 0
    if dropped:
        console.print(
            f"left out {dropped:,} points beyond --max-range (all tasks together)", soft_wrap=True
        )
    first, last = written[0].path.name, written[-1].path.name
    console.print(
        f"wrote {len(written)} cloud{'s' if len(written) != 1 else ''} to {out} ({first} .. "
        f"{last}, {int(np.mean([w.points for w in written])):,} points on average, unit "
        f"{written[0].unit or 'unknown'}"
        + (f", {crs_name(written[0].crs)}" if written[0].crs else "")
        + ")"
        + (f"; {missing} tasks' clouds were removed by the run's retention" if missing else "")
        + (f"; {written[0].note}" if written[0].note else ""),
        soft_wrap=True,
    )
    return 0
