"""Live camera streams: one reader thread per camera, tasks take the newest synchronized set.

A dataset whose ``frames.kind`` is ``"stream"`` names one source per camera: an ``http://``
MJPEG stream (read by :class:`edgerecon.io.mjpeg.MjpegHttpCapture`), anything else OpenCV's
FFmpeg backend opens (``rtsp://``, other HTTP streams, ...), a V4L2 device
(``/dev/video0``, or its index ``0``), or a video file, played at its own frame rate
(``loop`` replays it). :class:`StreamFrameSource` runs one reader thread per camera that keeps
only the **newest** frame and its capture time (wall clock, taken when the frame's data
arrived): nothing queues, so a slow consumer never sees old frames.

``read(t)`` returns the newest *synchronized* set, labelled time index ``t``:

1. cameras whose newest frame is older than ``stall_s`` are **stalled**: left out (``None``)
   until a frame arrives again; a warning is logged once when a camera stalls and once when
   it returns (never an exception: a reader reconnects on its own every ``reconnect_s``);
2. among the other cameras it waits, up to ``max_wait_s``, until every one has a frame newer
   than the one it gave the previous set and their capture times agree within
   ``sync_tolerance_s``. The set is the largest group of cameras whose capture times lie
   within the tolerance (the newest such group);
3. after ``max_wait_s`` it takes that group and leaves the others out of this set
   (counted in ``stats()["left_out_of_sync"]``); with fewer than ``min_cameras`` cameras
   (3 by default; or none alive) it raises ``DataError`` (the session records a failed task
   and goes on: one per ``max_wait_s`` while too few cameras are up).

OpenCV's FFmpeg backend opens one stream at a time in a process: an ``rtsp://`` camera that
accepts connections but sends nothing delays the (re)opening of the other FFmpeg streams by
up to ``open_timeout_s`` (HTTP MJPEG does not go through FFmpeg and is not affected).

The tolerance bounds how far the scene moves between views: by default one frame interval
(``1 / fps``; 40 ms without an ``fps``), the smallest value that free-running cameras at the
same rate always meet (right after the slowest camera delivers, every camera's newest frame is
less than one interval old); hardware-synchronized or loopback streams can use much less. The
spread of each set (newest minus oldest capture time) is reported per task as
``FrameSet.sync_spread_s``. Frames that arrive and are never part of a set are counted as
dropped (``stats()["frames_dropped"]``): the newest policy of a live deployment.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2

from edgerecon.geometry.lens import Rectification
from edgerecon.io.frames import FrameSource, MissingPolicy
from edgerecon.types import CalibrationError, DataError, FrameSet, Image

if TYPE_CHECKING:
    from edgerecon.geometry.camera import Rig

logger = logging.getLogger(__name__)

#: ``num_frames`` of a live source: unbounded.
LIVE_FRAMES = sys.maxsize
#: After (re)opening a network stream, frames that arrive closer than BURST_GAP_S to the
#: previous one among the first BURST_FRAMES are the read-ahead of the opening, not live.
BURST_FRAMES = 10
BURST_GAP_S = 0.005


@dataclass(frozen=True, kw_only=True)
class StreamConfig:
    """How live streams are read and synchronized (``dataset.json`` ``frames`` options)."""

    sync_tolerance_s: float | None = None
    """Largest spread of capture times within one set, seconds; None = one frame interval
    at the dataset's fps (0.04 s without an fps)."""
    max_wait_s: float = 1.0
    """How long a set waits for every live camera to deliver a synchronized frame before
    leaving the late ones out, seconds."""
    stall_s: float = 2.0
    """A camera whose newest frame is older than this is stalled and left out, seconds."""
    min_cameras: int = 3
    """Fewest cameras a set may have (fewer: after ``max_wait_s`` the read fails and the task
    is recorded failed); 3, what a reconstruction task needs (``config.MIN_CAMERAS``)."""
    open_timeout_s: float = 10.0
    """How long opening a stream may take (and, at dataset opening, how long to wait for
    each camera's first frame), seconds. A read waits for cameras still opening this long,
    then up to ``max_wait_s`` more for a synchronized set of the live ones."""
    reconnect_s: float = 1.0
    """Pause before a reader reopens a stream that failed or ended, seconds."""
    loop: bool = False
    """Video files: play again from the start when they end (otherwise the camera ends)."""

    def __post_init__(self) -> None:
        if self.sync_tolerance_s is not None and not self.sync_tolerance_s >= 0:
            raise ValueError(
                f"StreamConfig.sync_tolerance_s must be >= 0, got {self.sync_tolerance_s}"
            )
        for name in ("max_wait_s", "stall_s", "open_timeout_s", "reconnect_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"StreamConfig.{name} must be > 0, got {getattr(self, name)}")
        if self.min_cameras < 1:
            raise ValueError(f"StreamConfig.min_cameras must be >= 1, got {self.min_cameras}")

    def tolerance(self, fps: float | None) -> float:
        if self.sync_tolerance_s is not None:
            return self.sync_tolerance_s
        return 1.0 / fps if fps else 0.04

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> StreamConfig:
        names = set(cls.__dataclass_fields__)
        return cls(**{k: v for k, v in d.items() if k in names})

    def to_dict(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


@dataclass(frozen=True)
class _Frame:
    image: Image
    capture_s: float
    """Wall-clock time (time.time()) the frame's data arrived."""
    seq: int
    """1, 2, ... per camera (0 = none yet)."""


def _is_url(text: str) -> bool:
    return "://" in text


class CameraStream:
    """One camera's reader thread, keeping only its newest frame (see module docstring)."""

    def __init__(
        self,
        name: str,
        source: str,
        config: StreamConfig,
        *,
        expected_size: tuple[int, int] | None = None,
        changed: threading.Condition | None = None,
    ) -> None:
        self.name = name
        self.source = source
        self.config = config
        self.expected_size = expected_size
        self.changed = changed or threading.Condition()
        self.frames_received = 0
        self.reconnects = 0
        self.ended = False
        self.error = ""
        """Why the camera gives no frames (size mismatch, cannot open), "" when fine."""
        self._newest: _Frame | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._warned_open = False
        self._not_mjpeg = False

    @property
    def location(self) -> str:
        return self.source

    def start(self) -> CameraStream:
        if self._thread is None or not self._thread.is_alive():
            self._stop.clear()
            self._thread = threading.Thread(
                target=self._run, name=f"stream-{self.name}", daemon=True
            )
            self._thread.start()
        return self

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)

    def newest(self) -> _Frame | None:
        return self._newest

    # ------------------------------------------------------------------ the thread
    def _open(self) -> tuple[Any, bool]:
        """(capture, is_file) or (None, _) when it cannot be opened now."""
        src = self.source
        timeout_ms = int(self.config.open_timeout_s * 1000)
        if src.startswith(("http://", "https://")) and not self._not_mjpeg:
            from edgerecon.io.mjpeg import MjpegHttpCapture

            mjpeg = MjpegHttpCapture(
                src, open_timeout_s=self.config.open_timeout_s, read_timeout_s=self.config.stall_s
            )
            if mjpeg.isOpened():
                return mjpeg, False
            if not mjpeg.not_mjpeg:
                return None, False
            self._not_mjpeg = True  # another kind of HTTP stream: FFmpeg reads it
        if _is_url(src):
            cap = cv2.VideoCapture(
                src,
                cv2.CAP_FFMPEG,
                [
                    cv2.CAP_PROP_OPEN_TIMEOUT_MSEC,
                    timeout_ms,
                    cv2.CAP_PROP_READ_TIMEOUT_MSEC,
                    int(self.config.stall_s * 1000),
                ],
            )
            is_file = False
        elif src.isdigit() or src.startswith("/dev/"):
            cap = cv2.VideoCapture(int(src) if src.isdigit() else src)
            is_file = False
        else:
            if not Path(src).is_file():
                self.error = f"file {src} not found"
                return None, True
            cap = cv2.VideoCapture(src)
            is_file = True
        if not cap.isOpened():
            cap.release()
            return None, is_file
        return cap, is_file

    def _run(self) -> None:
        while not self._stop.is_set():
            cap, is_file = self._open()
            if cap is None:
                if not self._warned_open:
                    logger.warning(
                        "camera %r: cannot open %s; retrying every %.1f s",
                        self.name,
                        self.source,
                        self.config.reconnect_s,
                    )
                    self._warned_open = True
                self._stop.wait(self.config.reconnect_s)
                continue
            if self._warned_open:
                logger.warning("camera %r: %s opened", self.name, self.source)
                self._warned_open = False
            try:
                self._read(cap, is_file)
            finally:
                cap.release()
            if is_file and not self.config.loop:
                self.ended = True
                logger.warning("camera %r: %s ended", self.name, self.source)
                return
            if self._stop.is_set() or self.error:
                return
            self.reconnects += 1
            self._stop.wait(self.config.reconnect_s)

    def _read(self, cap: Any, is_file: bool) -> None:
        fps = float(cap.get(cv2.CAP_PROP_FPS)) if is_file else 0.0
        period = 1.0 / fps if fps > 0 else 0.04
        start = time.monotonic()
        k = 0
        last = time.monotonic()
        while not self._stop.is_set():
            if is_file:
                # A file plays at its own rate: frame k is due at start + k / fps.
                delay = start + k * period - time.monotonic()
                if delay > 0 and self._stop.wait(delay):
                    return
            if not cap.grab():
                return
            capture_s = time.time()
            now = time.monotonic()
            # Opening a network stream reads ahead (FFmpeg probes a few frames): those arrive
            # in one burst, their arrival times say nothing about when they were captured.
            burst = not is_file and k < BURST_FRAMES and now - last < BURST_GAP_S
            last = now
            k += 1
            if burst:
                continue
            ok, image = cap.retrieve()
            if not ok or image is None:
                continue
            if image.ndim == 2:
                image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
            h, w = image.shape[:2]
            if self.expected_size is not None and (w, h) != self.expected_size:
                self.error = (
                    f"frames are {w}x{h} but the calibration says "
                    f"{self.expected_size[0]}x{self.expected_size[1]}"
                )
                logger.error(
                    "camera %r (%s): %s; camera left out", self.name, self.source, self.error
                )
                return
            self.frames_received += 1
            with self.changed:
                self._newest = _Frame(image, capture_s, self.frames_received)
                self.changed.notify_all()


def best_group(times: Mapping[int, float], tolerance: float) -> list[int]:
    """The largest set of keys whose times lie within ``tolerance`` of each other (of equal
    sizes, the newest), in key order."""
    if not times:
        return []
    order = sorted(times, key=lambda k: times[k])
    best: tuple[int, float] = (0, -float("inf"))
    best_keys: list[int] = []
    j = 0
    for i, k in enumerate(order):
        while times[k] - times[order[j]] > tolerance:
            j += 1
        size = i - j + 1
        if (size, times[k]) > best:
            best = (size, times[k])
            best_keys = order[j : i + 1]
    return sorted(best_keys)


class StreamFrameSource(FrameSource):
    """Live frames of N cameras (see module docstring). ``read(t)`` is the newest
    synchronized set, labelled ``t``; there is no random access into the past."""

    def __init__(
        self,
        cameras: Mapping[str, str | os.PathLike[str]] | Sequence[str | os.PathLike[str]],
        *,
        rig: Rig | None = None,
        missing: MissingPolicy = "skip_camera",
        fps: float | None = None,
        config: StreamConfig | None = None,
        rectify: Mapping[str, Rectification] | None = None,
    ) -> None:
        from edgerecon.io.frames import _order

        self.config = config or StreamConfig()
        self._rig = rig
        self._missing = missing
        self._fps = fps
        self.tolerance_s = self.config.tolerance(fps)
        self._changed = threading.Condition()
        self._streams = []
        for name, src in _order(cameras, rig):
            size = rig[rig.index(name)].size if rig is not None else None
            self._streams.append(
                CameraStream(name, str(src), self.config, expected_size=size, changed=self._changed)
            )
        if not self._streams:
            raise DataError("a frame source needs at least one camera")
        rectify = dict(rectify or {})
        unknown = sorted(set(rectify) - {st.name for st in self._streams})
        if unknown:
            raise DataError(f"lenses given for unknown cameras {unknown}")
        # Fisheye cameras: the frames of a set are rectified once it is chosen (only those
        # the task uses pay the remap).
        self._rectify = [rectify.get(st.name) for st in self._streams]
        self._used_seq = [0] * len(self._streams)
        self._stalled = [False] * len(self._streams)
        self._stalled_since = [0.0] * len(self._streams)
        self._counts = {
            "sets": 0,
            "no_set": 0,
            "waited": 0,
            "left_out_of_sync": 0,
            "left_out_stalled": 0,
            "stalls": 0,
            "returns": 0,
        }
        self._frames_used = 0
        self._started = False
        self._started_at = 0.0

    # ------------------------------------------------------------------ FrameSource
    @property
    def camera_names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self._streams)

    @property
    def num_frames(self) -> int:
        return LIVE_FRAMES

    @property
    def fps(self) -> float | None:
        return self._fps

    @property
    def frame_sizes(self) -> dict[str, tuple[int, int]]:
        sizes = {}
        for s in self._streams:
            f = s.newest()
            if f is not None:
                sizes[s.name] = (int(f.image.shape[1]), int(f.image.shape[0]))
            elif s.expected_size is not None:
                sizes[s.name] = s.expected_size
        return sizes

    def start(self) -> StreamFrameSource:
        if not self._started:
            for s in self._streams:
                s.start()
            self._started = True
            self._started_at = time.time()
        return self

    def close(self) -> None:
        for s in self._streams:
            s._stop.set()
        for s in self._streams:
            s.stop()
        self._started = False

    def wait_first_frames(self, timeout_s: float | None = None) -> list[str]:
        """Wait until every camera delivered a frame (or ``timeout_s``, default
        ``open_timeout_s``); returns the cameras that did not. Raises
        ``CalibrationError`` for frames whose size differs from the rig's and ``DataError``
        when no camera delivered anything."""
        self.start()
        end = time.monotonic() + (self.config.open_timeout_s if timeout_s is None else timeout_s)
        with self._changed:
            while time.monotonic() < end:
                if all(s.newest() is not None or s.error or s.ended for s in self._streams):
                    break
                self._changed.wait(min(0.1, max(end - time.monotonic(), 0.0)))
        for s in self._streams:
            if s.error and "calibration" in s.error:
                raise CalibrationError(f"camera {s.name!r} ({s.source}): {s.error}")
        absent = [s.name for s in self._streams if s.newest() is None]
        if len(absent) == len(self._streams):
            raise DataError(
                "no camera stream delivered a frame within "
                f"{self.config.open_timeout_s:g} s: "
                + ", ".join(f"{s.name} = {s.source}" for s in self._streams)
            )
        return absent

    def read(self, t: int) -> FrameSet:
        self.start()
        deadline = time.monotonic() + self.config.max_wait_s
        need = min(self.config.min_cameras, len(self._streams))
        waited = False
        group: list[int] = []
        with self._changed:
            while True:
                now = time.time()
                newest = [s.newest() for s in self._streams]
                live = [
                    i
                    for i, f in enumerate(newest)
                    if f is not None and now - f.capture_s <= self.config.stall_s
                ]
                self._note_stalls(set(live), now)
                fresh = {
                    i: newest[i].capture_s  # type: ignore[union-attr]
                    for i in live
                    if newest[i].seq > self._used_seq[i]  # type: ignore[union-attr]
                }
                group = best_group(fresh, self.tolerance_s)
                # Cameras still connecting are waited for like live ones (the first read
                # waits for the streams to open), and then the live ones get the usual wait
                # for a synchronized set: at the very end of the open timeout their newest
                # frames may be one arrival apart (a loaded machine failed the first read so).
                connecting = {i for i in range(len(newest)) if self._connecting(i, now)}
                expected = set(live) | connecting
                if connecting and len(group) < need:
                    opened_by = (
                        time.monotonic() + self._started_at + self.config.open_timeout_s - now
                    )
                    deadline = max(deadline, opened_by + self.config.max_wait_s)
                timed_out = time.monotonic() >= deadline
                if group and (set(group) == expected or timed_out):
                    if len(group) >= need:
                        break
                if timed_out:
                    self._counts["no_set"] += 1
                    alive = [self._streams[i].name for i in live]
                    raise DataError(
                        f"no {self.config.min_cameras} cameras with synchronized frames within "
                        f"{self.config.max_wait_s:g} s (live: {alive or 'none'}; tolerance "
                        f"{self.tolerance_s * 1000:.0f} ms)"
                    )
                waited = True
                self._changed.wait(min(0.05, max(deadline - time.monotonic(), 0.001)))
        if self._missing == "error" and len(group) < len(self._streams):
            gone = [s.name for i, s in enumerate(self._streams) if i not in group]
            raise DataError(f"time index {t}: no synchronized frame from cameras {gone}")
        images: list[Image | None] = [None] * len(self._streams)
        times: list[float | None] = [None] * len(self._streams)
        for i in group:
            f = newest[i]
            assert f is not None
            rect = self._rectify[i]
            images[i] = f.image if rect is None else rect(f.image)
            times[i] = f.capture_s
            self._used_seq[i] = f.seq
        self._frames_used += len(group)
        self._counts["sets"] += 1
        self._counts["waited"] += int(waited)
        self._counts["left_out_of_sync"] += len(live) - len(group)
        self._counts["left_out_stalled"] += len(self._streams) - len(live)
        got = [x for x in times if x is not None]
        return FrameSet(
            time_index=t,
            images=tuple(images),
            timestamp_s=float(max(got)),
            capture_times_s=tuple(times),
        )

    @property
    def frame_counts(self) -> dict[str, int]:
        """Frames each camera delivered so far."""
        return {s.name: s.frames_received for s in self._streams}

    def check(self, t: int) -> tuple[FrameSet, dict[str, str]]:
        """``read(t)`` that never raises: the set (cameras left out are None) and camera ->
        why it is not in the set ("stalled", "out of sync", or the reader's error)."""
        try:
            frames = self.read(t)
        except DataError as exc:
            empty = FrameSet(time_index=t, images=(None,) * len(self._streams))
            return empty, {s.name: s.error or str(exc) for s in self._streams}
        problems = {}
        for i, s in enumerate(self._streams):
            if frames.images[i] is None:
                problems[s.name] = s.error or ("stalled" if self._stalled[i] else "out of sync")
        return frames, problems

    def iter_frames(
        self, start: int = 0, stop: int | None = None, step: int = 1
    ) -> Iterator[FrameSet]:
        """Successive sets (each of frames newer than the previous one's), labelled
        ``start, start + step, ...`` below ``stop`` (None: forever)."""
        t = start
        while stop is None or t < stop:
            yield self.read(t)
            t += step

    def _connecting(self, i: int, now: float) -> bool:
        """Camera ``i`` has not delivered its first frame yet, within ``open_timeout_s``."""
        s = self._streams[i]
        return (
            s.newest() is None
            and not s.error
            and not s.ended
            and now - self._started_at < self.config.open_timeout_s
        )

    def _note_stalls(self, live: set[int], now: float) -> None:
        for i, s in enumerate(self._streams):
            if self._connecting(i, now):
                continue  # not a stall yet
            if i not in live and not self._stalled[i]:
                self._stalled[i] = True
                self._counts["stalls"] += 1
                self._stalled_since[i] = now
                f = s.newest()
                why = s.error or (
                    "no frame yet" if f is None else f"no frame for {now - f.capture_s:.1f} s"
                )
                logger.warning(
                    "camera %r (%s): %s; left out of tasks until it returns", s.name, s.source, why
                )
            elif i in live and self._stalled[i]:
                self._stalled[i] = False
                self._counts["returns"] += 1
                logger.warning(
                    "camera %r is back after %.1f s", s.name, now - self._stalled_since[i]
                )

    def stats(self) -> dict[str, Any]:
        """Counts so far: sets taken, reads that gave no set (too few cameras), sets that
        waited for synchronization, cameras left out of sets (out of sync / stalled), stalls
        and returns of cameras, frames received / used / dropped, reconnects, and per camera
        whether it is stalled now."""
        received = sum(s.frames_received for s in self._streams)
        return {
            **self._counts,
            "frames_received": received,
            "frames_used": self._frames_used,
            "frames_dropped": received - self._frames_used,
            "reconnects": sum(s.reconnects for s in self._streams),
            "stalled": {s.name: self._stalled[i] for i, s in enumerate(self._streams)},
            "tolerance_s": self.tolerance_s,
        }
