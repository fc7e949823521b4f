"""Fisheye lenses, rectified to pinhole cameras when their frames are read.

The reconstruction works with pinhole cameras and OpenCV's plumb-bob distortion
(``Camera``). A fisheye lens (GoPro and other action cameras, Ego-Exo4D's exo cameras,
Kalibr's ``equidistant``, nerfstudio's ``OPENCV_FISHEYE``) follows OpenCV's fisheye model,
the Kannala-Brandt model with four coefficients: a ray at angle ``theta`` from the optical
axis lands at radius ``f * theta_d`` with
``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)``.

Such a camera enters the rig as the pinhole camera its frames are rectified to
(``Rectification``: the lens, and the pinhole ``K`` at the same image size, by default the
largest view with no invalid pixels, ``cv2.fisheye.estimateNewCameraMatrixForUndistortRectify``
with ``balance`` 0); the frame sources remap every frame of it once, as it is read
(``io.frames``; a live stream's, ``io.streams``, once a synchronized set is chosen). Nothing
else in the pipeline sees the lens. What it cannot do: a lens wider
than about 160 degrees keeps only the part of its view a pinhole camera can hold.
"""

from __future__ import annotations

import functools
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry.camera import Camera, Rig
from edgerecon.types import CalibrationError


@dataclass(frozen=True, kw_only=True, eq=False)
class FisheyeLens:
    """A fisheye camera's intrinsics (see the module docstring) at one image size."""

    width: int
    height: int
    K: NDArray[np.float64]
    """3x3 camera matrix (fx, fy, cx, cy; pixel centres on integer coordinates)."""
    D: NDArray[np.float64]
    """(k1, k2, k3, k4)."""

    def __post_init__(self) -> None:
        K = np.asarray(self.K, np.float64).reshape(3, 3)
        D = np.asarray(self.D, np.float64).ravel()
        if D.size != 4:
            raise CalibrationError(f"a fisheye lens has 4 coefficients (k1..k4), got {D.size}")
        if not (np.all(np.isfinite(K)) and np.all(np.isfinite(D))):
            raise CalibrationError("fisheye lens parameters must be finite")
        if not (K[0, 0] > 0 and K[1, 1] > 0) or not (
            1 <= self.width <= 65535 and 1 <= self.height <= 65535
        ):
            raise CalibrationError(
                f"fisheye lens: focal lengths {K[0, 0]:g}, {K[1, 1]:g} must be positive and the "
                f"size {self.width}x{self.height} between 1 and 65535 pixels"
            )
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "D", D)

    @property
    def size(self) -> tuple[int, int]:
        return (self.width, self.height)

    def resized(self, width: int, height: int) -> FisheyeLens:
        """The lens at another image size (the frames of a downscaled copy): K scales, the
        coefficients act on angles and stay."""
        sx, sy = width / self.width, height / self.height
        K = self.K.copy()
        K[0] *= sx
        K[1] *= sy
        # Pixel centres on integer coordinates: the centre of pixel (0, 0) stays at 0.
        K[0, 2] = (self.K[0, 2] + 0.5) * sx - 0.5
        K[1, 2] = (self.K[1, 2] + 0.5) * sy - 0.5
        return FisheyeLens(width=width, height=height, K=K, D=self.D)

    def pinhole_K(self, balance: float = 0.0) -> NDArray[np.float64]:
        """The pinhole camera matrix its frames are rectified to, at the same size:
        ``balance`` 0 keeps only valid pixels, 1 keeps the whole view (black corners)."""
        try:
            found = cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(
                self.K, self.D, self.size, np.eye(3), balance=float(balance)
            )
        except cv2.error as exc:
            raise CalibrationError(f"fisheye lens: no pinhole view ({exc})") from None
        K: NDArray[np.float64] = np.asarray(found, np.float64)
        if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0):
            raise CalibrationError(
                f"fisheye lens: no pinhole view (k1..k4 {', '.join(f'{d:g}' for d in self.D)} "
                "fold the image back on itself)"
            )
        return K

    def from_pinhole(self, K: NDArray[np.float64], uv: NDArray[np.float64]) -> NDArray[np.float64]:
        """Pixels ``uv`` (N, 2) of the pinhole camera ``K`` (the rectified view) -> the same
        rays' pixels in this lens's frames."""
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        if not len(uv):
            return uv.copy()
        x = (uv - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])
        out = cv2.fisheye.distortPoints(x.reshape(-1, 1, 2), self.K, self.D)
        return np.asarray(out, np.float64).reshape(-1, 2)

    def to_dict(self) -> dict[str, Any]:
        return {
            "model": "fisheye",
            "width": self.width,
            "height": self.height,
            "K": self.K.tolist(),
            "D": self.D.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> FisheyeLens:
        if d.get("model", "fisheye") != "fisheye":
            raise CalibrationError(f"unknown lens model {d.get('model')!r} (known: fisheye)")
        try:
            return cls(
                width=int(d["width"]),
                height=int(d["height"]),
                K=np.asarray(d["K"], np.float64),
                D=np.asarray(d["D"], np.float64),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise CalibrationError(f"a lens needs width, height, K and D ({exc})") from None


@dataclass(frozen=True, kw_only=True, eq=False)
class Rectification:
    """A fisheye camera's frames remapped to the pinhole camera ``K`` of the same size."""

    lens: FisheyeLens
    K: NDArray[np.float64]

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", np.asarray(self.K, np.float64).reshape(3, 3))

    @functools.cached_property
    def _maps(self) -> tuple[NDArray[np.int16], NDArray[np.uint16]]:
        m1, m2 = cv2.fisheye.initUndistortRectifyMap(
            self.lens.K, self.lens.D, np.eye(3), self.K, self.lens.size, cv2.CV_16SC2
        )
        return np.asarray(m1, np.int16), np.asarray(m2, np.uint16)

    def __call__(self, image: NDArray[np.uint8]) -> NDArray[np.uint8]:
        """The pinhole view of one frame of the lens (its size is checked by the caller)."""
        m1, m2 = self._maps
        return np.asarray(
            cv2.remap(image, m1, m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT),
            np.uint8,
        )

    def __getstate__(self) -> dict[str, Any]:
        # The maps (8 MB per 1080p camera) are rebuilt where the frames are read.
        return {k: v for k, v in self.__dict__.items() if k != "_maps"}

    def to_dict(self) -> dict[str, Any]:
        return {"lens": self.lens.to_dict(), "K": self.K.tolist()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Rectification:
        try:
            return cls(lens=FisheyeLens.from_dict(d["lens"]), K=np.asarray(d["K"], np.float64))
        except (KeyError, TypeError, ValueError) as exc:
            raise CalibrationError(f"a rectification needs a lens and K ({exc})") from None


@dataclass(frozen=True, kw_only=True, eq=False)
class CalibratedRig:
    """A calibration's rig and the fisheye lenses of its cameras that have one: those
    cameras are in ``rig`` as the pinhole cameras their frames are rectified to
    (``pinhole_camera``)."""

    rig: Rig
    lenses: dict[str, FisheyeLens]

    def pinhole_only(self, where: object) -> Rig:
        """The rig, when no camera has a fisheye lens; ``CalibrationError`` naming ``where``
        otherwise (its frames must be rectified: ``edgerecon import`` sets that up)."""
        if self.lenses:
            raise CalibrationError(
                f"{where}: cameras {', '.join(self.lenses)} have fisheye lenses: import the "
                "calibration with its frames (edgerecon import), which rectifies them"
            )
        return self.rig


def lens_camera(
    name: str,
    width: int,
    height: int,
    K: NDArray[np.float64],
    R: NDArray[np.float64],
    t: NDArray[np.float64],
    dist: NDArray[np.float64],
    *,
    fisheye: bool,
) -> tuple[Camera, FisheyeLens | None]:
    """A calibrated camera as a rig holds it: with OpenCV's plumb-bob model (``dist`` k1 k2
    p1 p2 [k3]) as it is; with OpenCV's fisheye model (``dist`` k1..k4) as the pinhole
    camera its frames are rectified to, and its lens."""
    if fisheye:
        lens = FisheyeLens(width=width, height=height, K=K, D=dist)
        return pinhole_camera(name, lens, R, t), lens
    return Camera(name=name, width=width, height=height, K=K, R=R, t=t, dist=dist), None


def calibrated_rig(made: Iterable[tuple[Camera, FisheyeLens | None]], **rig: Any) -> CalibratedRig:
    """The rig of ``lens_camera``'s cameras (``rig``: ``Rig``'s other fields) and their
    lenses."""
    pairs = list(made)
    return CalibratedRig(
        rig=Rig(cameras=tuple(c for c, _ in pairs), **rig),
        lenses={c.name: lens for c, lens in pairs if lens is not None},
    )


def pinhole_camera(
    name: str,
    lens: FisheyeLens,
    R: NDArray[np.float64],
    t: NDArray[np.float64],
    balance: float = 0.0,
) -> Camera:
    """The pinhole camera a fisheye lens's frames are rectified to (``FisheyeLens.pinhole_K``),
    with the camera's pose."""
    return Camera(
        name=name,
        width=lens.width,
        height=lens.height,
        K=lens.pinhole_K(balance),
        R=R,
        t=t,
        dist=np.zeros(5),
    )
