"""NeRF-style ``transforms.json``: the camera file of nerfstudio, Instant-NGP and the original
NeRF (Blender) scenes, and of the multi-view captures prepared for them.

A JSON object with a list ``frames``, one per image: ``file_path`` and ``transform_matrix``
(4x4 or 3x4 camera-to-world, OpenGL axes: x right, y up, z backwards). The intrinsics are
either at the top (shared) or in each frame (a frame's own win):

* ``fl_x`` / ``fl_y`` / ``cx`` / ``cy`` / ``w`` / ``h`` (nerfstudio, Instant-NGP), or
  ``intrinsic_matrix`` (3x3 or 4x4, NeuS2), or ``camera_angle_x`` (and ``camera_angle_y``):
  the horizontal field of view in radians (the Blender scenes, whose size is the images');
* ``camera_model`` ``PINHOLE`` / ``SIMPLE_PINHOLE`` / ``OPENCV`` with ``k1 k2 (k3) p1 p2``
  (OpenCV's plumb-bob model, as edgerecon's cameras), or ``OPENCV_FISHEYE`` (Instant-NGP:
  ``is_fisheye``) with ``k1 k2 k3 k4``: OpenCV's fisheye model, whose frames the import
  rectifies to pinhole cameras (``geometry.lens``); ``EQUIRECTANGULAR`` is refused.

The principal point defaults to the image centre and ``fl_y`` to ``fl_x``. Without ``w`` /
``h`` the size comes from ``image_sizes`` or from the image at ``file_path`` (relative to
the file; the Blender scenes leave out ``.png``). nerfstudio's pixel coordinates are OpenCV's
(``cx`` = w/2 for a centred principal point), so no half-pixel shift is applied.

A camera's name is its image's file name without the suffix (``images/cam03.png`` -> camera
``cam03``); when several frames share that name (``cam03/000000.png`` for every camera) the
folder names the camera. A file that lists the same camera at several timestamps (identical
pose and intrinsics) gives one camera. The world's scale is the file's (often COLMAP's,
arbitrary: the unit is assumed to be metres) and nerfstudio's world is z-up (the import checks
it against the cameras' horizons). In OpenCV's axes the camera-to-world rotation is
``[x, -y, -z]`` of OpenGL's; ``R = R_c2w^T`` and ``t = -R C``.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Collection, Mapping
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry.camera import Camera, Rig
from edgerecon.geometry.lens import CalibratedRig, FisheyeLens, calibrated_rig, lens_camera
from edgerecon.io._errors import in_file, read_json
from edgerecon.io.frames import probe_image_size
from edgerecon.types import CalibrationError, DataError

#: File names the NeRF tools write (searched in this order in a folder).
TRANSFORMS_FILES = ("transforms.json", "transforms_train.json")

#: Camera models of nerfstudio / COLMAP that are OpenCV's plumb-bob or a special case of it.
_PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "OPENCV", "SIMPLE_RADIAL", "RADIAL")

#: OpenGL camera axes (x right, y up, z back) -> OpenCV's (x right, y down, z forward).
_GL_TO_CV = np.diag([1.0, -1.0, -1.0])


def is_transforms(data: Any) -> bool:
    """Whether parsed JSON is a NeRF-style transforms file (frames with camera-to-world
    matrices)."""
    if not isinstance(data, dict):
        return False
    frames = data.get("frames")
    return (
        isinstance(frames, list)
        and len(frames) > 0
        and all(isinstance(f, dict) and "transform_matrix" in f for f in frames)
    )


def transforms_file(path: str | os.PathLike[str]) -> Path | None:
    """The transforms file of a path (the file itself, or a folder holding one of
    ``TRANSFORMS_FILES``), else None."""
    path = Path(path)
    if path.is_dir():
        for name in TRANSFORMS_FILES:
            if (path / name).is_file():
                return path / name
        return None
    return path if path.suffix.lower() == ".json" and path.is_file() else None


def _load(path: Path) -> dict[str, Any]:
    data = read_json(path)
    if not is_transforms(data):
        raise CalibrationError(
            f"{path}: not a NeRF transforms file (a 'frames' list whose items each have a "
            "'transform_matrix')"
        )
    return data


def _number(params: Mapping[str, Any], key: str, where: str) -> float | None:
    value = params.get(key)
    if value is None:
        return None
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise CalibrationError(f"{where}: {key} must be a number, got {value!r}") from None
    if not math.isfinite(out):
        raise CalibrationError(f"{where}: {key} is not finite ({value!r})")
    return out


def _matrix(value: Any, shapes: tuple[tuple[int, int], ...], key: str, where: str) -> NDArray:
    try:
        arr = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        raise CalibrationError(f"{where}: {key} is not a matrix of numbers") from None
    if arr.shape not in shapes:
        want = " or ".join(f"{r}x{c}" for r, c in shapes)
        raise CalibrationError(f"{where}: {key} must be {want}, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise CalibrationError(f"{where}: {key} holds NaN or infinite values")
    return arr


def _image_path(folder: Path, file_path: str) -> Path | None:
    """The image a frame names, if it exists (Blender scenes leave out the suffix)."""
    base = folder / file_path
    if base.is_file():
        return base
    for suffix in (".png", ".jpg", ".jpeg", ".PNG", ".JPG"):
        candidate = base.with_name(base.name + suffix)
        if candidate.is_file():
            return candidate
    return None


def _names(paths: list[str]) -> list[str]:
    """Camera names from the frames' image paths (see the module docstring)."""
    parts = [Path(p.replace("\\", "/")) for p in paths]
    stems = [
        p.stem if p.suffix.lower() in (".png", ".jpg", ".jpeg", ".exr") else p.name for p in parts
    ]
    if len(set(stems)) == len(stems):
        return stems
    parents = [p.parent.name for p in parts]
    if all(parents) and len(set(parents)) == len(parents):
        return parents
    joined = [str(p.with_suffix("")).lstrip("./").replace("/", "_") for p in parts]
    if len(set(joined)) == len(joined):
        return joined
    return [f"cam{k:02d}" for k in range(len(paths))]


def _intrinsics(
    params: Mapping[str, Any],
    size: tuple[int, int] | None,
    where: str,
) -> tuple[tuple[int, int], NDArray[np.float64], NDArray[np.float64], bool]:
    """(size, K, distortion, fisheye) of one frame's merged parameters: the distortion is
    OpenCV's (k1, k2, p1, p2, k3), or the fisheye model's (k1, k2, k3, k4)."""
    model = str(params.get("camera_model", "OPENCV")).upper()
    fisheye = model == "OPENCV_FISHEYE" or bool(params.get("is_fisheye"))
    if model not in (*_PINHOLE_MODELS, "OPENCV_FISHEYE"):
        raise CalibrationError(
            f"{where}: camera_model {model}: edgerecon models pinhole cameras with OpenCV's "
            "plumb-bob or fisheye distortion; reproject the frames to a pinhole camera first"
        )
    w, h = _number(params, "w", where), _number(params, "h", where)
    if w is not None and h is not None:
        size = (round(w), round(h))
    if size is None:
        raise CalibrationError(
            f"{where}: no image size (w, h) and no image to read it from; pass the frames "
            "(edgerecon import) or image sizes"
        )
    width, height = size
    if "intrinsic_matrix" in params:
        k = _matrix(params["intrinsic_matrix"], ((3, 3), (4, 4)), "intrinsic_matrix", where)
        fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    else:
        fx = _number(params, "fl_x", where)
        fy = _number(params, "fl_y", where)
        angle_x = _number(params, "camera_angle_x", where)
        angle_y = _number(params, "camera_angle_y", where)
        if fx is None and angle_x is not None:
            fx = 0.5 * width / math.tan(0.5 * angle_x)
        if fy is None and angle_y is not None:
            fy = 0.5 * height / math.tan(0.5 * angle_y)
        if fx is None:
            fx = fy
        if fy is None:
            fy = fx
        if fx is None or fy is None:
            raise CalibrationError(
                f"{where}: no focal length (fl_x / fl_y, camera_angle_x or intrinsic_matrix)"
            )
        cx = _number(params, "cx", where)
        cy = _number(params, "cy", where)
        cx = width / 2.0 if cx is None else cx
        cy = height / 2.0 if cy is None else cy
    if not (fx > 0 and fy > 0):
        raise CalibrationError(f"{where}: focal lengths must be > 0, got {fx:g}, {fy:g}")
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    if fisheye:
        D = np.array([_number(params, key, where) or 0.0 for key in ("k1", "k2", "k3", "k4")])
        return (width, height), K, D, True
    dist = np.array([_number(params, key, where) or 0.0 for key in ("k1", "k2", "p1", "p2", "k3")])
    if (_number(params, "k4", where) or 0.0) != 0.0:
        raise CalibrationError(
            f"{where}: k4 is set with camera_model {model}: k4 belongs to the fisheye model "
            "(camera_model OPENCV_FISHEYE)"
        )
    return (width, height), K, dist, False


def _pose(value: Any, where: str) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(R, t) world->OpenCV camera of an OpenGL camera-to-world matrix."""
    c2w = _matrix(value, ((4, 4), (3, 4)), "transform_matrix", where)
    rot = c2w[:3, :3] @ _GL_TO_CV
    u, s, vt = np.linalg.svd(rot)
    if not np.all(s > 0) or np.max(np.abs(s - s.mean())) > 1e-3 * s.mean():
        raise CalibrationError(
            f"{where}: transform_matrix's rotation is scaled or sheared (singular values "
            f"{', '.join(f'{x:.4g}' for x in s)}); a camera-to-world pose has a rotation"
        )
    rot = u @ vt  # files often hold float32 rotations: the nearest one
    if np.linalg.det(rot) < 0:
        raise CalibrationError(f"{where}: transform_matrix's rotation is a reflection")
    R = rot.T
    centre = c2w[:3, 3]
    return R, -R @ centre


def _unique_poses(
    file: Path, data: dict[str, Any]
) -> tuple[list[int], list[tuple[NDArray[np.float64], NDArray[np.float64]]]]:
    """The index and (R, t) of each frame whose pose no earlier frame has: a file that lists
    the rig at several timestamps repeats its cameras."""
    firsts: list[int] = []
    poses: list[tuple[NDArray[np.float64], NDArray[np.float64]]] = []
    keys: set[tuple[float, ...]] = set()
    for k, frame in enumerate(data["frames"]):
        R, t = _pose(frame["transform_matrix"], f"{file}: frame {k}")
        key = tuple(np.round(np.concatenate([R.ravel(), t]), 7).tolist())
        if key not in keys:
            keys.add(key)
            firsts.append(k)
            poses.append((R, t))
    return firsts, poses


def transforms_camera_names(path: str | os.PathLike[str]) -> list[str]:
    """The names ``read_transforms`` gives the cameras of a transforms file (nothing else is
    read: the import matches the frames by them before it knows the image sizes)."""
    file = transforms_file(path)
    if file is None:
        raise CalibrationError(f"{path}: no {' or '.join(TRANSFORMS_FILES)}")
    data = _load(file)
    firsts, _ = _unique_poses(file, data)
    return _names([str(data["frames"][k].get("file_path", f"frame{k:04d}")) for k in firsts])


def read_transforms(
    path: str | os.PathLike[str],
    image_sizes: Mapping[str, tuple[int, int]] | tuple[int, int] | None = None,
    *,
    only: Collection[str] | None = None,
) -> Rig:
    """Read a ``transforms.json`` (the file or its folder) as a rig; see the module
    docstring. ``image_sizes`` ((width, height) per camera name, or one for all) is used
    where the file records no size; ``only``: the cameras to read (those filmed). Fisheye
    cameras raise (``transforms_calibration`` gives them with their lenses)."""
    return transforms_calibration(path, image_sizes, only=only).pinhole_only(path)


def transforms_calibration(
    path: str | os.PathLike[str],
    image_sizes: Mapping[str, tuple[int, int]] | tuple[int, int] | None = None,
    *,
    only: Collection[str] | None = None,
) -> CalibratedRig:
    """``read_transforms``'s rig with the fisheye lenses (``OPENCV_FISHEYE``): those cameras
    are the pinhole cameras their frames are rectified to (``geometry.lens``)."""
    file = transforms_file(path)
    if file is None:
        raise CalibrationError(f"{path}: no {' or '.join(TRANSFORMS_FILES)}")
    data = _load(file)
    top = {k: v for k, v in data.items() if k != "frames"}
    firsts, poses = _unique_poses(file, data)
    frames = [data["frames"][k] for k in firsts]
    paths = [str(f.get("file_path", f"frame{k:04d}")) for k, f in zip(firsts, frames, strict=True)]
    names = _names(paths)
    made: list[tuple[Camera, FisheyeLens | None]] = []
    for k, frame, name, image, (R, t) in zip(firsts, frames, names, paths, poses, strict=True):
        if only is not None and name not in only:
            continue
        where = f"{file}: frame {k} ({image})"
        params = {**top, **frame}
        size: tuple[int, int] | None = None
        if isinstance(image_sizes, tuple):
            size = (int(image_sizes[0]), int(image_sizes[1]))
        elif image_sizes is not None and name in image_sizes:
            w, h = image_sizes[name]
            size = (int(w), int(h))
        if size is None and not ("w" in params and "h" in params):
            found = _image_path(file.parent, image)
            if found is not None:
                try:
                    size = probe_image_size(found)
                except DataError as exc:
                    raise CalibrationError(f"{where}: {exc}") from None
        (width, height), K, dist, fisheye = _intrinsics(params, size, where)
        with in_file(file):
            made.append(lens_camera(name, width, height, K, R, t, dist, fisheye=fisheye))
    with in_file(file):
        return calibrated_rig(made, unit="m", up=(0.0, 0.0, 1.0))


def write_transforms(
    path: str | os.PathLike[str],
    rig: Rig,
    image_paths: Mapping[str, str],
    *,
    ply_file_path: str | None = None,
) -> Path:
    """Write ``rig`` as a nerfstudio ``transforms.json`` (per-frame intrinsics, OPENCV model,
    OpenGL camera-to-world poses): one frame per camera, its image at ``image_paths[name]``
    (relative to the file's folder); ``ply_file_path`` names a point cloud nerfstudio's
    splatfacto starts from. Returns the file's path."""
    path = Path(path)
    out_frames = []
    for cam in rig:
        c2w = np.eye(4)
        c2w[:3, :3] = cam.R.T @ _GL_TO_CV
        c2w[:3, 3] = cam.center
        k1, k2, p1, p2, k3 = (list(np.asarray(cam.dist, np.float64).ravel()) + [0.0] * 5)[:5]
        out_frames.append(
            {
                "file_path": image_paths[cam.name],
                "camera_model": "OPENCV",
                "fl_x": float(cam.K[0, 0]),
                "fl_y": float(cam.K[1, 1]),
                "cx": float(cam.K[0, 2]),
                "cy": float(cam.K[1, 2]),
                "w": int(cam.width),
                "h": int(cam.height),
                "k1": float(k1),
                "k2": float(k2),
                "p1": float(p1),
                "p2": float(p2),
                "k3": float(k3),
                "transform_matrix": c2w.tolist(),
            }
        )
    data: dict[str, Any] = {"camera_model": "OPENCV", "frames": out_frames}
    if ply_file_path is not None:
        data["ply_file_path"] = ply_file_path
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2) + "\n", encoding="utf-8")
    os.replace(tmp, path)
    return path
