"""Synchronized frame sources: time index -> one BGR frame per camera.

A :class:`FrameSource` gives random access (``read(t)``) and streaming
(``iter_frames(start, stop, step)``) over the frames of a static multi-camera capture. Two
implementations share one per-camera reader interface:

* :class:`VideoFrameSource`: one video file per camera (``cv2.VideoCapture``). Each video is
  decoded once, front to back: reading ``t`` after ``t' < t`` skips the frames in between
  with ``grab()`` (no colour conversion). Frame seeking (``CAP_PROP_POS_FRAMES``) is never
  used: it is not frame-accurate on real files (on utrecht4cam cam4 it lands one frame off
  after frame ~320), so a read *before* the stream position restarts that video. Headers
  over-count frames (utrecht4cam: 428 claimed, 426 decode), so frame counts come from one
  ``grab()`` pass when a video is first opened (cached per file for the process), which
  also records each frame's timestamp: videos at different or variable frame rates are
  paired by time rather than by frame index (``VideoFrameSource``).
* :class:`ImageFolderFrameSource`: per camera a ``str.format`` pattern with an ``{index}``
  field (``frames/cam0/{index:06d}.png``), a folder whose sorted image files are the frames,
  or a single image file (a static camera with one frame).

Live cameras (``kind="stream"``) are :class:`edgerecon.io.streams.StreamFrameSource`.

The number of frames of a source is the minimum over its cameras (a warning is logged when
they differ). A frame that is missing or cannot be decoded raises ``DataError`` naming the
camera and the time index, unless the source was opened with ``missing="skip_camera"``:
then that camera's entry of ``FrameSet.images`` is ``None`` (the documented degradation the
online runtime uses; the task goes on with the other cameras). A frame whose size differs
from the rig's calibration raises ``CalibrationError`` whatever the policy: that is a
configuration error, not a dropped frame.

:class:`FrameSpec` is the picklable description of a source (kind + per-camera paths) that a
``Dataset`` carries; ``FrameSpec.open()`` builds the source.
"""

from __future__ import annotations

import functools
import logging
import os
import re
import struct
from abc import ABC, abstractmethod
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry.lens import Rectification
from edgerecon.types import CalibrationError, DataError, EdgereconError, FrameSet, Image

if TYPE_CHECKING:
    from edgerecon.geometry.camera import Rig
    from edgerecon.io.streams import StreamConfig

logger = logging.getLogger(__name__)

MissingPolicy = Literal["error", "skip_camera"]
MISSING_POLICIES: tuple[str, ...] = ("error", "skip_camera")

#: File extensions treated as images when a folder is listed.
IMAGE_EXTENSIONS = frozenset(
    {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm", ".exr"}
)
#: File extensions treated as videos when a camera folder is probed.
VIDEO_EXTENSIONS = frozenset({".avi", ".mp4", ".mkv", ".mov", ".m4v", ".mpg", ".mpeg", ".webm"})

#: Relative difference of the cameras' mean frame rates above which their videos are paired
#: by timestamps rather than by frame index (``VideoFrameSource``): 29.97 against 30 fps is 1e-3.
TIME_PAIRING_RATE_TOL = 5e-4

_INDEX_FIELD = re.compile(r"\{index(?::[^{}]*)?\}")


_warned: set[tuple[object, ...]] = set()


def _warn_once(key: tuple[object, ...]) -> bool:
    """True the first time ``key`` is seen (opening the same data twice warns once)."""
    if key in _warned:
        return False
    _warned.add(key)
    return True


class _FrameUnavailable(Exception):
    """A frame that is missing or cannot be decoded (internal; becomes DataError or None)."""


def natural_key(name: str) -> list[int | str]:
    """Sort key that orders ``img2.png`` before ``img10.png``."""
    return [int(p) if p.isdigit() else p.lower() for p in re.split(r"(\d+)", name)]


# --------------------------------------------------------------------------------- probing
@dataclass(frozen=True, kw_only=True, eq=False)
class VideoInfo:
    """What a video file's stream says about itself, with an exact frame count."""

    path: Path
    """The video file."""
    width: int
    """Frame width in pixels."""
    height: int
    """Frame height in pixels."""
    num_frames: int
    """Number of frames that decode, counted by decoding (headers are not trusted)."""
    fps: float | None
    """Frames per second from the header, None when the container does not say."""
    header_frames: int
    """Frame count claimed by the container header (may differ from ``num_frames``)."""
    timestamps_s: NDArray[np.float64] | None = None
    """Presentation time of each frame (seconds from the stream's start), read while the
    frames were counted; None when the container gives none that increase (then frame
    ``k`` is at ``k / fps``)."""

    @property
    def mean_fps(self) -> float | None:
        """Frames per second over the whole video, from the timestamps (else ``fps``)."""
        ts = self.timestamps_s
        if ts is None or len(ts) < 2 or not ts[-1] > ts[0]:
            return self.fps
        return float((len(ts) - 1) / (ts[-1] - ts[0]))

    @property
    def regular(self) -> bool:
        """Whether frame ``k`` is at ``k / fps`` within a quarter of a frame throughout (a
        constant frame rate); False for a variable frame rate or a drifting one."""
        ts, fps = self.timestamps_s, self.fps
        if ts is None or fps is None:
            return True
        ideal = ts[0] + np.arange(len(ts)) / fps
        return bool(np.max(np.abs(ts - ideal)) <= 0.25 / fps)


def probe_video(path: str | os.PathLike[str], camera: str | None = None) -> VideoInfo:
    """Open a video, read its size and fps, and count its frames by decoding them.

    Container headers over-count (utrecht4cam: 428 claimed, 426 decode) and OpenCV's frame
    seeking is not frame-accurate on real files (utrecht4cam cam4 lands one frame off after
    frame ~320), so the count comes from one ``grab()`` pass. It is cached per file (path,
    size, modification time) for the life of the process. Raises ``DataError`` if the file
    is missing, not a video, or has no decodable frame.
    """
    path = Path(path)
    who = f"camera {camera!r}: " if camera else ""
    try:
        st = path.stat()
    except FileNotFoundError:
        raise DataError(f"{who}video file not found: {path}") from None
    if not path.is_file():
        raise DataError(f"{who}video path is not a file: {path}")
    try:
        return _probe_video_cached(str(path.resolve()), st.st_size, st.st_mtime_ns)
    except DataError as exc:
        raise DataError(f"{who}{exc}") from None


@functools.lru_cache(maxsize=256)
def _probe_video_cached(path: str, size: int, mtime_ns: int) -> VideoInfo:
    cap = cv2.VideoCapture(path)
    try:
        if not cap.isOpened():
            raise DataError(f"cannot open video {path} (not a video, or unsupported codec)")
        width = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        height = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps_raw = float(cap.get(cv2.CAP_PROP_FPS))
        header = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        stamps: list[float] = []
        if width <= 0 or height <= 0:
            ok, frame = cap.read()
            if not ok or frame is None:
                raise DataError(f"video {path} has no decodable frame")
            height, width = frame.shape[:2]
            stamps.append(float(cap.get(cv2.CAP_PROP_POS_MSEC)))
        while cap.grab():
            stamps.append(float(cap.get(cv2.CAP_PROP_POS_MSEC)))
        count = len(stamps)
    finally:
        cap.release()
    if count == 0:
        raise DataError(f"video {path} has no decodable frame")
    if header > 0 and count != header:
        logger.debug("%s: header says %d frames, %d decode", path, header, count)
    ts: NDArray[np.float64] | None = np.asarray(stamps, np.float64) / 1000.0
    assert ts is not None
    if not (np.all(np.isfinite(ts)) and (len(ts) < 2 or np.all(np.diff(ts) > 0))):
        logger.debug("%s: frame timestamps do not increase; frames are k / fps", path)
        ts = None
    else:
        ts.setflags(write=False)
    return VideoInfo(
        path=Path(path),
        width=width,
        height=height,
        num_frames=count,
        fps=fps_raw if np.isfinite(fps_raw) and fps_raw > 0 else None,
        header_frames=header,
        timestamps_s=ts,
    )


def probe_image_size(path: str | os.PathLike[str]) -> tuple[int, int]:
    """(width, height) of an image file, from its header when it is PNG (cheap), otherwise
    by decoding it. Raises ``DataError`` if the file is missing or unreadable."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(24)
    except FileNotFoundError:
        raise DataError(f"image file not found: {path}") from None
    except OSError as exc:
        raise DataError(f"cannot read image {path}: {exc}") from None
    if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
        w, h = struct.unpack(">II", head[16:24])
        return int(w), int(h)
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DataError(f"cannot decode image {path}")
    return int(image.shape[1]), int(image.shape[0])


def _to_bgr8(image: np.ndarray) -> Image:
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    elif image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    if image.dtype != np.uint8:
        raise DataError(f"unsupported image dtype {image.dtype}")
    return image


# --------------------------------------------------------------------------------- readers
class _CameraReader(ABC):
    """Frames of one camera."""

    def __init__(self, camera: str) -> None:
        self.camera = camera
        self.num_rewinds = 0
        self.num_grabbed = 0
        self.num_decoded = 0

    @property
    @abstractmethod
    def num_frames(self) -> int: ...

    @property
    @abstractmethod
    def size(self) -> tuple[int, int]:
        """(width, height) of this camera's frames."""

    @property
    def fps(self) -> float | None:
        return None

    @property
    @abstractmethod
    def location(self) -> str:
        """Where the frames come from (for messages)."""

    def frame_location(self, t: int) -> str:
        """Where frame ``t`` comes from (for messages)."""
        return f"{self.location} (frame {t})"

    @abstractmethod
    def read(self, t: int) -> Image:
        """Frame ``t``; raises ``_FrameUnavailable(reason)``."""

    def close(self) -> None:  # noqa: B027 - optional hook
        pass


class _VideoReader(_CameraReader):
    def __init__(self, camera: str, path: Path) -> None:
        super().__init__(camera)
        self.info = probe_video(path, camera)
        self.path = path
        self._cap: cv2.VideoCapture | None = None
        self._pos: int | None = None  # index of the frame the next read() returns

    @property
    def num_frames(self) -> int:
        return self.info.num_frames

    @property
    def size(self) -> tuple[int, int]:
        return (self.info.width, self.info.height)

    @property
    def fps(self) -> float | None:
        return self.info.fps

    @property
    def location(self) -> str:
        return str(self.path)

    def _open(self) -> cv2.VideoCapture:
        if self._cap is None:
            self._cap = cv2.VideoCapture(str(self.path))
            if not self._cap.isOpened():
                self._cap = None
                raise _FrameUnavailable(f"cannot reopen video {self.path}")
            self._pos = 0
        return self._cap

    def read(self, t: int) -> Image:
        if self._pos is not None and t < self._pos:
            # Going back: restart the stream (frame seeking is not frame-accurate).
            self.close()
            self.num_rewinds += 1
        cap = self._open()
        pos = self._pos
        assert pos is not None
        while pos < t:
            if not cap.grab():
                self.close()
                raise _FrameUnavailable(f"video ends or is corrupt at frame {pos}")
            self.num_grabbed += 1
            pos += 1
        ok, frame = cap.read()
        if not ok or frame is None:
            self.close()
            raise _FrameUnavailable(f"frame does not decode from {self.path}")
        self.num_decoded += 1
        self._pos = t + 1
        return _to_bgr8(frame)

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None
            self._pos = None


class _ImageReader(_CameraReader):
    """A camera's frames as image files: a pattern with ``{index}``, a folder, or one file."""

    def __init__(self, camera: str, source: str | os.PathLike[str], start: int = 0) -> None:
        super().__init__(camera)
        text = str(source)
        self.start = start
        self._files: list[Path] | None = None
        self._pattern: str | None = None
        self._size: tuple[int, int] | None = None
        if _INDEX_FIELD.search(text):
            self._pattern = text
            try:
                text.format(index=start)
            except (KeyError, IndexError, ValueError) as exc:
                raise DataError(f"camera {camera!r}: bad frame pattern {text!r} ({exc})") from None
            self._num = _count_pattern(text, start)
            if self._num == 0:
                raise DataError(
                    f"camera {camera!r}: no frame matches {text!r} (from index {start})"
                )
        else:
            path = Path(text)
            if path.is_dir():
                files = sorted(
                    (p for p in path.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS),
                    key=lambda p: natural_key(p.name),
                )
                if not files:
                    raise DataError(f"camera {camera!r}: no image files in folder {path}")
                self._files = files
            elif path.is_file():
                self._files = [path]
            else:
                raise DataError(f"camera {camera!r}: frames not found: {path}")
            self._num = len(self._files)
        self._text = text

    @property
    def num_frames(self) -> int:
        return self._num

    @functools.cached_property
    def timestamps_s(self) -> NDArray[np.float64] | None:
        """Capture times (seconds) when the folder's files are named by them, as ROS bag
        exports and EuRoC-style datasets name them (``1403636579763555584.png``: 10 or more
        digits, increasing, spaced like frames once read as ns, us, ms or s); else None."""
        files = self._files
        if files is None or len(files) < 2:
            return None
        stems = [p.stem for p in files]
        if not all(x.isdigit() and 10 <= len(x) <= 19 for x in stems):
            return None
        raw = np.array([int(x) for x in stems], np.int64)
        steps = np.diff(raw)
        if np.any(steps <= 0):
            return None
        gap = float(np.median(steps))
        unit = next((u for u in (1e-9, 1e-6, 1e-3, 1.0) if 1e-3 <= gap * u <= 10.0), None)
        if unit is None:
            return None
        return np.asarray(raw * unit, np.float64)

    @property
    def location(self) -> str:
        return self._text

    def frame_location(self, t: int) -> str:
        return str(self.path(t))

    def path(self, t: int) -> Path:
        if self._files is not None:
            return self._files[t]
        assert self._pattern is not None
        return Path(self._pattern.format(index=self.start + t))

    @property
    def size(self) -> tuple[int, int]:
        if self._size is None:
            # The first frame that exists tells the size (a missing first frame must not hide
            # the others' size).
            last_error: DataError | None = None
            for t in range(min(self._num, 8)):
                try:
                    self._size = probe_image_size(self.path(t))
                    break
                except DataError as exc:
                    last_error = exc
            else:
                raise DataError(f"camera {self.camera!r}: {last_error}")
        return self._size

    def read(self, t: int) -> Image:
        path = self.path(t)
        if not path.is_file():
            raise _FrameUnavailable(f"file {path} is missing")
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if image is None:
            raise _FrameUnavailable(f"file {path} cannot be decoded")
        self.num_decoded += 1
        return _to_bgr8(image)


class _WrappedReader(_CameraReader):
    """A reader over another camera reader: time index t is the inner reader's frame
    ``frame_of(t)`` (the same by default); everything else is the inner reader's."""

    def __init__(self, inner: _CameraReader) -> None:
        super().__init__(inner.camera)
        self.inner = inner

    def frame_of(self, t: int) -> int:
        """The inner reader's frame of time index ``t``."""
        return t

    @property
    def num_frames(self) -> int:
        return self.inner.num_frames

    @property
    def size(self) -> tuple[int, int]:
        return self.inner.size

    @property
    def fps(self) -> float | None:
        return self.inner.fps

    @property
    def location(self) -> str:
        return self.inner.location

    def frame_location(self, t: int) -> str:
        return self.inner.frame_location(self.frame_of(t))

    def read(self, t: int) -> Image:
        return self.inner.read(self.frame_of(t))

    def close(self) -> None:
        self.inner.close()


class _OffsetReader(_WrappedReader):
    """A camera whose time index t is its own frame ``t + offset`` (synchronisation)."""

    def __init__(self, inner: _CameraReader, offset: int) -> None:
        super().__init__(inner)
        if offset < 0:
            raise ValueError(f"camera {inner.camera!r}: frame offset must be >= 0, got {offset}")
        self.offset = offset

    def frame_of(self, t: int) -> int:
        return t + self.offset

    @property
    def num_frames(self) -> int:
        return max(0, self.inner.num_frames - self.offset)

    @property
    def location(self) -> str:
        return f"{self.inner.location} (from its frame {self.offset})"


class _RectifiedReader(_WrappedReader):
    """A fisheye camera's frames remapped to its pinhole camera (``geometry.lens``)."""

    def __init__(self, inner: _CameraReader, rectification: Rectification) -> None:
        super().__init__(inner)
        self.rectification = rectification
        if tuple(inner.size) != rectification.lens.size:
            raise CalibrationError(
                f"camera {inner.camera!r}: frames in {inner.location} are "
                f"{inner.size[0]}x{inner.size[1]} but its fisheye lens is calibrated for "
                f"{rectification.lens.width}x{rectification.lens.height}"
            )

    def read(self, t: int) -> Image:
        return self.rectification(self.inner.read(t))


class _TimedReader(_WrappedReader):
    """A camera whose time index t is its frame nearest in time to ``start + t / fps``
    (frame-rate, variable-frame-rate and timestamp synchronisation, see ``VideoFrameSource``
    and ``ImageFolderFrameSource``). ``times``: its frames' times on the clock of ``start``
    (default: a video's timestamps with its frame ``offset`` at 0, and ``start`` 0)."""

    def __init__(
        self,
        inner: _CameraReader,
        fps: float,
        offset: int = 0,
        *,
        times: NDArray[np.float64] | None = None,
        start: float = 0.0,
    ) -> None:
        super().__init__(inner)
        if times is None:
            info = inner.info if isinstance(inner, _VideoReader) else None
            ts = None if info is None else info.timestamps_s
            if ts is None:
                rate = (info.fps if info is not None else None) or fps
                ts = np.arange(inner.num_frames, dtype=np.float64) / rate
            if not 0 <= offset < len(ts):
                raise ValueError(f"camera {inner.camera!r}: frame offset {offset} out of range")
            times = ts - ts[offset]
        self.offset = offset
        self.rate = fps
        self.start = float(start)
        self._times = np.asarray(times, np.float64)
        # Half of the camera's own median frame interval past its last frame still maps to it.
        later = self._times[self._times >= self.start - 1e-9]
        step = float(np.median(np.diff(later))) if len(later) > 1 else 1.0 / fps
        span = self._times[-1] - self.start
        self._num = max(0, int(np.floor((span + 0.5 * step) * fps + 1e-9)) + 1)

    def frame_of(self, t: int) -> int:
        """The camera's own frame index of time index ``t``."""
        target = self.start + t / self.rate
        k = int(np.searchsorted(self._times, target))
        if k > 0 and (
            k == len(self._times) or target - self._times[k - 1] <= self._times[k] - target
        ):
            k -= 1
        return k

    @property
    def num_frames(self) -> int:
        return self._num

    @property
    def fps(self) -> float | None:
        return self.rate

    @property
    def location(self) -> str:
        return self.inner.location + (f" (from its frame {self.offset})" if self.offset else "")


def _count_pattern(pattern: str, start: int) -> int:
    """Frames of an ``{index}`` pattern: ``max index - start + 1`` over the files that exist
    (gaps inside the range are missing frames, reported when read)."""
    directory, name = os.path.split(pattern)
    if _INDEX_FIELD.search(directory):
        # Index in a folder name: probe consecutive indices.
        n = 0
        while Path(pattern.format(index=start + n)).is_file():
            n += 1
        return n
    parts = _INDEX_FIELD.split(name)
    regex = re.compile(r"(\d+)".join(re.escape(p) for p in parts) + r"\Z")
    folder = Path(directory or ".")
    if not folder.is_dir():
        return 0
    best = -1
    for entry in os.scandir(folder):
        m = regex.match(entry.name)
        if not m:
            continue
        idx = int(m.group(1))
        if idx >= start and pattern.format(index=idx) == os.path.join(directory, entry.name):
            best = max(best, idx)
    return best - start + 1 if best >= 0 else 0


# --------------------------------------------------------------------------------- sources
class FrameSource(ABC):
    """Synchronized frames of N cameras, by time index.

    Use as a context manager (or call ``close()``) to release video decoders.
    """

    @property
    @abstractmethod
    def camera_names(self) -> tuple[str, ...]:
        """Camera names, in the order of ``FrameSet.images`` (the rig's order)."""

    @property
    @abstractmethod
    def num_frames(self) -> int:
        """Number of time indices (minimum over the cameras)."""

    @property
    @abstractmethod
    def fps(self) -> float | None:
        """Frames per second, or None when unknown (image folders)."""

    @property
    @abstractmethod
    def frame_sizes(self) -> dict[str, tuple[int, int]]:
        """(width, height) of each camera's frames."""

    @abstractmethod
    def read(self, t: int) -> FrameSet:
        """The frames of time index ``t`` (random access)."""

    @abstractmethod
    def check(self, t: int) -> tuple[FrameSet, dict[str, str]]:
        """Frame set ``t`` (unusable frames None) and camera -> what is wrong with its frame;
        never raises for a bad frame."""

    @property
    @abstractmethod
    def frame_counts(self) -> dict[str, int]:
        """Frames of each camera."""

    @property
    def camera_fps(self) -> dict[str, float | None]:
        """Each camera's own frame rate (here: the source's)."""
        return dict.fromkeys(self.camera_names, self.fps)

    @abstractmethod
    def iter_frames(
        self, start: int = 0, stop: int | None = None, step: int = 1
    ) -> Iterator[FrameSet]:
        """Stream the frame sets ``start, start + step, ... < stop`` (default: to the end)."""

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release decoders (the source can still be read afterwards: it reopens them)."""

    def __len__(self) -> int:
        return self.num_frames

    def __enter__(self) -> FrameSource:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def _innermost(reader: _CameraReader) -> _CameraReader:
    """The file reader under a reader's wrappers (offset, timing, rectification)."""
    while isinstance(reader, _WrappedReader):
        reader = reader.inner
    return reader


class _PerCameraSource(FrameSource):
    """Shared logic of sources made of one independent reader per camera."""

    def __init__(
        self,
        readers: Sequence[_CameraReader],
        *,
        rig: Rig | None,
        missing: MissingPolicy,
        fps: float | None,
        offsets: Mapping[str, int] | None = None,
        rectify: Mapping[str, Rectification] | None = None,
    ) -> None:
        if missing not in MISSING_POLICIES:
            raise ValueError(f"missing must be one of {MISSING_POLICIES}, got {missing!r}")
        if not readers:
            raise DataError("a frame source needs at least one camera")
        offsets = dict(offsets or {})
        unknown = sorted(set(offsets) - {r.camera for r in readers})
        if unknown:
            raise DataError(f"frame offsets given for unknown cameras {unknown}")
        rectify = dict(rectify or {})
        unknown = sorted(set(rectify) - {r.camera for r in readers})
        if unknown:
            raise DataError(f"lenses given for unknown cameras {unknown}")
        readers = [
            _OffsetReader(r, int(offsets[r.camera])) if offsets.get(r.camera) else r
            for r in readers
        ]
        readers = [
            _RectifiedReader(r, rectify[r.camera]) if r.camera in rectify else r for r in readers
        ]
        self._readers = list(readers)
        self._missing = missing
        self._rig = rig
        self._fps = fps
        counts = {r.camera: r.num_frames for r in self._readers}
        self._num_frames = min(counts.values())
        if len(set(counts.values())) > 1 and _warn_once(
            ("counts", *((r.location, r.num_frames) for r in self._readers))
        ):
            logger.warning(
                "cameras have different frame counts %s: using the first %d",
                counts,
                self._num_frames,
            )
        if rig is not None:
            for reader in self._readers:
                check_frame_size(rig, reader.camera, reader.size, reader.location)

    @property
    def camera_names(self) -> tuple[str, ...]:
        return tuple(r.camera for r in self._readers)

    @property
    def num_frames(self) -> int:
        return self._num_frames

    @property
    def fps(self) -> float | None:
        return self._fps

    @property
    def missing(self) -> MissingPolicy:
        return self._missing

    @property
    def frame_sizes(self) -> dict[str, tuple[int, int]]:
        """(width, height) of each camera's frames."""
        return {r.camera: r.size for r in self._readers}

    @property
    def frame_counts(self) -> dict[str, int]:
        """Frames of each camera (the source has the smallest count)."""
        return {r.camera: r.num_frames for r in self._readers}

    @property
    def camera_fps(self) -> dict[str, float | None]:
        """Each camera's own frame rate (its videos' mean rate), whatever the pairing."""
        out: dict[str, float | None] = {}
        for r in self._readers:
            info = getattr(_innermost(r), "info", None)
            out[r.camera] = info.mean_fps if isinstance(info, VideoInfo) else r.fps
        return out

    def stats(self) -> dict[str, int]:
        """Decoder work so far: frames decoded, frames skipped with ``grab()``, and rewinds
        (a read before the current stream position restarts that video from its start)."""
        inner = [_innermost(r) for r in self._readers]
        return {
            "decoded": sum(r.num_decoded for r in inner),
            "grabbed": sum(r.num_grabbed for r in inner),
            "rewinds": sum(r.num_rewinds for r in inner),
        }

    def _check_index(self, t: int) -> int:
        if isinstance(t, bool) or not isinstance(t, int | np.integer):
            raise TypeError(f"time index must be an integer, got {t!r}")
        t = int(t)
        if not 0 <= t < self._num_frames:
            raise DataError(
                f"time index {t} out of range: this source has {self._num_frames} frames "
                f"(0..{self._num_frames - 1})"
            )
        return t

    def _read(self, t: int) -> FrameSet:
        images: list[Image | None] = []
        for reader in self._readers:
            try:
                image = reader.read(t)
            except _FrameUnavailable as exc:
                if self._missing == "error":
                    raise DataError(
                        f"camera {reader.camera!r}, time index {t}: frame unavailable ({exc})"
                    ) from None
                logger.warning(
                    "camera %r, time index %d: frame unavailable (%s); camera skipped",
                    reader.camera,
                    t,
                    exc,
                )
                images.append(None)
                continue
            if self._rig is not None:
                h, w = image.shape[:2]
                check_frame_size(self._rig, reader.camera, (w, h), reader.frame_location(t))
            images.append(image)
        return FrameSet(
            time_index=t,
            images=tuple(images),
            timestamp_s=None if self._fps is None else t / self._fps,
        )

    def read(self, t: int) -> FrameSet:
        return self._read(self._check_index(t))

    def check(self, t: int) -> tuple[FrameSet, dict[str, str]]:
        """Frame set ``t`` with every camera's frame decoded, and what is wrong with the
        unusable ones (camera -> missing, does not decode, truncated video, wrong size);
        those are None in the frame set. Never raises for a bad frame."""
        t = self._check_index(t)
        images: list[Image | None] = []
        problems: dict[str, str] = {}
        for reader in self._readers:
            try:
                image = reader.read(t)
                if self._rig is not None:
                    h, w = image.shape[:2]
                    check_frame_size(self._rig, reader.camera, (w, h), reader.frame_location(t))
            except (_FrameUnavailable, EdgereconError) as exc:
                problems[reader.camera] = str(exc)
                images.append(None)
                continue
            images.append(image)
        fs = FrameSet(
            time_index=t,
            images=tuple(images),
            timestamp_s=None if self._fps is None else t / self._fps,
        )
        return fs, problems

    def iter_frames(
        self, start: int = 0, stop: int | None = None, step: int = 1
    ) -> Iterator[FrameSet]:
        if step < 1:
            raise ValueError(f"step must be >= 1, got {step}")
        stop = self._num_frames if stop is None else min(int(stop), self._num_frames)
        if start < 0:
            raise DataError(f"start index must be >= 0, got {start}")
        for t in range(int(start), stop, step):
            yield self._read(t)

    def close(self) -> None:
        for reader in self._readers:
            reader.close()


def _order(
    cameras: Mapping[str, str | os.PathLike[str]] | Sequence[str | os.PathLike[str]],
    rig: Rig | None,
) -> list[tuple[str, str | os.PathLike[str]]]:
    """(camera name, source) pairs in rig order; a sequence is taken in rig order."""
    if isinstance(cameras, Mapping):
        items = [(str(k), v) for k, v in cameras.items()]
        if rig is None:
            return items
        given = dict(items)
        unknown = sorted(set(given) - set(rig.names))
        if unknown:
            raise DataError(f"frames given for cameras {unknown} that the rig lacks ({rig.names})")
        absent = [n for n in rig.names if n not in given]
        if absent:
            raise DataError(f"no frames given for cameras {absent} of the rig")
        return [(n, given[n]) for n in rig.names]
    seq = list(cameras)
    if rig is None:
        return [(f"cam{i}", s) for i, s in enumerate(seq)]
    if len(seq) != len(rig):
        raise DataError(f"{len(seq)} frame sources for a rig of {len(rig)} cameras")
    return list(zip(rig.names, seq, strict=True))


class VideoFrameSource(_PerCameraSource):
    """One video file per camera.

    ``cameras`` maps camera names to video files (or lists files in rig order). With a
    ``rig``, frames are returned in rig order and their size is checked against it.

    Time index t is frame t of every camera (after its offset) when the videos run at one
    constant frame rate. When their rates differ (a 30 and a 60 fps phone, 29.97 against 30)
    or one's frames are not evenly spaced in time (a phone's variable frame rate), time
    index t is instead each camera's frame nearest in time to ``t / fps`` seconds after its
    first frame (after its offset, in its own frames), by the frames' timestamps
    (``VideoInfo.timestamps_s``); ``fps`` is then the slowest camera's mean rate unless given
    (``pairing == "time"``). Pairing frame t with frame t would drift apart by a frame
    every 1000 frames at 29.97 against 30 fps, and at once at 30 against 60.
    """

    def __init__(
        self,
        cameras: Mapping[str, str | os.PathLike[str]] | Sequence[str | os.PathLike[str]],
        *,
        rig: Rig | None = None,
        missing: MissingPolicy = "error",
        fps: float | None = None,
        offsets: Mapping[str, int] | None = None,
        rectify: Mapping[str, Rectification] | None = None,
    ) -> None:
        videos = [_VideoReader(name, Path(p)) for name, p in _order(cameras, rig)]
        readers: list[_CameraReader] = list(videos)
        self.pairing: Literal["index", "time"] = "index"
        """How the cameras' frames make a time index: "index" (frame t of each, after the
        offsets) or "time" (by their timestamps; see the class docstring)."""
        rates = {v.camera: v.info.mean_fps for v in videos if v.info.mean_fps is not None}
        irregular = sorted(v.camera for v in videos if not v.info.regular)
        if rates and (
            max(rates.values()) - min(rates.values()) > TIME_PAIRING_RATE_TOL * max(rates.values())
            or irregular
        ):
            offsets = dict(offsets or {})
            unknown = sorted(set(offsets) - {v.camera for v in videos})
            if unknown:
                raise DataError(f"frame offsets given for unknown cameras {unknown}")
            ref = fps if fps is not None else min(rates.values())
            readers = [_TimedReader(v, ref, int(offsets.get(v.camera, 0))) for v in videos]
            offsets, fps, self.pairing = None, ref, "time"
            shown = ", ".join(f"{n} {r:.3f}" for n, r in rates.items())
            why = f"variable or drifting frame rate: {', '.join(irregular)}" if irregular else ""
            if _warn_once(("pairing", *(v.location for v in videos))):
                logger.info(
                    "cameras paired by their frames' timestamps at %.3f fps (frame rates %s%s)",
                    ref,
                    shown,
                    f"; {why}" if why else "",
                )
        elif fps is None:
            nominal = {v.camera: v.fps for v in videos if v.fps is not None}
            if nominal:
                fps = min(nominal.values())
        super().__init__(
            readers, rig=rig, missing=missing, fps=fps, offsets=offsets, rectify=rectify
        )


class ImageFolderFrameSource(_PerCameraSource):
    """Per camera an ``{index}`` pattern, a folder of images (sorted naturally) or one image.

    ``start`` is the file index of time index 0 for patterns (e.g. 1 for 1-based names).
    Folders whose files are all named by capture times of one clock (ROS bag exports,
    EuRoC: ``1403636579763555584.png``) are paired by those times (``pairing``), not by
    their order: a camera that started late or dropped a frame stays in sync.
    """

    def __init__(
        self,
        cameras: Mapping[str, str | os.PathLike[str]] | Sequence[str | os.PathLike[str]],
        *,
        rig: Rig | None = None,
        missing: MissingPolicy = "error",
        fps: float | None = None,
        start: int = 0,
        offsets: Mapping[str, int] | None = None,
        rectify: Mapping[str, Rectification] | None = None,
    ) -> None:
        images = [_ImageReader(name, p, start) for name, p in _order(cameras, rig)]
        readers: list[_CameraReader] = list(images)
        self.pairing: Literal["index", "time"] = "index"
        """"time" when every camera's files are named by their capture times (one clock):
        time index t is then each camera's frame nearest to ``T0 + t / fps``, T0 the latest
        first frame (a camera's offset moves its clock back by its first frames' duration)."""
        stamps = [r.timestamps_s for r in images]
        if len(images) > 1 and all(ts is not None for ts in stamps):
            offsets = dict(offsets or {})
            unknown = sorted(set(offsets) - {r.camera for r in images})
            if unknown:
                raise DataError(f"frame offsets given for unknown cameras {unknown}")
            clocks = {}
            for r, ts in zip(images, stamps, strict=True):
                assert ts is not None
                k = int(offsets.get(r.camera, 0))
                if not 0 <= k < len(ts):
                    raise DataError(f"camera {r.camera!r}: offset {k} skips all its frames")
                clocks[r.camera] = ts - (ts[k] - ts[0])
            rates = {c: (len(ts) - 1) / (ts[-1] - ts[0]) for c, ts in clocks.items()}
            ref = fps if fps is not None else min(rates.values())
            first = max(float(ts[0]) for ts in stamps if ts is not None)
            readers = [
                _TimedReader(
                    r, ref, int(offsets.get(r.camera, 0)), times=clocks[r.camera], start=first
                )
                for r in images
            ]
            offsets, fps, self.pairing = None, ref, "time"
            if _warn_once(("stamped", *(r.location for r in images))):
                logger.info(
                    "cameras paired by the capture times their files are named by, at %.3f fps "
                    "from %.6f s",
                    ref,
                    first,
                )
        super().__init__(
            readers, rig=rig, missing=missing, fps=fps, offsets=offsets, rectify=rectify
        )


def check_frame_size(rig: Rig, camera: str, size: tuple[int, int], where: str) -> None:
    """Raise ``CalibrationError`` if frames of ``camera`` are not the calibration's size."""
    cam = rig[rig.index(camera)]
    if tuple(size) != cam.size:
        raise CalibrationError(
            f"camera {camera!r}: frames in {where} are {size[0]}x{size[1]} but the "
            f"calibration says {cam.width}x{cam.height}"
        )


# --------------------------------------------------------------------------------- specs
FrameKind = Literal["video", "images", "stream"]
FRAME_KINDS: tuple[str, ...] = ("video", "images", "stream")


@dataclass(frozen=True, kw_only=True)
class FrameSpec:
    """Picklable description of a frame source: what ``dataset.json`` says about it."""

    kind: FrameKind
    """"video" (one file per camera), "images" (pattern / folder / single file per camera)
    or "stream" (one live source per camera: URL, device or file played in real time; see
    ``io.streams``)."""
    cameras: tuple[tuple[str, str], ...]
    """(camera name, absolute path, pattern, URL or device) in rig order."""
    start: int = 0
    """File index of time index 0 (image patterns only)."""
    fps: float | None = None
    """Frame rate to report; None: the videos' own rate (images: unknown)."""
    stream: StreamConfig | None = None
    """How live streams are read and synchronized ("stream" only; None = defaults)."""
    offsets: tuple[tuple[str, int], ...] = ()
    """Synchronisation: (camera name, k >= 0) when time index t is that camera's frame t + k
    (cameras not listed: k = 0; files only)."""
    rectify: tuple[tuple[str, Rectification], ...] = ()
    """Fisheye cameras: (camera name, its lens and pinhole camera): their frames are
    remapped as they are read (``geometry.lens``)."""

    def __post_init__(self) -> None:
        if self.kind not in FRAME_KINDS:
            raise ValueError(f"kind must be one of {FRAME_KINDS}, got {self.kind!r}")
        if self.start < 0:
            raise ValueError(f"start must be >= 0, got {self.start}")
        if self.fps is not None and not self.fps > 0:
            raise ValueError(f"fps must be positive, got {self.fps}")
        object.__setattr__(self, "cameras", tuple((str(n), str(p)) for n, p in self.cameras))
        offsets = tuple((str(n), int(k)) for n, k in self.offsets if int(k) != 0)
        for n, k in offsets:
            if k < 0:
                raise ValueError(f"offset of camera {n!r} must be >= 0, got {k}")
        object.__setattr__(self, "offsets", offsets)

    @property
    def camera_names(self) -> tuple[str, ...]:
        return tuple(n for n, _ in self.cameras)

    def open(self, rig: Rig | None = None, missing: MissingPolicy = "error") -> FrameSource:
        """Build the frame source (opens and verifies the files)."""
        paths = dict(self.cameras)
        if self.kind == "stream":
            from edgerecon.io.streams import StreamFrameSource

            return StreamFrameSource(
                paths,
                rig=rig,
                missing=missing,
                fps=self.fps,
                config=self.stream,
                rectify=dict(self.rectify),
            )
        offsets, rectify = dict(self.offsets), dict(self.rectify)
        if self.kind == "video":
            return VideoFrameSource(
                paths, rig=rig, missing=missing, fps=self.fps, offsets=offsets, rectify=rectify
            )
        return ImageFolderFrameSource(
            paths,
            rig=rig,
            missing=missing,
            fps=self.fps,
            start=self.start,
            offsets=offsets,
            rectify=rectify,
        )


def open_frame_source(
    kind: FrameKind,
    cameras: Mapping[str, str | os.PathLike[str]],
    *,
    rig: Rig | None = None,
    missing: MissingPolicy = "error",
    fps: float | None = None,
    start: int = 0,
) -> FrameSource:
    """Shortcut for ``FrameSpec(...).open(rig, missing)``."""
    spec = FrameSpec(
        kind=kind, cameras=tuple((n, str(p)) for n, p in cameras.items()), start=start, fps=fps
    )
    return spec.open(rig, missing)
