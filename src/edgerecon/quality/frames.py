"""Is a frame usable at all? Black (lights out, lens cap), saturated (blinded) and textureless
(a uniform wall, a covered lens) frames carry nothing to reconstruct, and the scene stage
would take all of them for foreground (a lit background model sees every pixel change), so
the hull fills the room and the task costs many times the usual. They are found here, on a
subsample of the frame (~1 ms per camera), before any stage runs.
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry.camera import Camera, rotation_angle_deg
from edgerecon.types import FrameSet, Image

_EYE = np.eye(3)

#: Values of :func:`frame_defect`.
DEFECTS = ("black", "saturated", "textureless")


@dataclass(frozen=True, kw_only=True)
class FrameCheckConfig:
    """Thresholds of :func:`frame_defect` on 8-bit luminance."""

    black_max_level: float = 16.0
    """A frame whose 99th luminance percentile is below this is black (0-255)."""
    saturated_min_level: float = 240.0
    """A frame whose 1st luminance percentile is above this is saturated (0-255)."""
    textureless_max_std: float = 3.0
    """A frame whose luminance standard deviation is below this is textureless (0-255; sensor
    noise alone is ~1-2, real scenes measured 12-60 on the synthetic and real datasets)."""
    sample_px: int = 160
    """The check reads about this many pixels along the longer side (a strided subsample)."""
    frozen_after_s: float = 2.0
    """A camera whose frames have not changed bit for bit (on that subsample) over this many
    seconds of the stream while another camera's did is *frozen*: a stuck camera, or a
    stream or decoder repeating its last frame (:class:`FrozenCameras`); 0 = no check.
    Sensor noise changes a working camera's every frame."""
    moved_min_shift: float = 0.004
    """A camera whose whole view shifted (its static scene, against its own recent frames)
    by at least this share of the frame's longer side is *moved* (knocked, its mount
    slipped): 1 px of a 256-px thumbnail, 5 px of 1280 (about 0.3 degrees of a 1280-wide
    camera with a 90-degree field of view) (:class:`MovedCameras`); 0 = no check."""
    moved_after_frames: int = 3
    """... once that many updates in a row show the same shift (a person or a board that
    fills the frame moves on; a moved camera's view stays moved)."""
    stabilise: bool = True
    """A camera whose view moved (knocked: from that move on, unless the run re-poses moved
    cameras, ``--adopt-repairs``; a mount that sways: from the move after which it keeps
    moving in every run) has each frame turned back onto its view before its first move
    (:class:`Stabiliser`: the turn that best moves its tiles back, as a rotation about its
    centre of projection, which needs no depth): the calibration fits its frames again."""

    def __post_init__(self) -> None:
        if not 0 <= self.black_max_level < self.saturated_min_level <= 255:
            raise ValueError(
                "FrameCheckConfig: need 0 <= black_max_level < saturated_min_level <= 255, got "
                f"{self.black_max_level}, {self.saturated_min_level}"
            )
        if self.textureless_max_std < 0:
            raise ValueError(
                f"FrameCheckConfig.textureless_max_std must be >= 0, got {self.textureless_max_std}"
            )
        if self.sample_px < 8:
            raise ValueError(f"FrameCheckConfig.sample_px must be >= 8, got {self.sample_px}")
        if not 0 <= self.moved_min_shift < 0.25:
            raise ValueError(
                f"FrameCheckConfig.moved_min_shift must be in [0, 0.25), got {self.moved_min_shift}"
            )
        if self.moved_after_frames < 1:
            raise ValueError(
                f"FrameCheckConfig.moved_after_frames must be >= 1, got {self.moved_after_frames}"
            )
        if not self.frozen_after_s >= 0:
            raise ValueError(
                f"FrameCheckConfig.frozen_after_s must be >= 0, got {self.frozen_after_s}"
            )


def local_contrast(
    image: NDArray[np.floating] | NDArray[np.uint8], size: int
) -> NDArray[np.float32]:
    """Grey-level standard deviation in a ``size`` x ``size`` box around each pixel (the
    photo check's texture, the online estimate's textured pixels)."""
    im = np.asarray(image, np.float32)
    # (The channels' mean as NumPy's mean over the last axis computes it, without its
    # strided reduction: 3.4 -> 0.2 ms at 480x270.)
    grey = ((im[..., 0] + im[..., 1]) + im[..., 2]) / np.float32(3) if im.ndim == 3 else im
    m1 = cv2.blur(grey, (size, size))
    m2 = cv2.blur(grey * grey, (size, size))
    return np.sqrt(np.maximum(m2 - m1 * m1, 0.0)).astype(np.float32)


def _sample(image: Image, config: FrameCheckConfig) -> Image:
    """The strided subsample the checks read (about ``sample_px`` along the longer side)."""
    h, w = image.shape[:2]
    stride = max(1, max(h, w) // config.sample_px)
    return image[::stride, ::stride]


def frame_defect(image: Image, config: FrameCheckConfig | None = None) -> str | None:
    """``"black"``, ``"saturated"``, ``"textureless"`` or None (usable) for one BGR frame."""
    config = config or FrameCheckConfig()
    sample = _sample(image, config)
    gray = cv2.cvtColor(sample, cv2.COLOR_BGR2GRAY) if sample.ndim == 3 else sample
    p1, p99 = np.percentile(gray, (1, 99))
    if p99 < config.black_max_level:
        return "black"
    if p1 > config.saturated_min_level:
        return "saturated"
    if float(gray.std()) < config.textureless_max_std:
        return "textureless"
    return None


def frame_defects(
    frames: FrameSet, config: FrameCheckConfig | None = None
) -> tuple[str | None, ...]:
    """Per camera of ``frames``: its defect, or None (usable, or no frame)."""
    return tuple(None if im is None else frame_defect(im, config) for im in frames.images)


def without_defective(frames: FrameSet, defects: Sequence[str | None]) -> FrameSet:
    """``frames`` with the defective cameras' images dropped (as a camera without a frame)."""
    if not any(defects):
        return frames
    images = tuple(None if d else im for im, d in zip(frames.images, defects, strict=True))
    return dataclasses.replace(frames, images=images)


class FrozenCameras:
    """Which cameras' frames stopped changing while the others' went on.

    A camera that hangs, or a stream or decoder that repeats its last frame, keeps delivering
    an image: nothing else finds it, and the tasks reconstruct that camera's silhouette and
    colours of the moment it froze. :meth:`update`, called with each task's frames (in time
    order), compares a hash of each camera's check subsample with its previous one: a camera
    whose frame has been the same bit for bit over ``frozen_after_s`` seconds of the stream
    while another camera's changed in that time is frozen, until its frame changes. A scene
    where nothing changes in any camera (noise-free frames of a still scene, a paused
    stream) freezes nobody; a camera without a frame in an update (stalled, unusable) keeps
    its state. About 10 microseconds per camera.

    The tasks keep a frozen camera: on a 4-camera rig 90 degrees apart its stale view still
    helps the hull and the depths more than three cameras alone (hd4 at 1080p, one camera
    frozen for the last 2 s of 3.6, the tasks after it froze: foreground F at 0.5 % 0.357 ->
    0.276 with it kept, 0.143 with it left out; docs/BENCHMARKS.md).
    """

    def __init__(self, config: FrameCheckConfig | None = None, *, fps: float) -> None:
        self.config = config or FrameCheckConfig()
        self.fps = fps
        """The stream's rate: a frame set without a timestamp is at ``time_index / fps``."""
        self._hash: dict[int, bytes] = {}
        self._since: dict[int, float] = {}
        """Per camera: the stream time its current frame was first seen ..."""
        self._since_index: dict[int, int] = {}
        """... and that frame's time index."""
        self._frozen: set[int] = set()

    @property
    def frozen(self) -> frozenset[int]:
        """Indices of the cameras frozen as of the last update."""
        return frozenset(self._frozen)

    def since(self, camera: int) -> int | None:
        """The time index of the first update that gave ``camera``'s current frame (None:
        none seen yet)."""
        return self._since_index.get(camera)

    def update(self, frames: FrameSet) -> tuple[list[int], list[int]]:
        """Take the next frames; return the cameras that froze and those whose frames
        changed again since the last update (indices, ascending)."""
        if self.config.frozen_after_s <= 0:
            return [], []
        seconds = frames.timestamp_s
        if seconds is None:
            seconds = frames.time_index / self.fps
        absent = set()
        for i, image in enumerate(frames.images):
            if image is None:  # no frame (stalled, unusable): not judged this time
                absent.add(i)
                continue
            sample = np.ascontiguousarray(_sample(image, self.config))
            digest = hashlib.blake2b(sample.data, digest_size=16).digest()
            if self._hash.get(i) != digest:
                self._hash[i] = digest
                self._since[i] = seconds
                self._since_index[i] = frames.time_index
        now_frozen = {
            i
            for i, since in self._since.items()
            if i not in absent
            and seconds - since >= self.config.frozen_after_s
            and any(other > since for j, other in self._since.items() if j != i)
        } | (self._frozen & absent)
        froze = sorted(now_frozen - self._frozen)
        thawed = sorted(self._frozen - now_frozen)
        self._frozen = now_frozen
        return froze, thawed


@dataclass(frozen=True, kw_only=True)
class CameraMove:
    """A camera whose view moved (:class:`MovedCameras`): the image motion of its static
    scene, at the frame's resolution, as a rotation about the image centre then a shift."""

    camera: int
    time_index: int
    """The first update that showed the move."""
    shift_px: tuple[float, float]
    """The image centre's motion (x right, y down), pixels of the frame."""
    roll_deg: float
    """The turn about the image centre (positive: clockwise in the image)."""
    across_stop: bool = False
    """The move lies between a reference restored from before a stop (``restore``) and the
    first frame after it: the camera moved while the run was stopped (or at that frame)."""

    def magnitude_px(self, size: tuple[int, int]) -> float:
        """The largest motion of a pixel of a ``size`` (width, height) frame."""
        return float(self.shift_px[0] ** 2 + self.shift_px[1] ** 2) ** 0.5 + abs(
            np.radians(self.roll_deg)
        ) * 0.5 * float(np.hypot(*size))


class MovedCameras:
    """Which cameras' views moved: a camera knocked or whose mount slipped during a run.

    The calibration check (``quality.calibration``) tells a moved camera from its matches
    with the others, in the back-end's idle time, at most every ``calib_check_s``; this
    tells that *some* camera's view moved at once, from that camera's frames alone, so that
    the check comes at once (on frames after the move). Per camera,
    a thumbnail (256 px along the longer side, grey) is compared with a running average of
    its earlier thumbnails, tile by tile (3 x 3 tiles, OpenCV's phase correlation): the
    tiles whose correlation peak is clear give their shift, and a rotation about the centre
    and a shift (least squares) that moves at least 5 of them (and two thirds of those with
    a clear peak) to within half a pixel of where they went is the view's motion. A motion
    of at least ``moved_min_shift`` that stays the same over ``moved_after_frames`` updates
    is a move: one :class:`CameraMove`, and the camera's new view is its reference from
    then on. People and objects move a part of the frame, or the whole of it in ways no
    single turn explains, and not the same way three times in a row; the running average
    follows light that changes. About 1 ms per camera (1280x720). A run keeps the
    references over a stop (:meth:`references`, :meth:`restore`): a camera turned while the
    run was stopped is a move at the first frames after ``--resume``.

    Measured (docs/BENCHMARKS.md): caliscope_charuco's 111 frame sets (a person and a board
    waved up to the lens) and utrecht4cam's move no camera; a 1-degree turn of any one of
    caliscope_charuco's cameras about any axis, and the synthetic 2-degree knock, is a move
    at the first frame after it once ``moved_after_frames`` have shown it.
    """

    _THUMB_PX = 256
    _GRID = 3
    _MIN_RESPONSE = 0.15
    _MIN_TILES = 5
    _AVERAGE = 0.1

    def __init__(self, config: FrameCheckConfig | None = None) -> None:
        self.config = config or FrameCheckConfig()
        self._ref: dict[int, NDArray[np.float32]] = {}
        self._window: dict[tuple[int, int], NDArray[np.float32]] = {}
        self._pending: dict[int, tuple[int, NDArray[np.float64], int]] = {}
        """Per camera: the first update of a motion not yet reported, its tiles' shifts
        and how many updates in a row showed it."""
        self._before: dict[int, NDArray[np.float32]] = {}
        """Per camera that moved: its reference before its first move."""
        self._restored: set[int] = set()
        """Cameras whose reference was restored and who have had no update since."""
        self._resumed_at: dict[int, int] = {}
        """Per restored camera: the time index of its first update after the restore."""

    def references(self) -> dict[int, NDArray[np.uint8]]:
        """Each camera's reference view now (grey thumbnail, rounded to whole grey levels):
        what a run keeps over a stop (``runtime.state.OutputFolder.write_views``) so that a
        camera moved while it was stopped is seen when it goes on (``restore``)."""
        return {i: _grey_bytes(r) for i, r in self._ref.items()}

    def restore(self, references: Mapping[int, NDArray[np.generic]]) -> None:
        """Start from ``references`` (those of :meth:`references`, from before a stop):
        a camera whose first frames after it show its view moved from them is a move
        (``CameraMove.across_stop``). A camera whose frames have another size starts afresh
        (its reference is replaced at its first frame)."""
        for i, ref in references.items():
            self._ref[int(i)] = np.asarray(ref, np.float32).copy()
            self._pending.pop(int(i), None)
            self._restored.add(int(i))

    def _thumbnail(self, image: Image) -> NDArray[np.float32]:
        return thumbnail(image, self._THUMB_PX)

    def _tiles(
        self, ref: NDArray[np.float32], now: NDArray[np.float32]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        return tile_shifts(ref, now, self._GRID, self._MIN_RESPONSE, self._window)

    def first_reference(self, camera: int) -> NDArray[np.float32] | None:
        """``camera``'s view before its first move this run (its reference then), or its
        reference now when it has not moved (None: no frame of it yet)."""
        ref = self._before.get(camera, self._ref.get(camera))
        return None if ref is None else ref.copy()

    def _moved(self, shifts: NDArray[np.float64], least: float) -> NDArray[np.bool_] | None:
        """The tiles that moved, when they are the view's motion (None: not)."""
        clear = ~np.isnan(shifts[:, 0])
        size = np.hypot(shifts[:, 0], shifts[:, 1])
        moved = clear & (size >= least)
        still = clear & (size < least / 2)
        if moved.sum() < self._MIN_TILES or moved.sum() < 3 * still.sum():
            return None
        return moved

    def update(self, frames: FrameSet) -> list[CameraMove]:
        """Take the next frames (in time order); return the cameras whose move they
        confirm."""
        config = self.config
        if config.moved_min_shift <= 0:
            return []
        out = []
        for i, image in enumerate(frames.images):
            if image is None:
                continue  # no frame (stalled, unusable): not judged this time
            now = self._thumbnail(image)
            if i in self._restored:
                self._restored.discard(i)
                self._resumed_at[i] = frames.time_index
            ref = self._ref.get(i)
            if ref is None or ref.shape != now.shape:
                self._ref[i] = now
                self._pending.pop(i, None)
                continue
            h, w = now.shape
            centres, shifts = self._tiles(ref, now)
            moved = self._moved(shifts, config.moved_min_shift * max(h, w))
            if moved is None:
                self._pending.pop(i, None)
                cv2.accumulateWeighted(now, ref, self._AVERAGE)  # follows the light
                continue
            first, seen, count = self._pending.get(i, (frames.time_index, shifts, 0))
            # The same motion: the tiles that moved then moved alike now (a person or a
            # board moves on; a turned camera's view stays where it went).
            both = moved & ~np.isnan(seen[:, 0])
            gap = np.hypot(*(shifts[both] - seen[both]).T)
            alike = gap <= np.maximum(1.0, 0.25 * np.hypot(*seen[both].T))
            if count and alike.sum() < self._MIN_TILES:
                first, seen, count = frames.time_index, shifts, 0
            count += 1
            if count < config.moved_after_frames:
                self._pending[i] = (first, seen, count)
                continue
            self._pending.pop(i, None)
            self._before.setdefault(i, ref)
            self._ref[i] = now  # the new view
            m = _rigid_fit(centres[moved], centres[moved] + shifts[moved])
            centre = np.array([w / 2, h / 2])
            shift = centre @ m[:, :2].T + m[:, 2] - centre
            full = image.shape[1] / w
            out.append(
                CameraMove(
                    camera=i,
                    time_index=first,
                    shift_px=(round(float(shift[0] * full), 2), round(float(shift[1] * full), 2)),
                    roll_deg=round(float(np.degrees(np.arctan2(m[1, 0], m[0, 0]))), 3),
                    across_stop=self._resumed_at.get(i) == first,
                )
            )
        return out


def _grey_bytes(grey: NDArray[np.float32]) -> NDArray[np.uint8]:
    """A grey thumbnail rounded to whole grey levels (what a run keeps over a stop)."""
    return np.asarray(np.clip(np.rint(grey), 0, 255), np.uint8)


def thumbnail(image: Image, longer_px: int = 256) -> NDArray[np.float32]:
    """The frame's grey thumbnail: an area average by a whole factor (OpenCV's fast path:
    0.9 ms at 1280x720, 1.7 at 1920x1080), at least ``longer_px`` along the longer side."""
    h, w = image.shape[:2]
    k = max(1, max(h, w) // longer_px)
    size = (w // k, h // k)
    small = cv2.resize(image[: size[1] * k, : size[0] * k], size, interpolation=cv2.INTER_AREA)
    grey = cv2.cvtColor(small, cv2.COLOR_BGR2GRAY) if small.ndim == 3 else small
    return np.asarray(grey, np.float32)


def tile_shifts(
    ref: NDArray[np.float32],
    now: NDArray[np.float32],
    grid: int,
    min_response: float,
    windows: dict[tuple[int, int], NDArray[np.float32]] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The centres of ``grid`` x ``grid`` tiles and their shifts from ``ref`` to ``now``
    (OpenCV's phase correlation with a Hann window; NaN where the peak's response is under
    ``min_response``). ``windows``: a cache of the windows by tile size."""
    h, w = now.shape
    th, tw = h // grid, w // grid
    win = None if windows is None else windows.get((th, tw))
    if win is None:
        win = np.asarray(cv2.createHanningWindow((tw, th), cv2.CV_32F), np.float32)
        if windows is not None:
            windows[(th, tw)] = win
    centres = np.empty((grid * grid, 2))
    shifts = np.full((grid * grid, 2), np.nan)
    for r in range(grid):
        for c in range(grid):
            k = r * grid + c
            ys, xs = slice(r * th, (r + 1) * th), slice(c * tw, (c + 1) * tw)
            (dx, dy), response = cv2.phaseCorrelate(ref[ys, xs], now[ys, xs], win)
            centres[k] = ((c + 0.5) * tw, (r + 0.5) * th)
            if response >= min_response:
                shifts[k] = (dx, dy)
    return centres, shifts


def pixel_rays(
    points: NDArray[np.float64], K: NDArray[np.float64], dist: NDArray[np.float64] | None = None
) -> NDArray[np.float64]:
    """Unit rays (n, 3) through pixels ``points`` (n, 2) of a camera with intrinsics ``K``
    and OpenCV's lens distortion ``dist`` (None or zeros: a pinhole)."""
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    if dist is None or not np.any(dist):
        xy = (pts - K[:2, 2]) @ np.linalg.inv(K[:2, :2]).T
    else:
        xy = cv2.undistortPoints(pts.reshape(-1, 1, 2), K, dist).reshape(-1, 2)
    rays = np.c_[xy, np.ones(len(xy))]
    return np.asarray(rays / np.linalg.norm(rays, axis=1, keepdims=True), np.float64)


def ray_pixels(
    rays: NDArray[np.float64], K: NDArray[np.float64], dist: NDArray[np.float64] | None = None
) -> NDArray[np.float64]:
    """Pixels (n, 2) where rays (n, 3) in front of the camera meet its image."""
    if dist is None or not np.any(dist):
        uvw = rays @ K.T
        return np.asarray(uvw[:, :2] / uvw[:, 2:], np.float64)
    zero = np.zeros(3)
    px, _ = cv2.projectPoints(np.ascontiguousarray(rays, np.float64), zero, zero, K, dist)
    return np.asarray(px.reshape(-1, 2), np.float64)


def turned_back(
    image: NDArray[Any],
    R: NDArray[np.float64],
    K: NDArray[np.float64],
    dist: NDArray[np.float64] | None,
    step: int = 8,
    cache: dict[Any, tuple[tuple[int, int], NDArray[np.float64]]] | None = None,
    key: Any = None,
) -> NDArray[Any]:
    """``image`` (of a camera with intrinsics ``K``, lens distortion ``dist``) turned back
    by the camera turn ``R`` (its rays ``R r`` from the view wanted): each pixel of that
    view takes the image's pixel that its ray, turned, meets; the border uncovered repeats
    the edge. A pinhole: one homography warp; a distorted lens: the map on a grid of
    ``step`` pixels (its rays kept in ``cache`` under ``key``; OpenCV's projection of
    the turned rays costs about 0.5 us a point), interpolated, then one remap."""
    h, w = image.shape[:2]
    if dist is None or not np.any(dist):
        H = K @ R @ np.linalg.inv(K)  # wanted pixel -> this image's pixel
        return np.asarray(
            cv2.warpPerspective(
                image,
                H,
                (w, h),
                flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                borderMode=cv2.BORDER_REPLICATE,
            ),
            image.dtype,
        )
    gh, gw = -(-h // step), -(-w // step)
    grid = None if cache is None else cache.get(key)
    if grid is None or grid[0] != (h, w):
        # cv2.resize takes each grid point as the centre of its cell.
        xs = (np.arange(gw) + 0.5) * (w / gw) - 0.5
        ys = (np.arange(gh) + 0.5) * (h / gh) - 0.5
        u, v = np.meshgrid(xs, ys)
        grid = ((h, w), pixel_rays(np.stack([u.ravel(), v.ravel()], axis=1), K, dist))
        if cache is not None:
            cache[key] = grid
    src = ray_pixels(grid[1] @ R.T, K, dist).reshape(gh, gw, 2).astype(np.float32)
    maps = cv2.resize(src, (w, h), interpolation=cv2.INTER_LINEAR)
    return np.asarray(
        cv2.remap(image, maps, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE),
        image.dtype,
    )


def rotation_between(ra: NDArray[np.float64], rb: NDArray[np.float64]) -> NDArray[np.float64]:
    """The camera turn R (3x3) that takes rays ``ra`` to ``rb`` (n, 3): ``rb ~ R ra``, least
    squares (Wahba's problem, by SVD)."""
    u, _, vt = np.linalg.svd(ra.T @ rb)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    return np.asarray(vt.T @ np.diag([1.0, 1.0, d]) @ u.T, np.float64)


class Stabiliser:
    """Frames of the cameras whose views moved (a knock; a mount that sways, a camera on a
    pole in the wind), turned back onto a reference view: per frame, the shifts of 4 x 4
    tiles of its grey thumbnail against the reference (phase correlation), the camera turn
    that best explains them (:func:`rotation_between` of every tile; where some do not
    follow it, a person or a board across them, of the pair of tiles that most others
    follow; then again of those within ``_MAX_RESIDUAL``, at least ``_MIN_TILES`` of
    them), and the frame warped back by the turn's homography (``K R K^-1``, in one OpenCV
    warp; the border it uncovers repeats the edge). A turn about the centre of projection
    moves every pixel by the same homography whatever its depth, so the calibration fits
    the warped frame again; a camera that also shifts (a sway's lever arm) keeps that
    part. A lens's distortion is taken off the tiles' rays and put back in the warp (a
    map computed on a 16-pixel grid and interpolated, then one remap). A frame whose tiles give no turn is kept as it is
    (said in the result). About 3-10 ms per camera (thumbnail, 16 correlations, the warp
    at the frame's size)."""

    _THUMB_PX = 256
    _GRID = 4
    _MIN_RESPONSE = 0.1
    _MIN_TILES = 6
    _MAX_RESIDUAL = 0.75
    """Thumbnail pixels."""
    _KEEP_TURNS = 1000
    """Turns kept per camera (``steady_turn``)."""
    _MAP_STEP = 16
    """A distorted lens's warp of a frame is computed on a grid of this step (pixels) and
    interpolated (8 for the thumbnail)."""

    def __init__(self) -> None:
        self._ref: dict[int, tuple[NDArray[np.float32], Camera]] = {}
        """Per camera: its reference thumbnail, its calibration."""
        self._window: dict[tuple[int, int], NDArray[np.float32]] = {}
        self._grid: dict[Any, tuple[tuple[int, int], NDArray[np.float64]]] = {}
        """Per distorted camera and image kind: the coarse grid's pixels' rays
        (``turned_back``)."""
        self._turns: dict[int, deque[NDArray[np.float64]]] = {}
        """Per camera: the turns taken off its frames since ``start`` or ``forget``."""

    @property
    def cameras(self) -> frozenset[int]:
        """The cameras being stabilised."""
        return frozenset(self._ref)

    def references(self) -> dict[int, NDArray[np.uint8]]:
        """Each stabilised camera's reference view (rounded to whole grey levels): what a
        run keeps over a stop (``start`` again with it after ``--resume``)."""
        return {i: _grey_bytes(ref) for i, (ref, _) in self._ref.items()}

    def start(self, camera: int, reference: NDArray[np.float32], calibration: Camera) -> None:
        """Stabilise ``camera`` from now on onto ``reference`` (a grey thumbnail as
        :func:`thumbnail` makes them); ``calibration``: its camera of the rig (intrinsics
        and lens distortion; ``Camera.resized`` to each frame's size)."""
        self._ref[camera] = (np.asarray(reference, np.float32), calibration)
        for kind in ("thumb", "frame"):
            self._grid.pop((camera, kind), None)
        self.forget(camera)

    def _lens(
        self, camera: int, image: Image
    ) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
        """``camera``'s intrinsics at ``image``'s size and its distortion (None: none)."""
        cam = self._ref[camera][1]
        cam = cam.resized(image.shape[1], image.shape[0])
        return cam.K, (cam.dist if cam.has_distortion else None)

    def forget(self, camera: int) -> None:
        """Forget the turns taken off ``camera``'s frames so far (its view moved again)."""
        self._turns[camera] = deque(maxlen=self._KEEP_TURNS)

    def steady_turn(
        self, camera: int, *, min_frames: int = 3, max_spread_deg: float = 0.2
    ) -> NDArray[np.float64] | None:
        """The turn taken off ``camera``'s frames since ``start`` / ``forget`` when it held
        still (at least ``min_frames`` measured, none more than ``max_spread_deg`` from
        their mean: a camera knocked once, not one that sways), as a rotation (the mean of
        the turns, projected onto the rotations); else None. The camera's rays in its
        frames are ``R r``: the camera re-aimed so is ``R R_cw``, ``R t``."""
        turns = list(self._turns.get(camera, ()))
        if len(turns) < min_frames:
            return None
        u, _, vt = np.linalg.svd(np.sum(turns, axis=0))
        mean = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
        spread = max(rotation_angle_deg(T, mean) for T in turns)
        return mean if spread <= max_spread_deg else None

    def turn(self, camera: int, image: Image) -> NDArray[np.float64] | None:
        """The turn R of ``camera`` from its reference to ``image`` (its rays ``R r``;
        None: not measured). Twice: the thumbnail turned back by the first turn gives what
        is left of it (phase correlation's sub-pixel peak leans to whole pixels: a 1-degree
        turn of a real 720p camera measured 0.88 degrees in one pass)."""
        ref = self._ref[camera][0]
        K, dist = self._lens(camera, image)
        now = thumbnail(image, self._THUMB_PX)
        if now.shape != ref.shape:
            return None
        k = image.shape[1] / now.shape[1]  # thumbnail pixel -> frame pixel
        # The thumbnail's intrinsics (its pixel j covers the frame's j k .. j k + k - 1).
        Kt = np.array(
            [
                [K[0, 0] / k, K[0, 1] / k, (K[0, 2] + 0.5) / k - 0.5],
                [0.0, K[1, 1] / k, (K[1, 2] + 0.5) / k - 0.5],
                [0.0, 0.0, 1.0],
            ]
        )
        first = self._fit(ref, now, Kt, dist)
        if first is None:
            return None
        back = turned_back(now, first, Kt, dist, 8, self._grid, (camera, "thumb"))
        rest = self._fit(ref, back, Kt, dist)
        return first if rest is None else first @ rest

    def _fit(
        self,
        ref: NDArray[np.float32],
        now: NDArray[np.float32],
        K: NDArray[np.float64],
        dist: NDArray[np.float64] | None,
    ) -> NDArray[np.float64] | None:
        """The turn from ``ref`` to ``now`` (thumbnails with intrinsics ``K``) that most
        tiles follow (None: fewer than ``_MIN_TILES``)."""
        centres, shifts = tile_shifts(ref, now, self._GRID, self._MIN_RESPONSE, self._window)
        clear = ~np.isnan(shifts[:, 0])
        if clear.sum() < self._MIN_TILES:
            return None
        # A tile's centre as a pixel position (its pixels' centres are 0, 1, ...).
        a, b = centres[clear] - 0.5, centres[clear] - 0.5 + shifts[clear]
        ra, rb = pixel_rays(a, K, dist), pixel_rays(b, K, dist)

        def followers(R: NDArray[np.float64]) -> NDArray[np.bool_]:
            residual = np.hypot(*(ray_pixels(ra @ R.T, K, dist) - b).T)
            return np.asarray(residual <= self._MAX_RESIDUAL)

        # Tiles a person or a board moved do not follow the turn: when the turn of all the
        # tiles leaves some, the turn of the pair of tiles that most others follow (every
        # pair: at most 120), then of those.
        best = followers(rotation_between(ra, rb))
        if not best.all():
            for i, j in itertools.combinations(range(len(a)), 2):
                keep = followers(rotation_between(ra[[i, j]], rb[[i, j]]))
                if keep.sum() > best.sum():
                    best = keep
        for _ in range(2):
            if best.sum() < self._MIN_TILES:
                return None
            R = rotation_between(ra[best], rb[best])
            best = followers(R)
        return R if best.sum() >= self._MIN_TILES else None

    def apply(self, frames: FrameSet) -> tuple[FrameSet, dict[int, float | None]]:
        """``frames`` with each stabilised camera's image turned back onto its reference;
        per stabilised camera with an image, the turn taken off (degrees; None: no turn
        measured, the image as it was)."""
        if not self._ref:
            return frames, {}
        images = list(frames.images)
        turned: dict[int, float | None] = {}
        for i in sorted(self._ref):
            image = images[i] if i < len(images) else None
            if image is None:
                continue
            R = self.turn(i, image)
            if R is None:
                turned[i] = None
                continue
            turned[i] = round(rotation_angle_deg(R, _EYE), 3)
            self._turns.setdefault(i, deque(maxlen=self._KEEP_TURNS)).append(R)
            K, dist = self._lens(i, image)
            images[i] = turned_back(image, R, K, dist, self._MAP_STEP, self._grid, (i, "frame"))
        return dataclasses.replace(frames, images=tuple(images)), turned


def _rigid_fit(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """The rotation and shift (2x3) that take points ``a`` nearest ``b`` (least squares)."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    r = (u @ vt).T
    if np.linalg.det(r) < 0:
        vt[-1] *= -1
        r = (u @ vt).T
    return np.hstack([r, (cb - r @ ca)[:, None]])
