"""Calibration readers and writers: every format returns an ``edgerecon.geometry.Rig``.

Formats (``load_rig`` detects them from a file or a folder):

* **edgerecon rig JSON** (``rig.json``; ``save_rig`` / ``read_rig_json``): ``Rig.to_dict()``
  written with ``repr``-exact floats, so a round trip is bit-identical.
* **openMVG** ``sfm_data.json``: intrinsics ``pinhole``, ``pinhole_radial_k1``,
  ``pinhole_radial_k3`` (k1, k2, k3 -> OpenCV (k1, k2, 0, 0, k3)) and ``pinhole_brown_t2``
  (k1, k2, k3, t1, t2). openMVG's Brown model is
  ``x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + t2 (r^2 + 2 x^2) + 2 t1 x y`` and
  ``y_d = y (...) + t1 (r^2 + 2 y^2) + 2 t2 x y``, which is OpenCV's with ``p1 = t1`` and
  ``p2 = t2``. Poses: ``rotation`` is the world->camera R and ``center`` the camera centre C,
  so ``t = -R C``. Views without a pose are skipped with a warning. Camera names are the view
  file stems (``000.png`` -> ``"000"``), or ``"cam{key}"`` when they are not unique. The
  principal point is used as written (openMVG, like edgerecon, puts pixel centres on integer
  coordinates). openMVG stores no unit: SfM scales are arbitrary, pass ``unit=`` if known.
* **OpenCV FileStorage XML**, one file per camera as in utrecht4cam's ``camN/config.xml``:
  ``CameraMatrix`` (3x3), ``DistortionCoeffs`` (k1 k2 p1 p2 [k3]), ``Rotation`` (3x1 Rodrigues
  vector or 3x3 matrix) and ``Translation`` (3x1), world->camera. These files carry no image
  size: it comes from ``image_sizes`` or from a video / image next to the file (a folder of
  ``camN/config.xml`` uses ``camN/video.avi``). A folder of such cameras reads as unit "mm"
  and up = (0, 0, -1): utrecht4cam's checkerboard world frame has Z pointing down.
* **Middlebury** ``*_par.txt``: a count line, then per image
  ``name k11..k33 r11..r33 t1 t2 t3`` (``K [R | t]`` world->camera, metres). Image sizes
  are read from the image files next to it. Camera names are the image stems.
* **COLMAP model** (``cameras`` + ``images`` as ``.txt`` or ``.bin``, also under ``sparse/``
  or ``sparse/0``; ``edgerecon.io.colmap``). Models SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL,
  RADIAL, OPENCV and FULL_OPENCV (when k4..k6 are zero). Many images per camera (a capture's
  frames, ``cam0/000000.png`` ...) are grouped into the rig's cameras by COLMAP camera id,
  folder or pose. COLMAP puts the centre of the top-left pixel at (0.5, 0.5): principal
  points are shifted by 0.5 pixel. The writer records the rig's unit and up direction in a
  comment that the reader understands (COLMAP ignores comments).
* **anipose / Pose2Sim / caliscope TOML** (``calibration.toml``, ``Calib*.toml``,
  ``camera_array.toml``; ``edgerecon.io.calib_toml``): OpenCV cameras, world->camera.
* **EasyMocap** ``intri.yml`` + ``extri.yml`` (ZJU-MoCap's layout too) and **CMU Panoptic
  Studio** ``calibration_<sequence>.json`` (``edgerecon.io.calib_mocap``).
* **LLFF** ``poses_bounds.npy`` (NeRF's forward-facing scenes, Neural 3D Video;
  ``edgerecon.io.calib_llff``).
* **Kalibr** ``camchain.yaml`` (robotics rigs; ``edgerecon.io.calib_kalibr``): pinhole
  cameras with radtan or equidistant (fisheye) distortion chained by ``T_cn_cnm1`` from
  camera 0.
* **Ego-Exo4D** ``gopro_calibs.csv`` (``edgerecon.io.calib_egoexo``): static GoPros with
  Kannala-Brandt fisheye lenses.
* **multical** ``calibration.json`` (``edgerecon.io.calib_multical``): OpenCV or fisheye
  cameras, poses absolute or relative to a master camera.

Fisheye lenses (``geometry.lens``) come with ``load_calibration``: those cameras are in the
rig as the pinhole cameras their frames are rectified to as they are read; ``load_rig``
refuses them (the frames would not match).
* **NeRF** ``transforms.json`` (nerfstudio, Instant-NGP, the Blender scenes;
  ``edgerecon.io.calib_nerf``): OpenGL camera-to-world poses, pinhole or OPENCV cameras.

Every malformed or inconsistent input raises ``CalibrationError`` naming the file, the camera
when there is one, and the problem.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry.camera import Camera, Rig
from edgerecon.geometry.lens import CalibratedRig
from edgerecon.io._errors import check_distortion, read_json, rotation_matrix
from edgerecon.io._errors import in_file as _in_file
from edgerecon.io.calib_egoexo import egoexo_calibration, egoexo_file, is_egoexo_file
from edgerecon.io.calib_kalibr import is_kalibr_file, kalibr_calibration, kalibr_files
from edgerecon.io.calib_llff import LLFF_FILE, llff_file, read_llff
from edgerecon.io.calib_mocap import (
    easymocap_camera_names,
    easymocap_files,
    is_easymocap_file,
    is_panoptic,
    panoptic_files,
    read_easymocap,
    read_panoptic,
)
from edgerecon.io.calib_multical import is_multical, multical_calibration
from edgerecon.io.calib_nerf import is_transforms, transforms_calibration, transforms_file
from edgerecon.io.calib_toml import (
    load_toml,
    toml_calibration,
    toml_calibrations,
    toml_flavour,
)
from edgerecon.io.colmap import (
    colmap_calibration,
    find_colmap_model,
    read_colmap_rig,
    write_colmap_rig,
)
from edgerecon.io.frames import (
    IMAGE_EXTENSIONS,
    VIDEO_EXTENSIONS,
    natural_key,
    probe_image_size,
    probe_video,
)
from edgerecon.io.ply import atomic_write_text
from edgerecon.types import CalibrationError, DataError

logger = logging.getLogger(__name__)

ImageSizes = Mapping[str, tuple[int, int]] | tuple[int, int]
"""Image sizes ``(width, height)`` per camera name, or one size for every camera."""

#: Names of the calibration formats ``detect_calibration_format`` returns.
FORMATS = (
    "edgerecon",
    "openmvg",
    "opencv-xml",
    "middlebury",
    "colmap",
    "toml",
    "easymocap",
    "panoptic",
    "llff",
    "nerf",
    "kalibr",
    "egoexo",
    "multical",
)


def _size_for(image_sizes: ImageSizes | None, name: str) -> tuple[int, int] | None:
    if image_sizes is None:
        return None
    if (
        isinstance(image_sizes, tuple)
        and len(image_sizes) == 2
        and not isinstance(image_sizes[0], str)
    ):
        return (int(image_sizes[0]), int(image_sizes[1]))
    assert isinstance(image_sizes, Mapping)
    size = image_sizes.get(name)
    return None if size is None else (int(size[0]), int(size[1]))


# ============================================================================== rig JSON
def save_rig(path: str | os.PathLike[str], rig: Rig) -> Path:
    """Write ``rig`` as edgerecon rig JSON, atomically. ``json`` writes floats with ``repr``,
    which round-trips every float64 exactly."""
    return atomic_write_text(path, json.dumps(rig.to_dict(), indent=2) + "\n")


def read_rig_json(path: str | os.PathLike[str]) -> Rig:
    """Read an edgerecon rig JSON file (``save_rig``'s output)."""
    path = Path(path)
    data = read_json(path)
    if not isinstance(data, dict):
        raise CalibrationError(f"{path}: not an edgerecon rig file (top level is not an object)")
    with _in_file(path):
        for i, cam in enumerate(data.get("cameras", [])):
            if not isinstance(cam, dict):
                raise CalibrationError(f"camera #{i}: not a JSON object")
        try:
            return Rig.from_dict(data)
        except (TypeError, ValueError) as exc:
            if isinstance(exc, CalibrationError):
                raise
            raise CalibrationError(f"malformed rig file ({exc})") from None


# ============================================================================== openMVG
_OPENMVG_UNDEFINED = 4294967295  # openMVG's UndefinedIndexT


def read_openmvg_sfm_data(path: str | os.PathLike[str], *, unit: str = "m") -> Rig:
    """Read the posed views of an openMVG ``sfm_data.json`` as a rig."""
    path = Path(path)
    data = read_json(path)
    with _in_file(path):
        if not isinstance(data, dict) or "views" not in data:
            raise CalibrationError("not an openMVG sfm_data file (no 'views')")
        intrinsics = _openmvg_intrinsics(data.get("intrinsics", []))
        poses: dict[int, tuple[NDArray[np.float64], NDArray[np.float64]]] = {}
        for item in data.get("extrinsics", []):
            try:
                key = int(item["key"])
                value = item["value"]
                R = np.asarray(value["rotation"], dtype=np.float64)
                C = np.asarray(value["center"], dtype=np.float64)
            except (KeyError, TypeError, ValueError) as exc:
                raise CalibrationError(f"malformed extrinsic entry ({_describe(exc)})") from None
            poses[key] = (R, C)
        views = []
        for item in data["views"]:
            try:
                key = int(item["key"])
                view = item["value"]["ptr_wrapper"]["data"]
                id_pose = int(view["id_pose"])
                id_intrinsic = int(view["id_intrinsic"])
                filename = str(view.get("filename", ""))
            except (KeyError, TypeError, ValueError) as exc:
                raise CalibrationError(f"malformed view entry ({_describe(exc)})") from None
            views.append((key, filename, id_pose, id_intrinsic))
        stems = [Path(f).stem for _, f, _, _ in views]
        unique_stems = all(stems) and len(set(stems)) == len(stems)
        cameras = []
        for (key, filename, id_pose, id_intrinsic), stem in zip(views, stems, strict=True):
            name = stem if unique_stems else f"cam{key}"
            if id_pose == _OPENMVG_UNDEFINED or id_pose not in poses:
                logger.warning("%s: view %d (%s) has no pose; skipped", path, key, filename)
                continue
            if id_intrinsic not in intrinsics:
                raise CalibrationError(
                    f"camera {name!r}: view {key} refers to intrinsic {id_intrinsic}, "
                    "which the file does not define"
                )
            width, height, K, dist = intrinsics[id_intrinsic]
            R, C = poses[id_pose]
            if R.shape != (3, 3) or C.shape != (3,):
                raise CalibrationError(
                    f"camera {name!r}: rotation must be 3x3 and center 3-vector, got "
                    f"{R.shape} and {C.shape}"
                )
            cameras.append(
                Camera(name=name, width=width, height=height, K=K, R=R, t=-R @ C, dist=dist)
            )
        return Rig(cameras=tuple(cameras), unit=unit)


def _describe(exc: BaseException) -> str:
    if isinstance(exc, KeyError):
        return f"missing field {exc.args[0]!r}"
    return str(exc)


def _openmvg_intrinsics(
    items: list[Any],
) -> dict[int, tuple[int, int, NDArray[np.float64], NDArray[np.float64]]]:
    """Intrinsics by id. cereal writes a polymorphic type's name only at its first use;
    later entries refer to it by ``polymorphic_id`` (the first one has bit 31 set)."""
    names: dict[int, str] = {}
    out = {}
    for item in items:
        try:
            key = int(item["key"])
            value = item["value"]
            pid = int(value["polymorphic_id"]) & 0x7FFFFFFF
            if "polymorphic_name" in value:
                names[pid] = str(value["polymorphic_name"])
            model = names.get(pid)
            if model is None:
                raise CalibrationError(f"intrinsic {key}: unknown polymorphic id {pid}")
            d = value["ptr_wrapper"]["data"]
            width, height = int(d["width"]), int(d["height"])
            f = float(d["focal_length"])
            cx, cy = (float(v) for v in d["principal_point"])
            dist = np.zeros(5)
            if model == "pinhole":
                pass
            elif model == "pinhole_radial_k1":
                dist[0] = float(d["disto_k1"][0])
            elif model == "pinhole_radial_k3":
                k1, k2, k3 = (float(v) for v in d["disto_k3"])
                dist[:] = (k1, k2, 0.0, 0.0, k3)
            elif model == "pinhole_brown_t2":
                k1, k2, k3, t1, t2 = (float(v) for v in d["disto_t2"])
                dist[:] = (k1, k2, t1, t2, k3)
            else:
                raise CalibrationError(
                    f"intrinsic {key}: unsupported openMVG camera model {model!r} (supported: "
                    "pinhole, pinhole_radial_k1, pinhole_radial_k3, pinhole_brown_t2)"
                )
        except (KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, CalibrationError):
                raise
            raise CalibrationError(f"malformed intrinsic entry ({_describe(exc)})") from None
        K = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
        out[key] = (width, height, K, dist)
    return out


# ============================================================================== OpenCV XML
def read_opencv_camera_xml(
    path: str | os.PathLike[str], *, name: str, image_size: tuple[int, int] | None
) -> Camera:
    """Read one camera from an OpenCV FileStorage file (utrecht4cam's ``config.xml``).

    ``image_size`` (width, height) is required: these files do not record it.
    """
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"camera {name!r}: calibration file not found: {path}")
    if image_size is None:
        raise CalibrationError(
            f"camera {name!r}: {path} has no image size and none was found: give image_sizes "
            "or put the camera's video/images next to it"
        )
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:
        # OpenCV's parser errors surface as SystemError wrapping a cv2.error.
        cause = exc.__cause__ or exc.__context__ or exc
        detail = str(cause).strip().splitlines()[-1] if str(cause).strip() else type(cause).__name__
        raise CalibrationError(
            f"camera {name!r}: {path} is not a readable OpenCV FileStorage file ({detail})"
        ) from None
    try:
        if not fs.isOpened():
            raise CalibrationError(f"camera {name!r}: cannot open {path} as OpenCV FileStorage")

        def matrix(key: str, required: bool = True) -> NDArray[np.float64] | None:
            node = fs.getNode(key)
            if node.empty():
                if required:
                    raise CalibrationError(f"camera {name!r}: {path} has no {key!r} entry")
                return None
            mat = node.mat()
            if mat is None:
                raise CalibrationError(f"camera {name!r}: {path}: {key!r} is not a matrix")
            return np.asarray(mat, dtype=np.float64)

        K = matrix("CameraMatrix")
        dist = matrix("DistortionCoeffs", required=False)
        rot = matrix("Rotation")
        trans = matrix("Translation")
    finally:
        fs.release()
    assert K is not None and rot is not None and trans is not None
    with _in_file(path):
        where = f"camera {name!r}"
        return Camera(
            name=name,
            width=image_size[0],
            height=image_size[1],
            K=K,
            R=rotation_matrix(rot, where),
            t=trans.ravel(),
            dist=np.zeros(5) if dist is None else check_distortion(dist, where),
        )


def opencv_xml_cameras(root: str | os.PathLike[str]) -> list[tuple[str, Path]]:
    """(camera name, config file) of a utrecht4cam-style folder: sub-folders holding a
    ``config.xml``, named after the folder, in natural order. Empty if there are none."""
    root = Path(root)
    if not root.is_dir():
        return []
    found = [
        (d.name, d / "config.xml")
        for d in root.iterdir()
        if d.is_dir() and (d / "config.xml").is_file()
    ]
    return sorted(found, key=lambda item: natural_key(item[0]))


def camera_folder_frame_size(folder: Path, camera: str) -> tuple[int, int] | None:
    """Frame size of a camera folder from ``video.avi``, another video or an image in it."""
    candidates = [folder / "video.avi"] + sorted(
        (p for p in folder.iterdir() if p.suffix.lower() in VIDEO_EXTENSIONS),
        key=lambda p: natural_key(p.name),
    )
    for video in candidates:
        if video.is_file():
            info = probe_video(video, camera)
            return (info.width, info.height)
    images = sorted(
        (p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS),
        key=lambda p: natural_key(p.name),
    )
    if images:
        return probe_image_size(images[0])
    return None


def read_opencv_xml_rig(
    root: str | os.PathLike[str],
    image_sizes: ImageSizes | None = None,
    *,
    unit: str = "mm",
    up: tuple[float, float, float] = (0.0, 0.0, -1.0),
) -> Rig:
    """Read a utrecht4cam-style folder: ``camN/config.xml`` per camera.

    Image sizes come from ``image_sizes`` or from each camera folder's ``video.avi`` (or any
    video / image there). Defaults to utrecht4cam's unit (mm) and up direction (-Z).
    """
    root = Path(root)
    entries = opencv_xml_cameras(root)
    if not entries:
        raise CalibrationError(f"{root}: no camera folders with a config.xml")
    cameras = []
    for name, config in entries:
        size = _size_for(image_sizes, name)
        if size is None:
            try:
                size = camera_folder_frame_size(config.parent, name)
            except DataError as exc:
                raise CalibrationError(
                    f"camera {name!r}: {config} has no image size and the frames next to it "
                    f"cannot tell it ({exc})"
                ) from None
        cameras.append(read_opencv_camera_xml(config, name=name, image_size=size))
    with _in_file(root):
        return Rig(cameras=tuple(cameras), unit=unit, up=up)


# ============================================================================== Middlebury
def read_middlebury_par(
    path: str | os.PathLike[str], image_sizes: ImageSizes | None = None, *, unit: str = "m"
) -> Rig:
    """Read a Middlebury multi-view ``*_par.txt`` file; image sizes come from the images
    next to it unless ``image_sizes`` gives them."""
    path = Path(path)
    try:
        lines = [ln.split() for ln in path.read_text(encoding="utf-8").splitlines()]
    except FileNotFoundError:
        raise CalibrationError(f"calibration file not found: {path}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"{path}: cannot read ({exc})") from None
    lines = [ln for ln in lines if ln]
    if not lines:
        raise CalibrationError(f"{path}: empty Middlebury parameter file")
    try:
        declared = int(lines[0][0])
    except ValueError:
        raise CalibrationError(
            f"{path}: first line must be the number of images, got {' '.join(lines[0])!r}"
        ) from None
    rows = lines[1:]
    if len(rows) != declared:
        raise CalibrationError(f"{path}: declares {declared} images but lists {len(rows)}")
    cameras = []
    with _in_file(path):
        for lineno, row in enumerate(rows, start=2):
            if len(row) != 22:
                raise CalibrationError(
                    f"line {lineno}: expected 'name' + 21 numbers (K, R, t), got {len(row)} fields"
                )
            image_name = row[0]
            name = Path(image_name).stem
            try:
                values = np.array([float(v) for v in row[1:]])
            except ValueError as exc:
                raise CalibrationError(f"camera {name!r} (line {lineno}): {exc}") from None
            size = _size_for(image_sizes, name)
            if size is None:
                image_path = path.parent / image_name
                try:
                    size = probe_image_size(image_path)
                except DataError as exc:
                    raise CalibrationError(
                        f"camera {name!r}: image size unknown ({exc}); pass image_sizes"
                    ) from None
            cameras.append(
                Camera(
                    name=name,
                    width=size[0],
                    height=size[1],
                    K=values[:9],
                    R=values[9:18],
                    t=values[18:21],
                )
            )
        return Rig(cameras=tuple(cameras), unit=unit)


def middlebury_par_files(root: str | os.PathLike[str]) -> list[Path]:
    root = Path(root)
    return sorted(root.glob("*_par.txt")) if root.is_dir() else []


# ============================================================================== COLMAP
def read_colmap_text(path: str | os.PathLike[str], *, unit: str | None = None) -> Rig:
    """Read the rig of a COLMAP model (a folder with ``cameras`` + ``images`` as ``.txt`` or
    ``.bin``; many images per camera are grouped, see ``edgerecon.io.colmap``).

    ``unit`` overrides the unit recorded by edgerecon's writer (default "m").
    """
    return read_colmap_rig(path, unit=unit)


def write_colmap_text(path: str | os.PathLike[str], rig: Rig) -> Path:
    """Write ``rig`` as a COLMAP text model (``cameras.txt``, ``images.txt``, empty
    ``points3D.txt``) into the folder ``path``. Each camera becomes one COLMAP camera of the
    simplest model that holds it exactly (PINHOLE, OPENCV or FULL_OPENCV) and one image
    named ``<camera name>.png``."""
    return write_colmap_rig(path, rig, binary=False)


# ============================================================================== detection
def detect_calibration_format(path: str | os.PathLike[str]) -> str:
    """Which of ``FORMATS`` a calibration file or folder is in (``CalibrationError`` if none).

    Folders: ``rig.json`` > COLMAP (``cameras`` + ``images`` .txt or .bin, also under
    ``sparse/`` or ``sparse/0``) > one calibration ``*.toml`` (also under ``calibration/``) >
    ``*_par.txt`` > ``camN/config.xml`` > ``sfm_data*.json`` > EasyMocap's ``intri.yml`` +
    ``extri.yml`` > one Kalibr ``*camchain*.yaml`` > LLFF's ``poses_bounds.npy`` > one Panoptic
    ``calibration_*.json`` > a NeRF
    ``transforms.json`` (or ``transforms_train.json``).
    """
    path = Path(path)
    if not path.exists():
        raise CalibrationError(f"calibration not found: {path}")
    if path.is_dir():
        return _detect_in_folder(path)[0]
    name = path.name.lower()
    if path.name == LLFF_FILE:
        return "llff"
    if name.endswith("_par.txt"):
        return "middlebury"
    if name in ("cameras.txt", "images.txt", "cameras.bin", "images.bin"):
        return "colmap"
    if path.suffix.lower() in (".yml", ".yaml") and (
        name in ("intri.yml", "extri.yml") or is_easymocap_file(path)
    ):
        return "easymocap"
    if path.suffix.lower() in (".yml", ".yaml") and is_kalibr_file(path):
        return "kalibr"
    if path.suffix.lower() in (".xml", ".yml", ".yaml"):
        return "opencv-xml"
    if path.suffix.lower() == ".csv":
        if is_egoexo_file(path):
            return "egoexo"
        raise CalibrationError(f"{path}: CSV file is not an Ego-Exo4D gopro_calibs.csv")
    if path.suffix.lower() == ".toml":
        if toml_flavour(load_toml(path)) is None:
            raise CalibrationError(
                f"{path}: TOML file is not an anipose / Pose2Sim / caliscope calibration"
            )
        return "toml"
    if path.suffix.lower() == ".json":
        data = read_json(path)
        if isinstance(data, dict) and data.get("format") == "edgerecon-rig":
            return "edgerecon"
        if isinstance(data, dict) and "views" in data and "sfm_data_version" in data:
            return "openmvg"
        if is_panoptic(data):
            return "panoptic"
        if is_transforms(data):
            return "nerf"
        if is_multical(data):
            return "multical"
        raise CalibrationError(
            f"{path}: JSON file is neither an edgerecon rig (format: edgerecon-rig), an "
            "openMVG sfm_data file, a Panoptic calibration, a NeRF transforms.json nor a "
            "multical calibration"
        )
    raise CalibrationError(f"{path}: unknown calibration format (supported: {', '.join(FORMATS)})")


def _one(path: Path | None) -> list[Path]:
    return [] if path is None else [path]


def _easymocap_intri(folder: Path) -> Path | None:
    files = easymocap_files(folder)
    return None if files is None else files[0]


def _multical_files(folder: Path) -> list[Path]:
    path = folder / "calibration.json"
    return [path] if path.is_file() and is_multical(read_json(path)) else []


#: What a calibration folder may hold, in the order ``_detect_in_folder`` looks: (format,
#: what it is called in messages, the files of it in a folder).
_FOLDER_FORMATS: tuple[tuple[str, str, Callable[[Path], list[Path]]], ...] = (
    (
        "edgerecon",
        "rig.json",
        lambda f: _one(f / "rig.json" if (f / "rig.json").is_file() else None),
    ),
    ("colmap", "a COLMAP model", lambda f: _one(find_colmap_model(f))),
    ("toml", "an anipose / Pose2Sim / caliscope *.toml", toml_calibrations),
    ("middlebury", "*_par.txt", middlebury_par_files),
    ("opencv-xml", "camN/config.xml", lambda f: [f] if opencv_xml_cameras(f) else []),
    ("openmvg", "sfm_data*.json", lambda f: sorted(f.glob("sfm_data*.json"))),
    ("easymocap", "EasyMocap's intri.yml + extri.yml", lambda f: _one(_easymocap_intri(f))),
    ("kalibr", "a Kalibr camchain*.yaml", kalibr_files),
    ("llff", "LLFF's poses_bounds.npy", lambda f: _one(llff_file(f))),
    ("panoptic", "a Panoptic calibration_*.json", panoptic_files),
    ("nerf", "a NeRF transforms.json", lambda f: _one(transforms_file(f))),
    ("egoexo", "an Ego-Exo4D gopro_calibs.csv", lambda f: _one(egoexo_file(f))),
    ("multical", "a multical calibration.json", _multical_files),
)


def _detect_in_folder(folder: Path) -> tuple[str, Path]:
    for fmt, what, find in _FOLDER_FORMATS:
        found = find(folder)
        if len(found) > 1:
            raise CalibrationError(
                f"{folder}: {len(found)} files of {what} ({', '.join(p.name for p in found)}); "
                "pass one of them"
            )
        if found:
            return fmt, found[0]
    raise CalibrationError(
        f"{folder}: no calibration found (looked for "
        + ", ".join(what for _, what, _ in _FOLDER_FORMATS)
        + ")"
    )


def load_rig(path: str | os.PathLike[str], image_sizes: ImageSizes | None = None) -> Rig:
    """Read a rig from any supported calibration file or folder (format auto-detected).

    ``image_sizes`` ((width, height) per camera name, or one for all) is needed only by
    formats that do not store sizes and have no frames next to them (OpenCV XML, EasyMocap
    without ``H_`` / ``W_``); for other formats it is checked against the stored sizes.
    A calibration with fisheye cameras raises: its frames must be rectified, which
    ``edgerecon import`` sets up (``load_calibration`` gives the lenses).
    """
    return load_calibration(path, image_sizes).pinhole_only(path)


def load_calibration(
    path: str | os.PathLike[str], image_sizes: ImageSizes | None = None
) -> CalibratedRig:
    """``load_rig``'s rig with the fisheye lenses of the formats that record them (NeRF
    ``OPENCV_FISHEYE``, Kalibr ``equidistant``, Ego-Exo4D): those cameras are in the rig as
    the pinhole cameras their frames are rectified to (``geometry.lens``)."""
    path = Path(path)
    fmt = detect_calibration_format(path)
    target = _detect_in_folder(path)[1] if path.is_dir() else path
    lenses: CalibratedRig | None = None
    if fmt == "edgerecon":
        rig = read_rig_json(target)
    elif fmt == "openmvg":
        rig = read_openmvg_sfm_data(target)
    elif fmt == "middlebury":
        rig = read_middlebury_par(target, image_sizes)
    elif fmt == "colmap":
        lenses = colmap_calibration(target)
    elif fmt == "toml":
        lenses = toml_calibration(target)
    elif fmt == "easymocap":
        sizes = (
            None
            if image_sizes is None
            else {n: s for n in easymocap_camera_names(target) if (s := _size_for(image_sizes, n))}
        )
        rig = read_easymocap(target, sizes)
    elif fmt == "panoptic":
        rig = read_panoptic(target)
    elif fmt == "llff":
        rig = read_llff(target)
    elif fmt == "nerf":
        lenses = transforms_calibration(target, image_sizes)
    elif fmt == "kalibr":
        lenses = kalibr_calibration(target)
    elif fmt == "egoexo":
        lenses = egoexo_calibration(target)
    elif fmt == "multical":
        lenses = multical_calibration(target)
    elif target.is_dir():
        rig = read_opencv_xml_rig(target, image_sizes)
    else:
        raise CalibrationError(
            f"{target}: a single OpenCV XML file holds one camera; pass the folder of camN/ "
            "sub-folders (or use read_opencv_camera_xml)"
        )
    cal = lenses if lenses is not None else CalibratedRig(rig=rig, lenses={})
    if image_sizes is not None and fmt not in ("middlebury", "opencv-xml", "easymocap"):
        check_image_sizes(cal.rig, image_sizes, str(target))
    return cal


def check_image_sizes(rig: Rig, image_sizes: ImageSizes, source: str) -> None:
    """Raise ``CalibrationError`` for a camera whose calibrated size differs from the one
    given (e.g. measured on its frames)."""
    for cam in rig:
        size = _size_for(image_sizes, cam.name)
        if size is not None and size != cam.size:
            raise CalibrationError(
                f"{source}: camera {cam.name!r} is calibrated for {cam.width}x{cam.height} "
                f"but its frames are {size[0]}x{size[1]}"
            )
