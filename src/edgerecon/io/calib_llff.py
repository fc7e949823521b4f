"""LLFF's ``poses_bounds.npy``: the camera file of NeRF's forward-facing scenes and of the
multi-view video datasets in that layout (Neural 3D Video / DyNeRF: ``cam00.mp4`` ... next to
it).

An (N, 17) float array, one row per camera in the sorted order of its images (or videos):
15 values reshaped to a 3x5 matrix, then the near and far depth bounds. Columns 0-2 of the
matrix are the camera-to-world rotation with LLFF's axes (down, right, backwards), column 3
the camera centre, column 4 (height, width, focal length) in pixels. The principal point is
the image centre and there is no distortion (the images were undistorted). The scale is
COLMAP's (arbitrary); there is no up direction (the import estimates it).

In OpenCV's camera axes (right, down, forward) the rotation is ``[r, d, -b]`` of LLFF's
``[d, r, b]``; ``R = R_c2w^T`` and ``t = -R C``.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from edgerecon.geometry.camera import Camera, Rig
from edgerecon.io._errors import in_file
from edgerecon.types import CalibrationError

#: The file name LLFF's ``imgs2poses.py`` writes.
LLFF_FILE = "poses_bounds.npy"


def llff_file(path: str | os.PathLike[str]) -> Path | None:
    """The ``poses_bounds.npy`` of a path (the file, or a folder holding it), else None."""
    path = Path(path)
    if path.is_dir():
        path = path / LLFF_FILE
    return path if path.name == LLFF_FILE and path.is_file() else None


def llff_poses(path: str | os.PathLike[str]) -> np.ndarray:
    """The (N, 3, 5) pose matrices of a ``poses_bounds.npy``."""
    path = Path(path)
    try:
        arr = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise CalibrationError(f"calibration file not found: {path}") from None
    except (ValueError, OSError) as exc:
        raise CalibrationError(f"{path}: not a NumPy array file ({exc})") from None
    if arr.ndim != 2 or arr.shape[1] not in (15, 17) or len(arr) == 0:
        raise CalibrationError(
            f"{path}: an LLFF poses_bounds.npy is an (N, 17) array, got shape {arr.shape}"
        )
    poses = np.asarray(arr[:, :15], np.float64).reshape(-1, 3, 5)
    if not np.all(np.isfinite(poses)):
        raise CalibrationError(f"{path}: the poses hold NaN or infinite values")
    return poses


def read_llff(path: str | os.PathLike[str], names: Sequence[str] | None = None) -> Rig:
    """Read ``poses_bounds.npy`` (the file or its folder) as a rig; see the module docstring.
    ``names``: the cameras' names in row order (the sorted images or videos the rows were
    made from); default ``cam00``, ``cam01``, ... (Neural 3D Video's video names)."""
    file = llff_file(path)
    if file is None:
        raise CalibrationError(f"{path}: no LLFF {LLFF_FILE}")
    poses = llff_poses(file)
    if names is None:
        names = [f"cam{k:02d}" for k in range(len(poses))]
    if len(names) != len(poses):
        raise CalibrationError(
            f"{file}: {len(poses)} cameras (rows) but {len(names)} names / frame sources"
        )
    cameras = []
    for name, pose in zip(names, poses, strict=True):
        down, right, back, centre, hwf = pose.T
        height, width, focal = hwf
        if not (height >= 1 and width >= 1 and focal > 0):
            raise CalibrationError(
                f"{file}: camera {name!r}: height, width, focal {height:g}, {width:g}, "
                f"{focal:g} are not an image size and a focal length"
            )
        R = np.stack([right, down, -back])  # rows: world -> OpenCV camera axes
        u, _, vt = np.linalg.svd(R)  # files often hold float32 rotations: the nearest one
        R = u @ vt
        with in_file(file):
            cameras.append(
                Camera(
                    name=str(name),
                    width=int(np.rint(width)),
                    height=int(np.rint(height)),
                    K=np.array([[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0, 0, 1]]),
                    R=R,
                    t=-R @ centre,
                    dist=np.zeros(5),
                )
            )
    with in_file(file):
        return Rig(cameras=tuple(cameras), unit="m")
