"""Ego-Exo4D's exocentric cameras: ``trajectory/gopro_calibs.csv`` of a take.

Ego-Exo4D films each take with four to five static GoPros around the scene (plus a worn Aria
camera, which is not a static camera and is left out) and calibrates them with Project Aria's
Machine Perception Services: one CSV row per GoPro with

* ``cam_uid`` (``cam01`` ... or ``gp01`` ...: the videos are
  ``frame_aligned_videos/<cam_uid>.mp4``);
* ``tx_world_cam ty_world_cam tz_world_cam`` and ``qx_world_cam qy_world_cam qz_world_cam
  qw_world_cam``: the camera's pose in the world (camera -> world; camera axes x right, y
  down, z forward), metres;
* ``image_width image_height`` (the native 4K video's) and ``intrinsics_type``
  ``KANNALABRANDTK3`` with ``intrinsics_0..7`` = fx, fy, cx, cy, k1, k2, k3, k4: OpenCV's
  fisheye model (``geometry.lens``): ``edgerecon import`` rectifies the frames to pinhole
  cameras as they are read, at the size of the videos it is given (the take's 448-pixel
  ``downscaled`` copies too: the lens is rescaled);
* ``quality`` (optional): 1 localised, 0 failed, -1 unknown; cameras whose localisation
  failed are left out with a warning.

The world is gravity-aligned (the import checks the up direction against the cameras'
horizons). Pixel centres are taken on integer coordinates, as OpenCV's.
"""

from __future__ import annotations

import csv
import logging
import os
from pathlib import Path

import numpy as np

from edgerecon.geometry.camera import Camera
from edgerecon.geometry.lens import CalibratedRig, FisheyeLens, calibrated_rig, lens_camera
from edgerecon.io._errors import in_file
from edgerecon.types import CalibrationError

logger = logging.getLogger(__name__)

#: The file name of a take's exocentric calibration.
EGOEXO_FILE = "gopro_calibs.csv"

_POSE = ("tx_world_cam", "ty_world_cam", "tz_world_cam")
_QUAT = ("qx_world_cam", "qy_world_cam", "qz_world_cam", "qw_world_cam")
_INTRINSICS = tuple(f"intrinsics_{k}" for k in range(8))
_REQUIRED = ("cam_uid", *_POSE, *_QUAT, "image_width", "image_height", *_INTRINSICS)


def egoexo_file(path: str | os.PathLike[str]) -> Path | None:
    """The ``gopro_calibs.csv`` of a path (the file; a take's folder or its ``trajectory``
    folder), else None."""
    path = Path(path)
    if path.is_dir():
        for candidate in (path / EGOEXO_FILE, path / "trajectory" / EGOEXO_FILE):
            if candidate.is_file():
                return candidate
        return None
    return path if path.suffix.lower() == ".csv" and is_egoexo_file(path) else None


def is_egoexo_file(path: str | os.PathLike[str]) -> bool:
    """Whether a CSV file has the columns of an Ego-Exo4D GoPro calibration."""
    try:
        with open(path, newline="", encoding="utf-8") as f:
            header = next(csv.reader(f), [])
    except (OSError, UnicodeDecodeError):
        return False
    return all(c in header for c in _REQUIRED)


def _quaternion_matrix(xyzw: list[float], where: str) -> np.ndarray:
    x, y, z, w = xyzw
    q = np.array([w, x, y, z], np.float64)
    norm = float(np.linalg.norm(q))
    if not abs(norm - 1.0) < 1e-3:
        raise CalibrationError(f"{where}: the pose's quaternion has norm {norm:.6g}, not 1")
    w, x, y, z = q / norm
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def egoexo_calibration(path: str | os.PathLike[str]) -> CalibratedRig:
    """Read a ``gopro_calibs.csv`` (the file, a take's folder or its ``trajectory``) as a
    rig of the pinhole cameras the GoPros' frames are rectified to, with their lenses; see the
    module docstring."""
    file = egoexo_file(path)
    if file is None:
        raise CalibrationError(f"{path}: no Ego-Exo4D {EGOEXO_FILE}")
    with open(file, newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise CalibrationError(f"{file}: no cameras")
    made: list[tuple[Camera, FisheyeLens | None]] = []
    failed: list[str] = []
    for k, row in enumerate(rows):
        name = str(row.get("cam_uid") or f"cam{k}").strip()
        where = f"{file}: camera {name!r}"
        kind = str(row.get("intrinsics_type") or "KANNALABRANDTK3").strip().upper()
        if kind not in ("KANNALABRANDTK3", "KANNALA_BRANDT_K3"):
            raise CalibrationError(
                f"{where}: intrinsics_type {kind}: only KANNALABRANDTK3 (fisheye) is read"
            )
        try:
            values = {c: float(row[c]) for c in _REQUIRED if c != "cam_uid"}
            quality = float(row["quality"]) if row.get("quality") not in (None, "") else -1.0
        except (TypeError, ValueError) as exc:
            raise CalibrationError(f"{where}: a value is not a number ({exc})") from None
        if not all(np.isfinite(v) for v in values.values()):
            raise CalibrationError(f"{where}: values must be finite")
        if quality == 0:
            failed.append(name)
            continue
        fx, fy, cx, cy, *D = (values[c] for c in _INTRINSICS)
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        R = _quaternion_matrix([values[c] for c in _QUAT], where).T  # world -> camera
        t = -R @ np.array([values[c] for c in _POSE])
        width, height = int(values["image_width"]), int(values["image_height"])
        with in_file(where):
            made.append(lens_camera(name, width, height, K, R, t, np.asarray(D), fisheye=True))
    if failed:
        logger.warning(
            "%s: cameras %s failed to localise (quality 0) and are left out",
            file,
            ", ".join(failed),
        )
    with in_file(file):
        return calibrated_rig(made, unit="m", up=(0.0, 0.0, 1.0))
