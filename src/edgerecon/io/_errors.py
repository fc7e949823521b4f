"""Helpers shared by the calibration readers: errors that name the file, the checks every
format needs."""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.types import CalibrationError

#: Distortion vector lengths OpenCV writes (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1..s4 [tx ty]]]]).
DISTORTION_SIZES = (4, 5, 8, 12, 14)


@contextlib.contextmanager
def in_file(path: Path | str) -> Iterator[None]:
    """Prefix CalibrationErrors raised inside (e.g. by Camera/Rig validation) with a file."""
    try:
        yield
    except CalibrationError as exc:
        msg = str(exc)
        if str(path) in msg:
            raise
        raise CalibrationError(f"{path}: {msg}") from None


def rotation_matrix(values: NDArray[np.float64], where: str) -> NDArray[np.float64]:
    """A 3x3 rotation from a Rodrigues vector (3 values) or a matrix (9 values), as the
    calibration formats store it; ``CalibrationError`` naming ``where`` otherwise."""
    rot = np.asarray(values, np.float64)
    if rot.size == 3:
        return np.asarray(cv2.Rodrigues(rot.reshape(3, 1))[0], np.float64)
    if rot.size == 9:
        return rot.reshape(3, 3)
    raise CalibrationError(
        f"{where}: rotation must be a Rodrigues vector (3) or a 3x3 matrix, got {rot.size} values"
    )


def check_distortion(dist: NDArray[np.float64], where: str) -> NDArray[np.float64]:
    """``dist`` flattened, if OpenCV could have written its length; ``CalibrationError``
    naming ``where`` otherwise."""
    dist = np.asarray(dist, np.float64).ravel()
    if dist.size not in DISTORTION_SIZES:
        raise CalibrationError(
            f"{where}: distortion must have 4, 5, 8, 12 or 14 coefficients, got {dist.size}"
        )
    return dist


def read_json(path: Path | str) -> Any:
    """A calibration file's JSON; ``CalibrationError`` naming the file when it is missing or
    not readable JSON."""
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except FileNotFoundError:
        raise CalibrationError(f"calibration file not found: {path}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CalibrationError(f"{path}: not valid JSON ({exc})") from None
