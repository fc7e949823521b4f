"""multical's ``calibration.json``: the calibration of camera rigs by multical (several
cameras and boards at once).

* ``cameras``: per camera name, ``image_size`` [width, height], ``K`` (3x3) and ``dist``
  (a 1 x N list): OpenCV's plumb-bob coefficients (k1 k2 p1 p2 k3, or more for the
  ``rational`` / ``thin_prism`` / ``tilted`` models, read when the extras are zero), or four
  coefficients for multical's fisheye cameras (OpenCV's fisheye model: the import rectifies
  their frames, ``geometry.lens``);
* ``camera_poses``: ``R`` (3x3) and ``T`` (3) per camera, world -> camera (``X_cam = R X +
  T``), either for every camera (``"cam1"``) or relative to the master camera
  (``"cam2_to_cam1"``: the pose that, composed after the master's, gives the camera's, as
  multical's own importer chains them); the master's is the identity, so the world is its
  frame (the import estimates the up direction from the cameras' horizons);
* ``image_sets`` (ignored). Lengths are those of the boards' square size (metres in
  multical's board files).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry.camera import Camera
from edgerecon.geometry.lens import CalibratedRig, FisheyeLens, calibrated_rig, lens_camera
from edgerecon.io._errors import in_file, read_json
from edgerecon.types import CalibrationError


def is_multical(data: Any) -> bool:
    """Whether parsed JSON is a multical calibration (cameras with ``K`` and ``image_size``,
    and ``camera_poses``)."""
    if not isinstance(data, dict):
        return False
    cams, poses = data.get("cameras"), data.get("camera_poses")
    return (
        isinstance(cams, dict)
        and isinstance(poses, dict)
        and bool(cams)
        and all(isinstance(c, dict) and "K" in c and "image_size" in c for c in cams.values())
    )


def _array(value: Any, shape: tuple[int, ...], what: str, where: str) -> NDArray[np.float64]:
    try:
        arr = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        raise CalibrationError(f"{where}: {what} is not an array of numbers") from None
    if arr.size != int(np.prod(shape)) or not np.all(np.isfinite(arr)):
        raise CalibrationError(f"{where}: {what} must hold {int(np.prod(shape))} finite numbers")
    return arr.reshape(shape)


def _pose(entry: Any, where: str) -> NDArray[np.float64]:
    if not isinstance(entry, dict) or "R" not in entry or "T" not in entry:
        raise CalibrationError(f"{where}: a pose needs R and T")
    T = np.eye(4)
    T[:3, :3] = _array(entry["R"], (3, 3), "R", where)
    T[:3, 3] = _array(entry["T"], (3,), "T", where)
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        raise CalibrationError(f"{where}: R is not a rotation")
    return T


def _poses(file: Path, entries: dict[str, Any], names: list[str]) -> dict[str, NDArray]:
    """World -> camera per camera, chained from the relative entries as multical's importer
    does (``a_to_b``: the pose of ``a`` is the pose of ``b`` times it)."""
    known: dict[str, NDArray[np.float64]] = {}
    relations: list[tuple[str, str, NDArray[np.float64]]] = []
    for key, entry in entries.items():
        where = f"{file}: camera_poses.{key}"
        if "_to_" in key:
            a, b = key.split("_to_", 1)
            for n in (a, b):
                if n not in names:
                    raise CalibrationError(f"{where}: camera {n!r} is not in cameras")
            relations.append((a, b, _pose(entry, where)))
        elif key in names:
            known[key] = _pose(entry, where)
        else:
            raise CalibrationError(f"{where}: camera {key!r} is not in cameras")
    changed = True
    while changed:
        changed = False
        for a, b, t in relations:
            if b in known and a not in known:
                known[a] = known[b] @ t
                changed = True
            elif a in known and b not in known:
                known[b] = known[a] @ np.linalg.inv(t)
                changed = True
    missing = [n for n in names if n not in known]
    if missing:
        raise CalibrationError(f"{file}: no pose for cameras {', '.join(missing)}")
    return known


def multical_calibration(path: str | os.PathLike[str]) -> CalibratedRig:
    """Read a multical ``calibration.json`` (the file) as a rig with the lenses of its
    fisheye cameras; see the module docstring."""
    file = Path(path)
    data = read_json(file)
    if not is_multical(data):
        raise CalibrationError(f"{file}: not a multical calibration (cameras, camera_poses)")
    names = list(data["cameras"])
    poses = _poses(file, data["camera_poses"], names)
    made: list[tuple[Camera, FisheyeLens | None]] = []
    for name in names:
        entry = data["cameras"][name]
        where = f"{file}: camera {name!r}"
        size = _array(entry["image_size"], (2,), "image_size", where)
        width, height = int(size[0]), int(size[1])
        K = _array(entry["K"], (3, 3), "K", where)
        try:
            dist = np.asarray(entry.get("dist", [[0.0] * 5]), np.float64).ravel()
        except (TypeError, ValueError):
            raise CalibrationError(f"{where}: dist is not a list of numbers") from None
        if not np.all(np.isfinite(dist)):
            raise CalibrationError(f"{where}: dist holds NaN or infinite values")
        R, t = poses[name][:3, :3], poses[name][:3, 3]
        with in_file(file):
            # multical's fisheye cameras have cv2.fisheye's 4 coefficients.
            made.append(lens_camera(name, width, height, K, R, t, dist, fisheye=dist.size == 4))
    with in_file(file):
        return calibrated_rig(made, unit="m", up=(0.0, -1.0, 0.0))
