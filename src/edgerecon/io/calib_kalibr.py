"""Kalibr's camera chain (``camchain.yaml``, ``camchain-imucam.yaml``): the multi-camera
calibration of robotics rigs (drones, robots, camera arrays on ROS).

A YAML mapping ``cam0``, ``cam1``, ... of:

* ``camera_model`` ``pinhole`` with ``intrinsics`` ``[fu, fv, pu, pv]`` (pixels) and
  ``resolution`` ``[width, height]``;
* ``distortion_model`` ``radtan`` with ``distortion_coeffs`` ``[k1, k2, r1, r2]`` (OpenCV's
  ``k1 k2 p1 p2``), ``none``, or ``equidistant`` ``[k1, k2, k3, k4]`` (OpenCV's fisheye
  model: the import rectifies those frames to pinhole cameras, ``geometry.lens``); ``fov``
  and the omnidirectional camera models are refused with a clear error;
* ``T_cn_cnm1`` (4x4, every camera but the first): the pose of camera n-1 in camera n
  (``X_n = T X_{n-1}``), so camera 0's frame is the world (y down: the import estimates the
  up direction from the cameras' horizons); in a ``camchain-imucam.yaml`` ``T_cam_imu``
  instead puts the IMU's frame at the world's when a camera has no ``T_cn_cnm1``.

Lengths are in metres (Kalibr's targets are given in metres). The cameras are named after
their keys (``cam0``); ``rostopic`` is kept out of the name. A malformed file raises
``CalibrationError`` naming the file, the camera and the problem.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry.camera import Camera, Rig
from edgerecon.geometry.lens import CalibratedRig, FisheyeLens, calibrated_rig, lens_camera
from edgerecon.io._errors import in_file
from edgerecon.types import CalibrationError

_CAM_KEY = re.compile(r"cam(\d+)\Z")


def load_yaml(path: Path) -> Any:
    import yaml

    try:
        return yaml.safe_load(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise CalibrationError(f"calibration file not found: {path}") from None
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise CalibrationError(f"{path}: not a readable YAML file ({exc})") from None


def is_kalibr(data: Any) -> bool:
    """Whether parsed YAML is a Kalibr camera chain (``camN`` keys with intrinsics)."""
    if not isinstance(data, dict) or not data:
        return False
    cams = [k for k in data if isinstance(k, str) and _CAM_KEY.match(k)]
    return bool(cams) and all(
        isinstance(data[k], dict) and "intrinsics" in data[k] and "camera_model" in data[k]
        for k in cams
    )


def is_kalibr_file(path: str | os.PathLike[str]) -> bool:
    """Whether a ``.yaml`` / ``.yml`` file is a Kalibr camera chain (a cheap look first: the
    OpenCV FileStorage YAML files of other formats start with ``%YAML:1.0``)."""
    path = Path(path)
    try:
        head = path.read_text(encoding="utf-8", errors="replace")[:4096]
    except OSError:
        return False
    if head.lstrip().startswith("%YAML:") or "intrinsics" not in head:
        return False
    try:
        return is_kalibr(load_yaml(path))
    except CalibrationError:
        return False


def kalibr_files(folder: str | os.PathLike[str]) -> list[Path]:
    """The Kalibr camera chains in a folder (``*camchain*.yaml``), sorted."""
    folder = Path(folder)
    return sorted(
        p
        for p in folder.iterdir()
        if p.is_file()
        and "camchain" in p.name.lower()
        and p.suffix.lower() in (".yaml", ".yml")
        and is_kalibr_file(p)
    )


def _floats(value: Any, n: int | tuple[int, ...], key: str, where: str) -> NDArray[np.float64]:
    try:
        arr = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        raise CalibrationError(f"{where}: {key} is not a list of numbers") from None
    sizes = (n,) if isinstance(n, int) else n
    if arr.size not in sizes or not np.all(np.isfinite(arr)):
        want = " or ".join(str(s) for s in sizes)
        raise CalibrationError(f"{where}: {key} must hold {want} finite numbers, got {value!r}")
    return arr.ravel()


def _transform(value: Any, key: str, where: str) -> NDArray[np.float64]:
    T = _floats(value, 16, key, where).reshape(4, 4)
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        raise CalibrationError(f"{where}: {key}'s 3x3 block is not a rotation")
    u, _, vt = np.linalg.svd(R)  # written with a few digits: the nearest rotation
    out = np.eye(4)
    out[:3, :3] = u @ vt
    out[:3, 3] = T[:3, 3]
    return out


def read_kalibr(path: str | os.PathLike[str]) -> Rig:
    """Read a Kalibr ``camchain.yaml`` (the file, or a folder holding one) as a rig; see the
    module docstring. Fisheye cameras raise (``kalibr_calibration`` gives their lenses)."""
    return kalibr_calibration(path).pinhole_only(path)


def kalibr_calibration(path: str | os.PathLike[str]) -> CalibratedRig:
    """``read_kalibr``'s rig with the lenses of its ``equidistant`` cameras (OpenCV's fisheye
    model: those cameras are the pinhole cameras their frames are rectified to)."""
    file = Path(path)
    if file.is_dir():
        found = kalibr_files(file)
        if len(found) != 1:
            raise CalibrationError(
                f"{file}: {'no' if not found else 'several'} Kalibr camchain*.yaml"
                + (f" ({', '.join(p.name for p in found)}); pass one of them" if found else "")
            )
        file = found[0]
    data = load_yaml(file)
    if not is_kalibr(data):
        raise CalibrationError(
            f"{file}: not a Kalibr camera chain (cam0, cam1, ... with intrinsics)"
        )
    keys = sorted(
        (k for k in data if isinstance(k, str) and _CAM_KEY.match(k)),
        key=lambda k: int(k[3:]),
    )
    if [int(k[3:]) for k in keys] != list(range(len(keys))):
        raise CalibrationError(f"{file}: cameras {keys} are not numbered cam0, cam1, ... in order")
    chain = all("T_cn_cnm1" in data[k] for k in keys[1:])
    imu = all("T_cam_imu" in data[k] for k in keys)
    if not chain and not imu:
        missing = [k for k in keys[1:] if "T_cn_cnm1" not in data[k]]
        raise CalibrationError(
            f"{file}: {', '.join(missing)} without T_cn_cnm1 (and not every camera has "
            "T_cam_imu): the cameras' poses are unknown"
        )
    made: list[tuple[Camera, FisheyeLens | None]] = []
    pose = np.eye(4)  # world (camera 0, or the IMU) -> current camera
    for n, key in enumerate(keys):
        entry = data[key]
        where = f"{file}: {key}"
        model = str(entry.get("camera_model", "")).lower()
        if model != "pinhole":
            raise CalibrationError(
                f"{where}: camera_model {model!r}: edgerecon models pinhole cameras only "
                "(omni, ds, eucm are not)"
            )
        dmodel = str(entry.get("distortion_model", "none")).lower()
        coeffs = entry.get("distortion_coeffs", [])
        fisheye = dmodel == "equidistant"
        if dmodel == "radtan":
            k1, k2, p1, p2 = _floats(coeffs, 4, "distortion_coeffs", where)
            dist = np.array([k1, k2, p1, p2, 0.0])
        elif dmodel == "none":
            dist = np.zeros(5)
        elif fisheye:
            dist = _floats(coeffs, 4, "distortion_coeffs", where)
        else:
            raise CalibrationError(
                f"{where}: distortion_model {dmodel!r}: edgerecon models radtan (OpenCV's "
                "plumb-bob) and equidistant (OpenCV's fisheye) only"
            )
        fu, fv, pu, pv = _floats(entry.get("intrinsics"), 4, "intrinsics", where)
        width, height = (int(x) for x in _floats(entry.get("resolution"), 2, "resolution", where))
        if chain:
            if n > 0:
                pose = _transform(entry["T_cn_cnm1"], "T_cn_cnm1", where) @ pose
        else:
            pose = _transform(entry["T_cam_imu"], "T_cam_imu", where)
        K = np.array([[fu, 0.0, pu], [0.0, fv, pv], [0.0, 0.0, 1.0]])
        R, t = pose[:3, :3].copy(), pose[:3, 3].copy()
        with in_file(file):
            made.append(lens_camera(key, width, height, K, R, t, dist, fisheye=fisheye))
    with in_file(file):
        return calibrated_rig(made, unit="m", up=(0.0, -1.0, 0.0))
