"""TOML calibrations of the common multi-camera capture tools: anipose / aniposelib,
Pose2Sim and caliscope (``camera_array.toml``).

All three write OpenCV cameras, one table per camera:

* **anipose / aniposelib** ``calibration.toml``: ``[cam_0]`` ... with ``name``, ``size``
  ``[width, height]``, ``matrix`` (3x3 K), ``distortions`` (k1 k2 p1 p2 k3), ``rotation``
  (Rodrigues vector) and ``translation``, world->camera; a ``[metadata]`` table. The length
  unit is that of the calibration board (often millimetres) and is not recorded.
* **Pose2Sim** ``Calib*.toml``: the same layout (sizes may be floats, 4 distortion
  coefficients) plus ``fisheye = false``; metres.
* **caliscope** ``camera_array.toml``: ``[cameras.0]`` ... (older versions: ``[cam_0]`` with
  ``port``) with ``cam_id``, ``size``, ``matrix``, ``distortions``, ``rotation`` (a 3x3
  matrix, or a Rodrigues vector in some versions), ``translation`` (metres) and ``ignore``.
  Cameras are named ``cam_<id>`` (caliscope's video names).

``rotation`` / ``translation`` are world->camera (``X_cam = R X + t``, OpenCV's
``projectPoints`` convention), edgerecon's own. Principal points follow OpenCV's pixel-centre
convention, as edgerecon's. Cameras marked ``ignore = true`` or without extrinsics are
skipped with a warning. aniposelib's fisheye cameras (``fisheye = true``, ``distortions``
k1..k4 of OpenCV's fisheye model) come with their lenses (``toml_calibration``): ``edgerecon
import`` rectifies their frames to pinhole cameras as they are read (``geometry.lens``).

Units: caliscope and Pose2Sim write metres. anipose does not record its unit, so it is
guessed from the rig's size (``guess_unit``: cameras 0.05-50 units from the point they look
at -> metres, 50-100,000 -> millimetres) unless ``unit=`` is given, and the guess is logged.
"""

from __future__ import annotations

import logging
import os
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from edgerecon.geometry.camera import Camera, Rig
from edgerecon.geometry.lens import CalibratedRig, FisheyeLens, calibrated_rig, lens_camera
from edgerecon.io._errors import in_file, rotation_matrix
from edgerecon.types import CalibrationError

logger = logging.getLogger(__name__)

#: Flavours ``toml_flavour`` recognises.
FLAVOURS = ("anipose", "pose2sim", "caliscope")
_CAMERA_KEYS = ("matrix", "distortions", "rotation", "translation", "size")


def load_toml(path: str | os.PathLike[str]) -> dict[str, Any]:
    path = Path(path)
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise CalibrationError(f"calibration file not found: {path}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"{path}: not valid TOML ({exc})") from None


def _camera_tables(data: dict[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    """(table key, table) of each camera, in the file's order."""
    if isinstance(data.get("cameras"), dict):
        # caliscope >= 0.5: [cameras.0], [cameras.1], ...
        return [(str(k), v) for k, v in data["cameras"].items() if isinstance(v, dict)]
    return [
        (k, v)
        for k, v in data.items()
        if isinstance(v, dict) and k != "metadata" and ("matrix" in v or "size" in v)
    ]


def toml_flavour(data: dict[str, Any]) -> str | None:
    """Which tool wrote a parsed TOML calibration, or None when it is not one."""
    tables = _camera_tables(data)
    if not tables or not all("matrix" in t for _, t in tables):
        return None
    if isinstance(data.get("cameras"), dict) or any(
        "port" in t or "cam_id" in t or "ignore" in t for _, t in tables
    ):
        return "caliscope"
    if any(t.get("fisheye") is False for _, t in tables):
        return "pose2sim"  # Pose2Sim writes ``fisheye = false``; aniposelib's fisheye ``true``
    return "anipose"


def is_toml_calibration(path: str | os.PathLike[str]) -> bool:
    try:
        return toml_flavour(load_toml(path)) is not None
    except CalibrationError:
        return False


def guess_unit(rig: Rig) -> str | None:
    """ "m" or "mm" from the rig's size (distance of the cameras from the point their axes
    converge on), None when the size fits neither."""
    from edgerecon.runtime.config import median_camera_distance

    d = median_camera_distance(rig)
    if 0.05 <= d <= 50:
        return "m"
    if 50 < d <= 1e5:
        return "mm"
    return None


def read_toml_calibration(
    path: str | os.PathLike[str],
    *,
    unit: str | None = None,
    up: tuple[float, float, float] | None = None,
) -> Rig:
    """Read an anipose / Pose2Sim / caliscope TOML calibration as a rig (see the module
    docstring for the formats and units). Fisheye cameras raise (``toml_calibration`` gives
    their lenses)."""
    return toml_calibration(path, unit=unit, up=up).pinhole_only(path)


def toml_calibration(
    path: str | os.PathLike[str],
    *,
    unit: str | None = None,
    up: tuple[float, float, float] | None = None,
) -> CalibratedRig:
    """``read_toml_calibration``'s rig with the lenses of its ``fisheye = true`` cameras
    (aniposelib's fisheye cameras: OpenCV's fisheye model, in the rig as the pinhole cameras
    their frames are rectified to)."""
    path = Path(path)
    data = load_toml(path)
    flavour = toml_flavour(data)
    if flavour is None:
        raise CalibrationError(
            f"{path}: not an anipose / Pose2Sim / caliscope calibration (no camera tables "
            "with 'matrix', 'distortions', 'rotation', 'translation', 'size')"
        )
    made: list[tuple[Camera, FisheyeLens | None]] = []
    for key, table in _camera_tables(data):
        name = _camera_name(flavour, key, table)
        if table.get("ignore") is True:
            logger.warning("%s: camera %r is marked ignore = true; skipped", path, name)
            continue
        if table.get("rotation") is None or table.get("translation") is None:
            logger.warning("%s: camera %r has no extrinsics (not calibrated); skipped", path, name)
            continue
        made.append(_camera(path, name, table))
    with in_file(path):
        cal = calibrated_rig(made, unit=unit or "m", up=up or (0.0, 0.0, 1.0))
    rig = cal.rig
    if unit is None and flavour == "anipose":
        guessed = guess_unit(rig)
        if guessed is None:
            logger.warning(
                "%s: anipose calibrations do not record their unit and this rig's size fits "
                "neither metres nor millimetres; assuming metres (give the unit explicitly)",
                path,
            )
        else:
            logger.info("%s: anipose calibration, unit guessed from its size: %s", path, guessed)
            rig = Rig(cameras=rig.cameras, unit=guessed, up=rig.up)
    return CalibratedRig(rig=rig, lenses=cal.lenses)


def _camera_name(flavour: str, key: str, table: dict[str, Any]) -> str:
    if flavour == "caliscope":
        for field in ("cam_id", "port"):
            if isinstance(table.get(field), int):
                return f"cam_{table[field]}"
        return key if key.startswith("cam") else f"cam_{key}"
    name = table.get("name")
    return str(name) if name not in (None, "") else key


def _camera(path: Path, name: str, table: dict[str, Any]) -> tuple[Camera, FisheyeLens | None]:
    """One camera table: the camera, and its lens when it is a fisheye one (the camera is
    then the pinhole camera its frames are rectified to)."""
    where = f"{path}: camera {name!r}"
    missing = [k for k in _CAMERA_KEYS if k not in table and k != "distortions"]
    if missing:
        raise CalibrationError(f"{where}: missing {', '.join(missing)}")
    fisheye = table.get("fisheye") is True
    try:
        size = [float(v) for v in table["size"]]
        K = np.asarray(table["matrix"], np.float64)
        dist = np.asarray(table.get("distortions", [0.0] * (4 if fisheye else 5)), np.float64)
        dist = dist.ravel()
        rot = np.asarray(table["rotation"], np.float64)
        t = np.asarray(table["translation"], np.float64).ravel()
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"{where}: malformed values ({exc})") from None
    if len(size) != 2 or any(v != int(v) or v <= 0 for v in size):
        raise CalibrationError(f"{where}: size must be [width, height] in pixels, got {size}")
    R = rotation_matrix(rot, where)
    if fisheye and dist.size != 4:
        raise CalibrationError(
            f"{where}: a fisheye camera has 4 distortion coefficients (k1..k4), got {dist.size}"
        )
    if not fisheye and dist.size > 5:
        raise CalibrationError(
            f"{where}: {dist.size} distortion coefficients; edgerecon supports OpenCV's "
            "k1 k2 p1 p2 k3"
        )
    with in_file(path):
        return lens_camera(name, int(size[0]), int(size[1]), K, R, t, dist, fisheye=fisheye)


def toml_calibrations(folder: str | os.PathLike[str]) -> list[Path]:
    """TOML calibration files directly in ``folder`` (anipose's ``calibration.toml``,
    Pose2Sim's ``Calib*.toml`` in ``calibration/``, caliscope's ``camera_array.toml``)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    found = []
    for sub in (folder, folder / "calibration"):
        if sub.is_dir():
            found += [p for p in sorted(sub.glob("*.toml")) if is_toml_calibration(p)]
    return found


__all__ = [
    "FLAVOURS",
    "guess_unit",
    "is_toml_calibration",
    "read_toml_calibration",
    "toml_calibration",
    "toml_calibrations",
    "toml_flavour",
]
