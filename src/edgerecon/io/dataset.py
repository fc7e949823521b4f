"""Datasets: a rig tied to its synchronized frame sources, opened from one folder.

``open_dataset(DIR)`` reads ``DIR/dataset.json`` (the format in docs/ARCHITECTURE.md) or, when
there is none, recognises two layouts as they are published:

* **utrecht4cam**: ``camN/config.xml`` + ``camN/video.avi`` [+ ``camN/background.avi``];
  image sizes from the videos, unit mm, up = -Z.
* **Middlebury**: one ``*_par.txt`` + the images it names; a static scene with a single
  timestamp (frame 0 of each camera is its image).

Every problem found while opening (missing files, fewer than 3 cameras, frames whose size
differs from the calibration) raises an ``EdgereconError`` subclass naming what is wrong, so
later stages can trust ``Dataset``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np

from edgerecon.geometry.camera import Rig
from edgerecon.geometry.lens import Rectification
from edgerecon.io.calibration import (
    detect_calibration_format,
    load_rig,
    middlebury_par_files,
    opencv_xml_cameras,
    read_middlebury_par,
    read_opencv_xml_rig,
    save_rig,
)
from edgerecon.io.frames import (
    FrameKind,
    FrameSource,
    FrameSpec,
    MissingPolicy,
    probe_video,
)
from edgerecon.io.ply import atomic_write_text
from edgerecon.types import DataError, EdgereconError

logger = logging.getLogger(__name__)

DESCRIPTOR = "dataset.json"
DESCRIPTOR_FORMAT = "edgerecon-dataset"
DESCRIPTOR_VERSION = 1


@dataclass(frozen=True, kw_only=True)
class Dataset:
    """A calibrated rig and where its frames are. Picklable (no open decoders inside)."""

    root: Path
    """The dataset folder."""
    name: str
    """Human-readable name (descriptor ``name`` or the folder name)."""
    rig: Rig
    """The calibrated cameras; frame sources return images in this order."""
    frames: FrameSpec
    """The synchronized frames of the scene (``open_frames()`` builds the source)."""
    num_frames: int
    """Number of time indices (minimum over cameras, verified when the dataset was opened)."""
    fps: float | None = None
    """Frames per second, None when unknown (image sequences without a descriptor rate)."""
    background: FrameSpec | None = None
    """Optional clip of the empty scene (same cameras), for background models."""
    ground_truth: Path | None = None
    """Optional ground-truth folder (synthetic scenes)."""
    layout: str = "descriptor"
    """How the dataset was recognised: "descriptor", "utrecht4cam" or "middlebury"."""

    def __post_init__(self) -> None:
        # Far from its world's origin (georeferenced), the rig works in a local frame
        # (``Rig.localised``); outputs carry the origin back (``io.ply``).
        object.__setattr__(self, "rig", self.rig.localised())

    @property
    def num_cameras(self) -> int:
        return len(self.rig)

    @property
    def is_live(self) -> bool:
        """True for live camera streams (``frames.kind == "stream"``): no fixed frame count,
        each read is the newest synchronized set."""
        return self.frames.kind == "stream"

    @property
    def is_static(self) -> bool:
        """True for a single-timestamp dataset (e.g. Middlebury)."""
        return self.num_frames == 1

    def open_frames(self, missing: MissingPolicy = "error") -> FrameSource:
        """The scene's frame source (use it as a context manager)."""
        return self.frames.open(self.rig, missing)

    def open_background(self, missing: MissingPolicy = "error") -> FrameSource | None:
        """The empty-scene clip's frame source, or None when the dataset has none."""
        return None if self.background is None else self.background.open(self.rig, missing)

    def to_dict(self) -> dict[str, Any]:
        """Summary for ``--json`` outputs."""
        return {
            "root": str(self.root),
            "name": self.name,
            "layout": self.layout,
            "num_cameras": self.num_cameras,
            "num_frames": None if self.is_live else self.num_frames,
            "fps": self.fps,
            "unit": self.rig.unit,
            "crs": self.rig.crs,
            "frames_kind": self.frames.kind,
            "background": self.background is not None,
            "ground_truth": None if self.ground_truth is None else str(self.ground_truth),
        }


# ============================================================================== opening
def open_dataset(path: str | os.PathLike[str]) -> Dataset:
    """Open a dataset folder: ``dataset.json`` if present, else a known layout."""
    root = Path(path)
    if not root.exists():
        raise DataError(f"dataset not found: {root}")
    if root.is_file():
        if root.name == DESCRIPTOR or root.suffix == ".json":
            return _open_descriptor(root)
        raise DataError(f"{root}: a dataset is a folder (or its {DESCRIPTOR})")
    if (root / DESCRIPTOR).is_file():
        return _open_descriptor(root / DESCRIPTOR)
    if opencv_xml_cameras(root):
        return _open_utrecht(root)
    if middlebury_par_files(root):
        return _open_middlebury(root)
    raise DataError(
        f"{root}: not a dataset: no {DESCRIPTOR}, no camN/config.xml + camN/video.avi "
        "(utrecht4cam layout), no *_par.txt (Middlebury layout)"
    )


def _check_source(spec: FrameSpec, rig: Rig, what: str) -> tuple[int, float | None]:
    """Open ``spec`` against ``rig`` once: checks files and frame sizes; returns
    (num_frames, fps). Live streams: waits for each camera's first frame (a camera that
    delivers none is reported and joins when it comes up)."""
    if spec.kind == "stream":
        from edgerecon.io.streams import StreamFrameSource

        with spec.open(rig) as live:
            assert isinstance(live, StreamFrameSource)
            absent = live.wait_first_frames()
            if absent:
                logger.warning("%s: no frame yet from cameras %s", what, absent)
            return live.num_frames, live.fps
    with spec.open(rig) as source:
        if source.num_frames == 0:
            raise DataError(f"{what}: no frames")
        return source.num_frames, source.fps


def _open_utrecht(root: Path) -> Dataset:
    entries = opencv_xml_cameras(root)
    videos = {}
    sizes = {}
    for name, config in entries:
        video = config.parent / "video.avi"
        if not video.is_file():
            raise DataError(
                f"{root}: camera {name!r} has {config.name} but no video.avi "
                "(utrecht4cam layout: camN/config.xml + camN/video.avi)"
            )
        info = probe_video(video, name)
        videos[name] = str(video)
        sizes[name] = (info.width, info.height)
    rig = read_opencv_xml_rig(root, sizes)
    frames = FrameSpec(kind="video", cameras=tuple(videos.items()))
    num_frames, fps = _check_source(frames, rig, f"{root} videos")
    background = None
    bg = {name: config.parent / "background.avi" for name, config in entries}
    present = [n for n, p in bg.items() if p.is_file()]
    if present and len(present) == len(bg):
        background = FrameSpec(kind="video", cameras=tuple((n, str(p)) for n, p in bg.items()))
        _check_source(background, rig, f"{root} background clips")
    elif present:
        logger.warning(
            "%s: only cameras %s have a background.avi; background clip ignored", root, present
        )
    return Dataset(
        root=root,
        name=root.name,
        rig=rig,
        frames=frames,
        num_frames=num_frames,
        fps=fps,
        background=background,
        layout="utrecht4cam",
    )


def _open_middlebury(root: Path) -> Dataset:
    par = middlebury_par_files(root)
    if len(par) > 1:
        raise DataError(
            f"{root}: several Middlebury parameter files ({', '.join(p.name for p in par)}); "
            f"write a {DESCRIPTOR} to choose one"
        )
    rig = read_middlebury_par(par[0])
    images = []
    with open(par[0], encoding="utf-8") as f:
        lines = [ln.split() for ln in f.read().splitlines()[1:] if ln.strip()]
    for cam, row in zip(rig, lines, strict=True):
        images.append((cam.name, str(root / row[0])))
    frames = FrameSpec(kind="images", cameras=tuple(images))
    num_frames, fps = _check_source(frames, rig, f"{root} images")
    up = ring_axis_up(rig)
    if up is not None:
        rig = dataclasses.replace(rig, up=up)
    return Dataset(
        root=root,
        name=par[0].name.removesuffix("_par.txt"),
        rig=rig,
        frames=frames,
        num_frames=num_frames,
        fps=fps,
        layout="middlebury",
    )


def ring_axis_up(rig: Rig, max_flatness: float = 0.1) -> tuple[float, float, float] | None:
    """The axis of a ring of cameras (the normal of the plane through their centres), signed
    so that the cameras look slightly down; None when the centres are not close to a plane.

    Middlebury's world frames carry no 'up'; its ring captures circle the object around its
    vertical axis, which is what ground-plane hypotheses and viewers need.
    """
    centers = rig.centers - rig.centers.mean(axis=0)
    _, s, vt = np.linalg.svd(centers)
    if s[1] <= 0 or s[2] > max_flatness * s[1]:
        return None
    axis = vt[2]
    looks = np.array([cam.viewing_direction for cam in rig]) @ axis
    if np.median(looks) > 0:
        axis = -axis
    return (float(axis[0]), float(axis[1]), float(axis[2]))


def _spec_from_section(
    section: Any, names: list[str], root: Path, what: str, descriptor: Path, fps: float | None
) -> FrameSpec:
    if not isinstance(section, Mapping):
        raise DataError(f"{descriptor}: {what!r} must be an object with 'kind' and 'cameras'")
    kind = section.get("kind")
    kinds = ("video", "images", "stream") if what == "frames" else ("video", "images")
    if kind not in kinds:
        raise DataError(f"{descriptor}: {what}.kind must be one of {kinds}, got {kind!r}")
    cameras = section.get("cameras")
    pattern = section.get("pattern")
    if cameras is None and isinstance(pattern, str):
        # Extension: one pattern for all cameras with a {camera} field.
        cameras = {name: pattern.replace("{camera}", name) for name in names}
    if not isinstance(cameras, Mapping) or not cameras:
        raise DataError(
            f"{descriptor}: {what}.cameras must map camera names to files, folders or patterns"
        )
    unknown = sorted(set(cameras) - set(names))
    if unknown:
        raise DataError(
            f"{descriptor}: {what} names cameras {unknown} that the rig does not have "
            f"(rig cameras: {names})"
        )
    absent = [n for n in names if n not in cameras]
    if absent:
        raise DataError(f"{descriptor}: {what} has no entry for rig cameras {absent}")
    start = section.get("start", 0)
    if not isinstance(start, int) or start < 0:
        raise DataError(f"{descriptor}: {what}.start must be a non-negative integer")
    offsets = section.get("offsets", {})
    if not isinstance(offsets, Mapping) or not all(
        isinstance(k, int) and k >= 0 for k in offsets.values()
    ):
        raise DataError(
            f"{descriptor}: {what}.offsets must map camera names to non-negative frame counts"
        )
    unknown = sorted(set(offsets) - set(names))
    if unknown:
        raise DataError(f"{descriptor}: {what}.offsets names cameras {unknown} the rig lacks")
    rectify_section = section.get("rectify", {})
    if not isinstance(rectify_section, Mapping):
        raise DataError(f"{descriptor}: {what}.rectify must map camera names to lenses")
    unknown = sorted(set(rectify_section) - set(names))
    if unknown:
        raise DataError(f"{descriptor}: {what}.rectify names cameras {unknown} the rig lacks")
    try:
        rectify = tuple(
            (str(n), Rectification.from_dict(dict(v))) for n, v in rectify_section.items()
        )
    except (EdgereconError, TypeError, ValueError) as exc:
        raise DataError(f"{descriptor}: {what}.rectify: {exc}") from None
    if kind == "stream":
        paths = tuple((n, _stream_location(str(cameras[n]), root)) for n in names)
    else:
        paths = tuple((n, str(root / str(cameras[n]))) for n in names)
    try:
        stream = None
        if kind == "stream":
            from edgerecon.io.streams import StreamConfig

            stream = StreamConfig.from_dict(section)
        return FrameSpec(
            kind=cast(FrameKind, kind),
            cameras=paths,
            start=start,
            fps=fps,
            stream=stream,
            offsets=tuple(offsets.items()),
            rectify=rectify,
        )
    except (ValueError, TypeError) as exc:
        raise DataError(f"{descriptor}: {what}: {exc}") from None


def _stream_location(text: str, root: Path) -> str:
    """A stream entry as given when it is a URL or a device; a file relative to ``root``."""
    if "://" in text or text.startswith("/dev/") or text.isdigit():
        return text
    return str(root / text)


def _open_descriptor(descriptor: Path) -> Dataset:
    root = descriptor.parent
    try:
        data = json.loads(descriptor.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataError(f"{descriptor}: not valid JSON ({exc})") from None
    if not isinstance(data, dict) or data.get("format") != DESCRIPTOR_FORMAT:
        raise DataError(f"{descriptor}: not an edgerecon dataset (format: {DESCRIPTOR_FORMAT})")
    version = data.get("version", DESCRIPTOR_VERSION)
    if not isinstance(version, int) or version > DESCRIPTOR_VERSION:
        raise DataError(
            f"{descriptor}: descriptor version {version!r} is newer than this edgerecon reads "
            f"({DESCRIPTOR_VERSION})"
        )
    for key in ("rig", "frames"):
        if key not in data:
            raise DataError(f"{descriptor}: missing field {key!r}")
    fps = data.get("fps")
    if fps is not None and (not isinstance(fps, int | float) or not fps > 0):
        raise DataError(f"{descriptor}: fps must be a positive number, got {fps!r}")
    fps = None if fps is None else float(fps)
    rig_path = root / str(data["rig"])
    if not rig_path.exists():
        raise DataError(f"{descriptor}: rig file {rig_path} not found")
    rig = _load_descriptor_rig(rig_path, data, root, descriptor)
    frames = _spec_from_section(data["frames"], rig.names, root, "frames", descriptor, fps)
    num_frames, source_fps = _check_source(frames, rig, f"{descriptor} frames")
    background = None
    if data.get("background") is not None:
        background = _spec_from_section(
            data["background"], rig.names, root, "background", descriptor, fps
        )
        _check_source(background, rig, f"{descriptor} background")
    ground_truth = None
    if data.get("ground_truth") is not None:
        ground_truth = root / str(data["ground_truth"])
        if not ground_truth.exists():
            raise DataError(f"{descriptor}: ground truth {ground_truth} not found")
    return Dataset(
        root=root,
        name=str(data.get("name", root.name)),
        rig=rig,
        frames=frames,
        num_frames=num_frames,
        fps=fps if fps is not None else source_fps,
        background=background,
        ground_truth=ground_truth,
        layout="descriptor",
    )


def _load_descriptor_rig(rig_path: Path, data: dict[str, Any], root: Path, descriptor: Path) -> Rig:
    """The descriptor's rig; formats without image sizes (OpenCV XML folders) take them from
    the first frame of each camera's source."""
    if detect_calibration_format(rig_path) != "opencv-xml" or not rig_path.is_dir():
        return load_rig(rig_path)
    names = [name for name, _ in opencv_xml_cameras(rig_path)]
    spec = _spec_from_section(data["frames"], names, root, "frames", descriptor, None)
    with spec.open() as source:
        sizes = source.frame_sizes
    return load_rig(rig_path, sizes)


# ============================================================================== writing
def write_dataset_descriptor(
    root: str | os.PathLike[str],
    *,
    rig: Rig | str | os.PathLike[str],
    frames: FrameSpec | Mapping[str, Any],
    name: str | None = None,
    background: FrameSpec | Mapping[str, Any] | None = None,
    fps: float | None = None,
    ground_truth: str | os.PathLike[str] | None = None,
    rig_file: str = "rig.json",
) -> Path:
    """Write ``root/dataset.json`` (atomically) and return its path.

    ``rig`` is a ``Rig`` (saved as ``root/rig_file``) or the path of an existing calibration
    file relative to ``root``. ``frames`` / ``background`` are ``FrameSpec`` objects (paths
    under ``root`` are written relative to it) or the descriptor's JSON sections as they
    should appear (``{"kind": "images", "cameras": {"cam0": "frames/cam0/{index:06d}.png"}}``).
    """
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    if isinstance(rig, Rig):
        save_rig(root / rig_file, rig)
        rig_ref = rig_file
        names: list[str] | None = rig.names
    else:
        rig_ref = _relative(Path(rig), root)
        names = None
    data: dict[str, Any] = {
        "format": DESCRIPTOR_FORMAT,
        "version": DESCRIPTOR_VERSION,
        "name": name if name is not None else root.name,
        "rig": rig_ref,
        "frames": _section(frames, root, names, "frames"),
    }
    if background is not None:
        data["background"] = _section(background, root, names, "background")
    if fps is not None:
        if not fps > 0:
            raise ValueError(f"fps must be positive, got {fps}")
        data["fps"] = float(fps)
    if ground_truth is not None:
        data["ground_truth"] = _relative(Path(ground_truth), root)
    return atomic_write_text(root / DESCRIPTOR, json.dumps(data, indent=2) + "\n")


def _relative(path: Path, root: Path) -> str:
    if not path.is_absolute():
        return path.as_posix()
    try:
        return path.relative_to(root.resolve() if not root.is_absolute() else root).as_posix()
    except ValueError:
        return str(path)


def _section(
    spec: FrameSpec | Mapping[str, Any], root: Path, names: list[str] | None, what: str
) -> dict[str, Any]:
    if isinstance(spec, FrameSpec):
        out: dict[str, Any] = {
            "kind": spec.kind,
            # A FrameSpec's paths are files as this process sees them (a dataset opened
            # through a relative path holds paths relative to the working directory): those
            # under root are written relative to it, the others absolute.
            "cameras": {
                n: p if spec.kind == "stream" else _relative(Path(p).absolute(), root.absolute())
                for n, p in spec.cameras
            },
        }
        if spec.start:
            out["start"] = spec.start
        if spec.stream is not None:
            out.update(spec.stream.to_dict())
        if spec.offsets:
            out["offsets"] = dict(spec.offsets)
        if spec.rectify:
            out["rectify"] = {n: r.to_dict() for n, r in spec.rectify}
    else:
        out = dict(spec)
        if out.get("kind") not in ("video", "images", "stream"):
            raise ValueError(
                f"{what}.kind must be 'video', 'images' or 'stream', got {out.get('kind')!r}"
            )
        if "cameras" in out:
            out["cameras"] = {str(k): str(v) for k, v in out["cameras"].items()}
        elif "pattern" not in out:
            raise ValueError(f"{what} needs 'cameras' (or a 'pattern' with {{camera}})")
    if names is not None and "cameras" in out and set(out["cameras"]) != set(names):
        raise ValueError(f"{what} cameras {sorted(out['cameras'])} do not match the rig's {names}")
    return out


__all__ = [
    "DESCRIPTOR",
    "Dataset",
    "open_dataset",
    "write_dataset_descriptor",
]
