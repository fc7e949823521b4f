"""``import_dataset``: per-camera videos or image folders + any supported calibration -> an
edgerecon dataset folder (``dataset.json`` + ``rig.json``), checked camera by camera.

What it does, in order:

1. Reads the calibration with ``load_calibration`` (any format, including COLMAP models with many
   images per camera and anipose / Pose2Sim / caliscope TOML), applies ``unit`` and ``up``.
2. Finds each camera's frames. Sources are given as ``NAME=PATH`` pairs, as paths (video
   files, image folders or ``{index}`` patterns) or as one folder holding them
   (``cam0.mp4``, ``cam0/`` with images or one video, ...). Paths are matched to camera
   names: exactly, ignoring case and punctuation (``cam_0`` = ``cam0.mp4``), or as a word of
   the file name (camera ``A`` = ``vid-cam-A.avi``); when names do not tell, paths are taken
   in natural order if their count equals the rig's (and the report says so). A COLMAP
   model's own images (``--images DIR``) are the frames of its cameras.
3. Applies synchronisation offsets (``{camera: k}``: time index t is that camera's frame
   t + k; negative values shift the other cameras instead).
4. Checks every camera: frames readable, frame counts, frame size against the calibration.
   A calibration made at another resolution with the same aspect ratio is rescaled to the
   frames (and reported); anything else is an error naming the camera.
5. Writes ``rig.json`` and ``dataset.json`` atomically and opens the result once more as a
   user would (``open_dataset``).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import re
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from edgerecon.geometry.camera import Rig
from edgerecon.geometry.lens import CalibratedRig, FisheyeLens, Rectification, pinhole_camera
from edgerecon.io.calib_llff import read_llff
from edgerecon.io.calib_mocap import easymocap_camera_names, read_easymocap
from edgerecon.io.calib_nerf import transforms_calibration, transforms_camera_names
from edgerecon.io.calibration import detect_calibration_format, load_calibration
from edgerecon.io.colmap import find_colmap_model, read_colmap_model, rig_from_colmap
from edgerecon.io.crs import check_crs
from edgerecon.io.dataset import DESCRIPTOR, Dataset, open_dataset, write_dataset_descriptor
from edgerecon.io.frames import (
    IMAGE_EXTENSIONS,
    VIDEO_EXTENSIONS,
    FrameSpec,
    natural_key,
)
from edgerecon.io.sync import SyncResult, estimate_offsets
from edgerecon.types import CalibrationError, DataError

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class CameraImport:
    """What was found for one camera."""

    name: str
    kind: str
    """"video" or "images"."""
    source: str
    """Video file, image folder or pattern."""
    matched_by: str
    """"name", "order", "explicit" or "colmap"."""
    num_frames: int
    """Frames of this camera after its offset."""
    size: tuple[int, int]
    fps: float | None
    offset: int
    rescaled_from: tuple[int, int] | None = None
    """Calibrated size when the calibration was rescaled to the frames."""


@dataclass(frozen=True, kw_only=True, eq=False)
class ImportReport:
    """The dataset written by ``import_dataset`` and what was found on the way."""

    dataset: Dataset
    calibration: str
    calibration_format: str
    cameras: list[CameraImport]
    unit_note: str
    up_note: str
    notes: list[str] = field(default_factory=list)
    sync: SyncResult | None = None
    """The offsets' estimate (``offsets="auto"``)."""

    def to_dict(self) -> dict[str, Any]:
        ds = self.dataset
        return {
            **ds.to_dict(),
            "calibration": self.calibration,
            "calibration_format": self.calibration_format,
            "up": list(ds.rig.up),
            "scene_scale": ds.rig.scene_scale(),
            "unit_note": self.unit_note,
            "up_note": self.up_note,
            "cameras": [dataclasses.asdict(c) for c in self.cameras],
            "notes": self.notes,
            "sync": None if self.sync is None else self.sync.to_dict(),
        }


# ============================================================================== up
def level_horizon_up(rig: Rig, max_ratio: float = 0.05) -> tuple[float, float, float] | None:
    """The world direction orthogonal to every camera's image x-axis (cameras mounted with
    level horizons), signed like the images' up; None when the axes do not pin it down
    (smallest / middle eigenvalue above ``max_ratio``)."""
    xs = np.array([cam.R[0] for cam in rig])
    w, v = np.linalg.eigh(xs.T @ xs)
    if w[1] <= 0 or w[0] > max_ratio * w[1]:
        return None
    up = v[:, 0]
    image_up = -np.array([cam.R[1] for cam in rig]).sum(axis=0)
    if float(up @ image_up) < 0:
        up = -up
    return (float(up[0]), float(up[1]), float(up[2]))


def _snap_to_axis(up: tuple[float, float, float], max_deg: float = 10.0) -> tuple[str, Any]:
    """(axis label, vector) of the world axis within ``max_deg`` of ``up``, else ("", up)."""
    u = np.asarray(up)
    k = int(np.argmax(np.abs(u)))
    angle = math.degrees(math.acos(min(1.0, abs(float(u[k])))))
    if angle <= max_deg:
        axis = [0.0, 0.0, 0.0]
        axis[k] = 1.0 if u[k] > 0 else -1.0
        return ("+-"[int(u[k] < 0)] + "XYZ"[k], tuple(axis))
    return ("", up)


def parse_up(text: str) -> tuple[float, float, float] | str:
    """``auto``, ``keep``, ``+z``/``-y``/... or ``x,y,z``."""
    t = text.strip().lower()
    if t in ("auto", "keep"):
        return t
    m = re.fullmatch(r"([+-]?)([xyz])", t)
    if m:
        v = [0.0, 0.0, 0.0]
        v["xyz".index(m.group(2))] = -1.0 if m.group(1) == "-" else 1.0
        return (v[0], v[1], v[2])
    try:
        vals = [float(x) for x in t.replace(",", " ").split()]
    except ValueError:
        vals = []
    if len(vals) != 3 or not np.linalg.norm(vals) > 0:
        raise ValueError(f"--up must be auto, keep, +x/-y/..., or X,Y,Z; got {text!r}")
    n = float(np.linalg.norm(vals))
    return (vals[0] / n, vals[1] / n, vals[2] / n)


# ============================================================================== sources
def _norm(label: str) -> str:
    return re.sub(r"[^0-9a-z]", "", label.lower())


def _tokens(label: str) -> list[str]:
    return [t for t in re.split(r"[^0-9A-Za-z]+", label.lower()) if t]


@dataclass(frozen=True)
class _Source:
    label: str
    kind: str
    path: str
    explicit_name: str | None = None


def _classify(path: Path) -> _Source | None:
    """A single camera's source at ``path``, or None when it is not one."""
    text = str(path)
    if "{index" in text:
        return _Source(Path(text).parent.name or Path(text).stem, "images", text)
    if path.is_file():
        if path.suffix.lower() in VIDEO_EXTENSIONS:
            return _Source(path.stem, "video", text)
        if path.suffix.lower() in IMAGE_EXTENSIONS:
            return _Source(path.stem, "images", text)
        return None
    if path.is_dir():
        files = [p for p in path.iterdir() if p.is_file()]
        images = [p for p in files if p.suffix.lower() in IMAGE_EXTENSIONS]
        videos = [p for p in files if p.suffix.lower() in VIDEO_EXTENSIONS]
        if images:
            return _Source(path.name, "images", text)
        if len(videos) == 1:
            return _Source(path.name, "video", str(videos[0]))
        named = [v for v in videos if v.stem in ("video", path.name)]
        if len(named) == 1:
            return _Source(path.name, "video", str(named[0]))
    return None


def collect_sources(items: Sequence[str]) -> list[_Source]:
    """The per-camera sources named by ``items`` (``NAME=PATH``, paths, or one folder that
    holds the cameras' videos / image folders)."""
    out: list[_Source] = []
    for item in items:
        name = None
        text = item
        if "=" in item and not Path(item).exists():
            name, text = item.split("=", 1)
        # Absolute: the dataset is opened from its own folder, not from where this runs.
        path = Path(text).absolute()
        if not path.exists() and "{index" not in text:
            raise DataError(f"frames not found: {text}")
        src = _classify(path)
        if src is not None and not (path.is_dir() and _is_container(path)):
            out.append(dataclasses.replace(src, explicit_name=name))
            continue
        if path.is_dir() and name is None:
            inner = [
                s
                for p in sorted(path.iterdir(), key=lambda p: natural_key(p.name))
                if (s := _classify(p)) is not None
            ]
            if inner:
                out.extend(inner)
                continue
        raise DataError(
            f"{text}: neither a video, an image folder or pattern, nor a folder of per-camera "
            "videos / image folders"
        )
    return out


def _is_container(path: Path) -> bool:
    """A folder whose sub-folders are cameras (they hold images or a video) and that holds
    no images itself."""
    files = [p for p in path.iterdir() if p.is_file()]
    if any(p.suffix.lower() in IMAGE_EXTENSIONS for p in files):
        return False
    subs = [p for p in path.iterdir() if p.is_dir() and _classify(p) is not None]
    return len(subs) >= 2 or sum(p.suffix.lower() in VIDEO_EXTENSIONS for p in files) >= 2


def _name_in_label(name: str, label: str) -> bool:
    """Whether camera ``name`` is a word, or a run of words, of a file's ``label``
    (camera ``A`` in ``vid-cam-A``, Panoptic's ``00_03`` in ``hd_00_03``)."""
    words, label_words = _tokens(name), _tokens(label)
    if _norm(name) in label_words:
        return True
    k = len(words)
    return k > 0 and any(label_words[i : i + k] == words for i in range(len(label_words) - k + 1))


def match_sources(
    names: Sequence[str], sources: Sequence[_Source], subset_min: int | None = None
) -> dict[str, tuple[_Source, str]]:
    """Camera name -> (source, how it was matched); see the module docstring. With
    ``subset_min``, a calibration may hold more cameras than there are sources when every
    source is one camera's, explicitly or by name, and at least ``subset_min`` cameras have
    one: the others are not in the result."""
    if subset_min is None:
        subset_min = len(names) + 1
    result: dict[str, tuple[_Source, str]] = {}
    rest = []
    for s in sources:
        if s.explicit_name is not None:
            if s.explicit_name not in names:
                raise DataError(
                    f"frames given for camera {s.explicit_name!r}, which the calibration lacks "
                    f"(cameras: {', '.join(names)})"
                )
            result[s.explicit_name] = (s, "explicit")
        else:
            rest.append(s)
    todo = [n for n in names if n not in result]
    if not rest:
        if todo and len(result) < subset_min:
            raise DataError(f"no frames for cameras {todo}")
        return result
    by_name: dict[str, _Source] = {}
    for n in todo:
        exact = [s for s in rest if _norm(s.label) == _norm(n)]
        cands = exact or [s for s in rest if _name_in_label(n, s.label)]
        if len(cands) == 1:
            by_name[n] = cands[0]
    used = [id(s) for s in by_name.values()]
    if len(set(used)) == len(used) and (
        len(by_name) == len(todo)
        # A calibration of more cameras than were filmed (a dome's): every source is one
        # camera's by name, the others are left out (``import_dataset`` says which).
        or (len(by_name) == len(rest) and len(result) + len(by_name) >= subset_min)
    ):
        result.update({n: (s, "name") for n, s in by_name.items()})
        return result
    subset = subset_min <= len(names)
    if (
        subset
        and len(by_name) == len(rest) == len(set(used))
        and len(result) + len(by_name) < subset_min
    ):
        have = sorted([*result, *by_name])
        raise DataError(
            f"only {len(have)} of the calibration's cameras have frames ({', '.join(have)}); "
            f"a rig needs at least {subset_min}"
        )
    if len(rest) == len(todo):
        ordered = sorted(rest, key=lambda s: natural_key(s.label))
        result.update({n: (s, "order") for n, s in zip(todo, ordered, strict=True)})
        return result
    raise DataError(
        f"cannot tell which frames belong to which camera: cameras {todo}, sources "
        f"{[s.path for s in rest]}; give them as NAME=PATH"
    )


def _colmap_frames(
    calibration: Path, images: Path, out: Path, rig: Rig
) -> dict[str, tuple[_Source, str]]:
    """Each camera's frames from a COLMAP model's image names under ``images``: the image
    folder itself when it holds exactly that camera's images, else a folder of links."""
    model = read_colmap_model(calibration, points=False)
    grouped = rig_from_colmap(model, source=str(calibration))
    result = {}
    for name in rig.names:
        files = [images / n for n in grouped.frames[name]]
        missing = [str(f) for f in files if not f.is_file()]
        if missing:
            raise DataError(
                f"camera {name!r}: {len(missing)} of its {len(files)} COLMAP images are not in "
                f"{images} (first: {missing[0]})"
            )
        folders = {f.parent for f in files}
        if len(folders) == 1:
            folder = next(iter(folders))
            listed = sorted(
                (p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS),
                key=lambda p: natural_key(p.name),
            )
            if [p.resolve() for p in listed] == [f.resolve() for f in files]:
                result[name] = (_Source(name, "images", str(folder)), "colmap")
                continue
        link_dir = out / "frames" / name
        link_dir.mkdir(parents=True, exist_ok=True)
        for k, f in enumerate(files):
            link = link_dir / f"{k:06d}{f.suffix.lower()}"
            link.unlink(missing_ok=True)
            try:
                link.symlink_to(f.resolve())
            except OSError:
                import shutil

                shutil.copyfile(f, link)
        result[name] = (_Source(name, "images", str(link_dir)), "colmap")
    return result


def _probe(src: _Source) -> tuple[int, tuple[int, int], float | None]:
    """(frames, size, fps) of one camera's source."""
    spec = FrameSpec(kind=src.kind, cameras=(("c", src.path),))  # type: ignore[arg-type]
    with spec.open() as source:
        return source.num_frames, source.frame_sizes["c"], source.fps


# ============================================================================== import
#: Formats that may record no image size (EasyMocap without ``H_`` / ``W_``, the Blender
#: scenes' ``transforms.json``): their cameras' names, then the calibration read at the
#: sizes of the frames matched to them (only the filmed cameras).
_SIZED_BY_FRAMES: dict[
    str,
    tuple[
        Callable[[Path], list[str]],
        Callable[[Path, dict[str, tuple[int, int]], Collection[str]], CalibratedRig],
    ],
] = {
    "easymocap": (
        easymocap_camera_names,
        lambda c, sizes, only: CalibratedRig(rig=read_easymocap(c, sizes, only=only), lenses={}),
    ),
    "nerf": (
        transforms_camera_names,
        lambda c, sizes, only: transforms_calibration(c, sizes, only=only),
    ),
}

#: Formats whose tools write metres, and the tools' names.
_IN_METRES = {"easymocap": "EasyMocap", "kalibr": "Kalibr", "egoexo": "Ego-Exo4D"}


def import_dataset(
    out: str | os.PathLike[str],
    *,
    calibration: str | os.PathLike[str],
    frames: Sequence[str] = (),
    images: str | os.PathLike[str] | None = None,
    background: Sequence[str] = (),
    offsets: Mapping[str, int] | Literal["auto"] | None = None,
    unit: str | None = None,
    up: str | tuple[float, float, float] = "auto",
    fps: float | None = None,
    name: str | None = None,
    crs: str | None = None,
    overwrite: bool = False,
) -> ImportReport:
    """Write a dataset folder ``out`` from a calibration and per-camera frames (see the module
    docstring). ``offsets="auto"``: estimated from the frames (``io.sync``). Raises
    ``DataError`` / ``CalibrationError`` naming the camera and problem."""
    out = Path(out)
    calib = Path(calibration)
    if (out / DESCRIPTOR).exists() and not overwrite:
        raise DataError(f"{out / DESCRIPTOR} exists; pass overwrite=True (--force) to replace it")
    if crs:
        check_crs(crs)  # before any work
    fmt = detect_calibration_format(calib)
    if images is not None and fmt != "colmap":
        raise DataError("--images goes with a COLMAP model (its image names are the frames)")
    if images is None and not frames:
        raise DataError("no frames given: pass per-camera videos / image folders (or --images)")
    sources = collect_sources(frames) if images is None else []
    matched: dict[str, tuple[_Source, str]] = {}
    listed: list[str] | None = None  # the calibration's cameras, where it was read in part
    lenses: dict[str, FisheyeLens] = {}  # fisheye cameras (in the rig as their pinhole views)
    if fmt == "llff":
        # Rows follow the sorted images / videos they were made from: the sources in natural
        # order name the cameras.
        ordered = sorted(sources, key=lambda s: natural_key(s.label))
        rig = read_llff(calib, [s.label for s in ordered])
        matched = {s.label: (s, "order") for s in ordered}
    elif fmt in _SIZED_BY_FRAMES:
        # The file may record no image size: the frames' own, before the cameras are read.
        names_of, read = _SIZED_BY_FRAMES[fmt]
        listed = names_of(calib)
        matched = match_sources(listed, sources, subset_min=3)
        sizes = {n: _probe(src)[1] for n, (src, _) in matched.items()}
        cal = read(calib, sizes, matched.keys())
        rig, lenses = cal.rig, dict(cal.lenses)
    else:
        cal = load_calibration(calib)
        rig, lenses = cal.rig, dict(cal.lenses)
    if crs:
        rig = dataclasses.replace(rig, crs=crs)
    notes: list[str] = []
    unit_note = f"{rig.unit} (from the calibration)"
    if unit is not None:
        unit_note = f"{unit} (given)" if unit != rig.unit else unit_note
        rig = dataclasses.replace(rig, unit=unit)
    elif fmt == "toml":
        flavour = _toml_flavour(calib)
        unit_note = (
            f"{rig.unit} (guessed from the rig's size: anipose files store no unit; give --unit)"
            if flavour == "anipose"
            else f"{rig.unit} ({flavour} calibrations are in metres)"
        )
    elif fmt in ("openmvg", "colmap", "llff", "nerf") and rig.unit == "m":
        unit_note = "m (assumed: the format stores no unit; SfM scales are arbitrary)"
    elif fmt in _IN_METRES:
        unit_note = f"m ({_IN_METRES[fmt]} calibrations are in metres)"
    elif fmt == "multical":
        unit_note = "m (multical: the boards' unit, metres in its board files; give --unit)"
    elif fmt == "panoptic":
        unit_note = (
            "cm (Panoptic Studio calibrations are in centimetres)"
            if rig.unit == "cm"
            else f"{rig.unit} (guessed from the rig's size: Panoptic's own files are in "
            "centimetres; give --unit)"
        )

    out.mkdir(parents=True, exist_ok=True)
    if images is not None:
        model_dir = find_colmap_model(calib)
        assert model_dir is not None
        matched = _colmap_frames(model_dir, Path(images), out, rig)
    else:
        matched = matched or match_sources(rig.names, sources, subset_min=rig.min_cameras)
        left_out = [n for n in (listed or rig.names) if n not in matched]
        if left_out:
            rig = dataclasses.replace(rig, cameras=tuple(c for c in rig if c.name in matched))
            shown = ", ".join(left_out[:8])
            more = f" and {len(left_out) - 8} more" if len(left_out) > 8 else ""
            notes.append(
                f"{len(left_out)} of the calibration's {len(left_out) + len(rig)} cameras have "
                f"no frames and are left out: {shown}{more}"
            )
    unused = [s.path for s in sources if all(s is not m for m, _ in matched.values())]
    if unused:
        shown = ", ".join(Path(p).name for p in unused[:8])
        more = f" and {len(unused) - 8} more" if len(unused) > 8 else ""
        notes.append(
            f"{len(unused)} source(s) named after no camera of the calibration, left out: "
            f"{shown}{more}"
        )
    rig, up_note = _apply_up(rig, up, fmt)
    kinds = {src.kind for src, _ in matched.values()}
    if len(kinds) > 1:
        raise DataError(
            "all cameras need the same kind of frames (videos or images), got "
            + ", ".join(f"{n}: {s.kind}" for n, (s, _) in matched.items())
        )
    kind = kinds.pop()
    sync = None
    if offsets == "auto":
        sync = _estimate_offsets(kind, rig.names, matched, fps, notes)
        offsets = sync.offsets
    offs = _normalise_offsets(offsets or {}, rig.names)

    cameras: list[CameraImport] = []
    new_cams = []
    for cam in rig:
        src, how = matched[cam.name]
        n, size, cam_fps = _probe(src)
        rescaled = None
        if size != cam.size:
            if _same_aspect(size, cam.size) and cam.name in lenses:
                rescaled = cam.size
                lens = lenses[cam.name] = lenses[cam.name].resized(*size)
                cam = pinhole_camera(cam.name, lens, cam.R, cam.t)
                notes.append(
                    f"camera {cam.name!r}: calibrated at {rescaled[0]}x{rescaled[1]}, frames "
                    f"are {size[0]}x{size[1]}: the fisheye lens rescaled"
                )
            elif _same_aspect(size, cam.size):
                rescaled = cam.size
                cam = cam.resized(*size)
                notes.append(
                    f"camera {cam.name!r}: calibrated at {rescaled[0]}x{rescaled[1]}, frames "
                    f"are {size[0]}x{size[1]}: intrinsics rescaled"
                )
            else:
                raise CalibrationError(
                    f"camera {cam.name!r}: frames in {src.path} are {size[0]}x{size[1]} but the "
                    f"calibration says {cam.width}x{cam.height}"
                )
        new_cams.append(cam)
        k = offs.get(cam.name, 0)
        if k >= n:
            raise DataError(
                f"camera {cam.name!r}: offset {k} skips all of its {n} frames ({src.path})"
            )
        cameras.append(
            CameraImport(
                name=cam.name,
                kind=src.kind,
                source=src.path,
                matched_by=how,
                num_frames=n - k,
                size=size,
                fps=cam_fps,
                offset=k,
                rescaled_from=rescaled,
            )
        )
    rig = dataclasses.replace(rig, cameras=tuple(new_cams))
    if any(c.matched_by == "order" for c in cameras):
        notes.append(
            "frames matched to cameras by order (names did not tell): "
            + ", ".join(f"{c.name} <- {Path(c.source).name}" for c in cameras)
        )
    rectify = tuple(
        (c.name, Rectification(lens=lenses[c.name], K=c.K)) for c in rig if c.name in lenses
    )
    if rectify:
        notes.append(
            f"{len(rectify)} camera(s) with fisheye lenses ("
            + ", ".join(f"{c.name} f {c.K[0, 0]:.0f} px" for c in rig if c.name in lenses)
            + " as pinhole cameras): their frames are rectified as they are read, to the "
            "widest pinhole view without invalid pixels"
        )
    spec = FrameSpec(
        kind=kind,  # type: ignore[arg-type]
        cameras=tuple((c.name, c.source) for c in cameras),
        offsets=tuple(offs.items()),
        rectify=rectify,
    )
    bg_spec = None
    if background:
        bg = match_sources(rig.names, collect_sources(background))
        bg_kinds = {s.kind for s, _ in bg.values()}
        if len(bg_kinds) > 1:
            raise DataError("the background clips must all be videos or all image folders")
        bg_spec = FrameSpec(
            kind=bg_kinds.pop(),  # type: ignore[arg-type]
            cameras=tuple((n, bg[n][0].path) for n in rig.names),
            rectify=rectify,
        )
    write_dataset_descriptor(
        out,
        rig=rig,
        frames=spec,
        background=bg_spec,
        fps=fps,
        name=name or out.name,
    )
    dataset = open_dataset(out)
    counts = {c.name: c.num_frames for c in cameras}
    if kind in ("video", "images"):
        with dataset.open_frames() as opened:
            if getattr(opened, "pairing", "index") == "time" and kind == "video":
                notes.append(
                    "the videos' frame rates differ or vary ("
                    + ", ".join(f"{c.name} {c.fps:.3f}" for c in cameras if c.fps)
                    + f" fps in their headers): time index t pairs each camera's frame nearest "
                    f"in time to t / {opened.fps:.3f} s (its frames' timestamps)"
                )
                counts = opened.frame_counts  # in time indices
            elif getattr(opened, "pairing", "index") == "time":
                notes.append(
                    "every camera's image files are named by capture times: time index t "
                    "pairs each camera's frame nearest to the latest first frame's time + t / "
                    f"{opened.fps:.3f} s"
                )
                counts = opened.frame_counts
    if len(set(counts.values())) > 1:
        notes.append(
            f"cameras have different frame counts {counts}: the dataset uses the first "
            f"{min(counts.values())}"
        )
    logger.info("imported %s: %d cameras, %d frames", out, len(rig), dataset.num_frames)
    return ImportReport(
        dataset=dataset,
        calibration=str(calib),
        calibration_format=fmt,
        cameras=cameras,
        unit_note=unit_note,
        up_note=up_note,
        notes=notes,
        sync=sync,
    )


def _estimate_offsets(
    kind: str,
    names: Sequence[str],
    matched: Mapping[str, tuple[_Source, str]],
    fps: float | None,
    notes: list[str],
) -> SyncResult:
    """``offsets="auto"``: the cameras' offsets from their motion (``io.sync``), said in
    ``notes``; cameras it cannot link stay at the best-linked camera's time."""
    spec = FrameSpec(
        kind=kind,  # type: ignore[arg-type]
        cameras=tuple((n, matched[n][0].path) for n in names),
        fps=fps,
    )
    with spec.open() as source:
        result = estimate_offsets(source, progress=True)
    used = [p for p in result.pairs if p.used]
    notes.append(
        "offsets estimated from the cameras' motion over their first "
        f"{result.frames_read} frames: "
        + ", ".join(f"{n} {k}" for n, k in result.offsets.items())
        + f" (from {len(used)} of {len(result.pairs)} camera pairs, peaks "
        + (
            f"{min(p.peak for p in used):.1f}-{max(p.peak for p in used):.1f} sigma)"
            if used
            else "-)"
        )
    )
    if result.unlinked:
        notes.append(
            "no camera pair agreed on the offset of "
            + ", ".join(result.unlinked)
            + ": left at the best-linked camera's time (too little motion seen by it and "
            "the others in the window, or a periodic motion); check it, or give --offset"
        )
    return result


def _toml_flavour(calib: Path) -> str | None:
    from edgerecon.io.calib_toml import load_toml, toml_calibrations, toml_flavour

    files = toml_calibrations(calib) if calib.is_dir() else [calib]
    return toml_flavour(load_toml(files[0])) if files else None


def _same_aspect(a: tuple[int, int], b: tuple[int, int]) -> bool:
    return abs(a[0] / b[0] - a[1] / b[1]) <= 0.01 * max(a[0] / b[0], a[1] / b[1])


def _normalise_offsets(offsets: Mapping[str, int], names: Sequence[str]) -> dict[str, int]:
    unknown = sorted(set(offsets) - set(names))
    if unknown:
        raise DataError(f"offsets given for cameras {unknown} the calibration lacks ({names})")
    full = {n: int(offsets.get(n, 0)) for n in names}
    low = min(full.values())
    return {n: k - low for n, k in full.items() if k - low}


def _apply_up(rig: Rig, up: str | tuple[float, float, float], fmt: str) -> tuple[Rig, str]:
    if isinstance(up, str):
        up = parse_up(up)
    if isinstance(up, tuple):
        return dataclasses.replace(rig, up=up), f"{_fmt_vec(up)} (given)"
    if (
        up == "keep"
        or fmt in ("edgerecon", "opencv-xml", "middlebury")
        or (fmt == "colmap" and tuple(rig.up) != (0.0, 0.0, 1.0))
    ):
        return rig, f"{_fmt_vec(rig.up)} (from the calibration)"
    est = level_horizon_up(rig)
    if est is None:
        return rig, f"{_fmt_vec(rig.up)} (default; the cameras' horizons do not tell: give --up)"
    label, vec = _snap_to_axis(est)
    if label:
        return (
            dataclasses.replace(rig, up=vec),
            f"{label} (the cameras' level horizons point within 10 deg of it)",
        )
    return dataclasses.replace(
        rig, up=est
    ), f"{_fmt_vec(est)} (estimated from the cameras' level horizons)"


def _fmt_vec(v: Sequence[float]) -> str:
    return "(" + ", ".join(f"{x:.3g}" for x in v) + ")"


def parse_offsets(items: Sequence[str]) -> dict[str, int] | Literal["auto"]:
    """``NAME=K`` items (or comma-separated lists of them) -> {name: K}; ``auto`` alone ->
    "auto" (estimated from the frames)."""
    if [i.strip().lower() for i in items] == ["auto"]:
        return "auto"
    out: dict[str, int] = {}
    for item in items:
        for part in item.split(","):
            if not part.strip():
                continue
            if "=" not in part:
                raise ValueError(f"--offset expects CAMERA=FRAMES, got {part!r}")
            n, k = part.split("=", 1)
            try:
                out[n.strip()] = int(k)
            except ValueError:
                raise ValueError(f"--offset {part!r}: FRAMES must be an integer") from None
    return out


__all__ = [
    "CameraImport",
    "ImportReport",
    "collect_sources",
    "import_dataset",
    "level_horizon_up",
    "match_sources",
    "parse_offsets",
    "parse_up",
]
