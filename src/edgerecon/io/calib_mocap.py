"""Calibrations of the multi-view people-capture tools and datasets: EasyMocap and the CMU
Panoptic Studio.

* **EasyMocap** (also ZJU-MoCap and the datasets converted to its layout): two OpenCV
  FileStorage YAML files side by side. ``intri.yml``: ``names`` (a list of camera names),
  ``K_<name>`` (3x3) and ``dist_<name>`` (k1 k2 p1 p2 [k3]; ``D_<name>`` in some files),
  optionally ``H_<name>`` / ``W_<name>`` (the image size). ``extri.yml``: ``names``,
  ``R_<name>`` (a Rodrigues vector), ``Rot_<name>`` (the same rotation as a 3x3 matrix) and
  ``T_<name>`` (3x1), world->camera (``X_cam = R X + T``), in metres (EasyMocap's rule).
  Without ``H_`` / ``W_`` the size comes from ``image_sizes`` or from the camera's frames in
  EasyMocap's layout next to the files (``videos/<name>.mp4``, ``images/<name>/``). The up
  direction is not recorded (the import estimates it from the cameras' horizons).
* **CMU Panoptic Studio** ``calibration_<sequence>.json``: ``cameras``, a list of ``name``
  (``"00_03"``: panel 00 is the HD cameras, 01-20 the VGA ones, 50 the Kinects), ``type``,
  ``resolution`` [width, height], ``K`` (3x3), ``distCoef`` (k1 k2 p1 p2 k3), ``R`` (3x3) and
  ``t`` (3x1), world->camera, in centimetres (other tools write the format in metres or
  millimetres: ``panoptic_unit`` reads the rig's size); the world's y axis points down (up
  is -y; ``edgerecon import`` checks it against the cameras' horizons). The
  file lists every camera of the dome (31 HD, 480 VGA, 10 Kinect): ``edgerecon import``
  keeps those whose frames it is given (``hdVideos/hd_00_03.mp4`` is camera ``00_03``).

Both use OpenCV's pinhole model and pixel-centre convention, as edgerecon does. A malformed or
inconsistent file raises ``CalibrationError`` naming the file, the camera and the problem.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Collection, Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry.camera import Camera, Rig
from edgerecon.io._errors import check_distortion, in_file, read_json, rotation_matrix
from edgerecon.io.frames import VIDEO_EXTENSIONS, probe_video
from edgerecon.types import CalibrationError

logger = logging.getLogger(__name__)

#: File names of an EasyMocap calibration.
EASYMOCAP_FILES = ("intri.yml", "extri.yml")


# ============================================================================== EasyMocap
def easymocap_files(path: str | os.PathLike[str]) -> tuple[Path, Path] | None:
    """(intri.yml, extri.yml) of an EasyMocap calibration given as its folder or as either
    file; None when ``path`` is not one."""
    path = Path(path)
    folder = path if path.is_dir() else path.parent
    if not path.is_dir() and path.name.lower() not in EASYMOCAP_FILES:
        return None
    intri, extri = folder / EASYMOCAP_FILES[0], folder / EASYMOCAP_FILES[1]
    if intri.is_file() and extri.is_file():
        return intri, extri
    if not path.is_dir():
        missing = extri if path.name.lower() == EASYMOCAP_FILES[0] else intri
        raise CalibrationError(
            f"{path}: an EasyMocap calibration needs both intri.yml and extri.yml; "
            f"{missing} is missing"
        )
    return None


class _Storage:
    """One OpenCV FileStorage file, read with errors that name it."""

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            self.fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        except (cv2.error, SystemError) as exc:
            cause = exc.__cause__ or exc.__context__ or exc
            lines = str(cause).strip().splitlines()
            raise CalibrationError(
                f"{path}: not a readable OpenCV FileStorage file "
                f"({lines[-1] if lines else type(cause).__name__})"
            ) from None
        if not self.fs.isOpened():
            raise CalibrationError(f"{path}: cannot open it as an OpenCV FileStorage file")

    def names(self) -> list[str]:
        node = self.fs.getNode("names")
        if node.empty() or not node.isSeq():
            raise CalibrationError(f"{self.path}: no 'names' list of cameras")
        out = []
        for i in range(node.size()):
            item = node.at(i)
            text = item.string() if item.isString() else ""
            if not text and (item.isReal() or item.isInt()):
                value = item.real()
                text = str(int(value)) if float(value).is_integer() else str(value)
            if text and text != "none":
                out.append(text)
        if not out:
            raise CalibrationError(f"{self.path}: the 'names' list is empty")
        return out

    def matrix(self, key: str) -> NDArray[np.float64] | None:
        node = self.fs.getNode(key)
        if node.empty():
            return None
        mat = node.mat()
        if mat is None:
            raise CalibrationError(f"{self.path}: {key!r} is not an OpenCV matrix")
        return np.asarray(mat, dtype=np.float64)

    def integer(self, key: str) -> int | None:
        node = self.fs.getNode(key)
        if node.empty() or not (node.isInt() or node.isReal()):
            return None
        return int(node.real())

    def release(self) -> None:
        self.fs.release()


def is_easymocap_file(path: str | os.PathLike[str]) -> bool:
    """Whether a YAML file looks like EasyMocap's (a ``names`` list and ``K_`` / ``R_``
    entries of its first camera), whatever its name."""
    try:
        fs = _Storage(Path(path))
    except CalibrationError:
        return False
    try:
        names = fs.names()
        return any(not fs.fs.getNode(f"{k}_{names[0]}").empty() for k in ("K", "R", "Rot"))
    except CalibrationError:
        return False
    finally:
        fs.release()


def easymocap_camera_names(path: str | os.PathLike[str]) -> list[str]:
    """The cameras an EasyMocap calibration lists (``intri.yml``'s ``names``)."""
    files = easymocap_files(path)
    if files is None:
        raise CalibrationError(f"{path}: not an EasyMocap calibration (intri.yml + extri.yml)")
    fs = _Storage(files[0])
    try:
        return fs.names()
    finally:
        fs.release()


def _frame_size_nearby(folder: Path, name: str) -> tuple[int, int] | None:
    """The size of camera ``name``'s frames in EasyMocap's layout under ``folder``
    (``videos/<name>.*``, ``images/<name>/*``), if there are any."""
    from edgerecon.io.calibration import camera_folder_frame_size  # (imports this module)

    videos = folder / "videos"
    if videos.is_dir():
        for p in sorted(videos.iterdir()):
            if p.stem == name and p.suffix.lower() in VIDEO_EXTENSIONS:
                info = probe_video(p, camera=name)
                return (info.width, info.height)
    images = folder / "images" / name
    return camera_folder_frame_size(images, name) if images.is_dir() else None


def read_easymocap(
    path: str | os.PathLike[str],
    image_sizes: Mapping[str, tuple[int, int]] | None = None,
    *,
    only: Collection[str] | None = None,
) -> Rig:
    """Read an EasyMocap calibration (its folder, ``intri.yml`` or ``extri.yml``); see the
    module docstring. ``image_sizes``: (width, height) per camera, used for cameras whose
    ``intri.yml`` records no ``H_`` / ``W_``. ``only``: read these cameras alone (in the
    file's order)."""
    files = easymocap_files(path)
    if files is None:
        raise CalibrationError(f"{path}: not an EasyMocap calibration (intri.yml + extri.yml)")
    intri_path, extri_path = files
    intri, extri = _Storage(intri_path), _Storage(extri_path)
    try:
        names = intri.names()
        in_extri = set(extri.names())
        cameras = []
        if only is not None:
            unknown = sorted(set(only) - set(names))
            if unknown:
                raise CalibrationError(f"{intri_path}: no cameras {unknown} (cameras: {names})")
            names = [n for n in names if n in only]
        for name in names:
            if name not in in_extri:
                raise CalibrationError(f"{extri_path}: camera {name!r} of intri.yml is not listed")
            cameras.append(_easymocap_camera(name, intri, extri, image_sizes))
    finally:
        intri.release()
        extri.release()
    with in_file(intri_path.parent):
        return Rig(cameras=tuple(cameras), unit="m")


def _easymocap_camera(
    name: str,
    intri: _Storage,
    extri: _Storage,
    image_sizes: Mapping[str, tuple[int, int]] | None,
) -> Camera:
    K = intri.matrix(f"K_{name}")
    if K is None:
        raise CalibrationError(f"{intri.path}: camera {name!r} has no K_{name}")
    dist = intri.matrix(f"dist_{name}")
    if dist is None:
        dist = intri.matrix(f"D_{name}")
    where = f"{intri.path}: camera {name!r}: dist_{name}"
    dist = np.zeros(5) if dist is None else check_distortion(dist, where)
    rot = extri.matrix(f"Rot_{name}")
    if rot is None:
        rot = extri.matrix(f"R_{name}")
    T = extri.matrix(f"T_{name}")
    if rot is None or T is None:
        raise CalibrationError(
            f"{extri.path}: camera {name!r} needs R_{name} (or Rot_{name}) and T_{name}"
        )
    R = rotation_matrix(rot, f"{extri.path}: camera {name!r}")
    if T.size != 3:
        raise CalibrationError(f"{extri.path}: camera {name!r}: T_{name} must have 3 values")
    h, w = intri.integer(f"H_{name}"), intri.integer(f"W_{name}")
    size = (w, h) if h is not None and w is not None and h > 0 and w > 0 else None
    if size is None and image_sizes is not None:
        size = image_sizes.get(name)
    if size is None:
        size = _frame_size_nearby(intri.path.parent, name)
    if size is None:
        raise CalibrationError(
            f"{intri.path}: camera {name!r} has no image size (no H_{name} / W_{name}) and no "
            f"frames were found for it (videos/{name}.mp4 or images/{name}/ next to the file); "
            "import it with its frames"
        )
    with in_file(intri.path):
        return Camera(
            name=name,
            width=int(size[0]),
            height=int(size[1]),
            K=K,
            R=R,
            t=T.ravel(),
            dist=dist,
        )


# ============================================================================== Panoptic
def is_panoptic(data: Any) -> bool:
    """Whether parsed JSON is a Panoptic Studio calibration."""
    if not isinstance(data, dict) or not isinstance(data.get("cameras"), list):
        return False
    cams = data["cameras"]
    keys = ("K", "distCoef", "R", "t")
    return bool(cams) and all(isinstance(c, dict) and all(k in c for k in keys) for c in cams)


def panoptic_files(folder: str | os.PathLike[str]) -> list[Path]:
    """The Panoptic calibrations in a folder (``calibration_*.json``)."""
    folder = Path(folder)
    return sorted(folder.glob("calibration_*.json")) if folder.is_dir() else []


def _panoptic_name(cam: dict[str, Any], k: int) -> str:
    if isinstance(cam.get("name"), str) and cam["name"]:
        return str(cam["name"])
    if "panel" in cam and "node" in cam:
        return f"{int(cam['panel']):02d}_{int(cam['node']):02d}"
    return f"cam{k}"


def read_panoptic(path: str | os.PathLike[str]) -> Rig:
    """Read a CMU Panoptic Studio ``calibration_<sequence>.json`` (every camera it lists;
    see the module docstring): unit "cm", up (0, -1, 0)."""
    path = Path(path)
    data = read_json(path)
    if not is_panoptic(data):
        raise CalibrationError(
            f"{path}: not a Panoptic calibration (a 'cameras' list with K, distCoef, R, t)"
        )
    cameras = []
    for k, cam in enumerate(data["cameras"]):
        name = _panoptic_name(cam, k)
        with in_file(path):
            try:
                res = cam.get("resolution")
                if not (isinstance(res, list | tuple) and len(res) == 2):
                    raise ValueError("'resolution' must be [width, height]")
                dist = check_distortion(cam["distCoef"], f"camera {name!r}: distCoef")
                t = np.asarray(cam["t"], np.float64).ravel()
                if t.size != 3:
                    raise ValueError(f"t must have 3 values, got {t.size}")
                camera = Camera(
                    name=name,
                    width=int(res[0]),
                    height=int(res[1]),
                    K=np.asarray(cam["K"], np.float64),
                    R=np.asarray(cam["R"], np.float64),
                    t=t,
                    dist=dist,
                )
            except (TypeError, ValueError) as exc:
                raise CalibrationError(f"camera {name!r}: {exc}") from None
        cameras.append(camera)
    with in_file(path):
        rig = Rig(cameras=tuple(cameras), unit="cm", up=(0.0, -1.0, 0.0))
    unit = panoptic_unit(rig)
    if unit != "cm":
        logger.info(
            "%s: the cameras are too %s the scene for centimetres: read as %s (Panoptic's "
            "own files are in centimetres)",
            path,
            "near" if unit == "m" else "far from",
            unit,
        )
    return dataclasses.replace(rig, unit=unit)


def panoptic_unit(rig: Rig) -> str:
    """The unit of a calibration in Panoptic's format: centimetres (the Panoptic Studio's),
    unless the cameras' distance from the scene says otherwise (other tools write the format
    too): under 20 units "m", over 3000 "mm"."""
    from edgerecon.runtime.config import median_camera_distance

    d = median_camera_distance(rig)
    return "m" if d < 20 else "mm" if d > 3000 else "cm"
