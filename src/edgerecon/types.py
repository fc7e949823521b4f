"""Data structures that cross module and node boundaries.

Arrays carry their shape and dtype in the aliases' comments. Images are OpenCV's BGR ``uint8``
(H, W, 3); point colours are RGB ``uint8`` (what PLY viewers expect).
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

Points3D = NDArray[np.float64]  # (N, 3) world coordinates, rig units
Points2D = NDArray[np.float64]  # (N, 2) pixel coordinates
Colors = NDArray[np.uint8]  # (N, 3) RGB
Normals = NDArray[np.float32]  # (N, 3) unit vectors
Image = NDArray[np.uint8]  # (H, W, 3) BGR
Mask = NDArray[np.bool_]  # (H, W) True = selected pixel
DepthMap = NDArray[np.float32]  # (H, W) depth along the optical axis, 0 or NaN = unknown

#: Label of background points in labelled clouds; foreground objects are 1, 2, ...
BACKGROUND_LABEL = 0
#: Label of points whose foreground/background status is unknown.
UNKNOWN_LABEL = -1
#: Per-point attribute (uint8 0/1) of points that were inferred, not measured: 1 = the point
#: was synthesised (e.g. ground-plane completion of a floor stereo left), 0 = measured by stereo.
#: Absent = all measured (clouds from before the flag existed).
INFERRED = "inferred"


class EdgereconError(Exception):
    """Base class of errors caused by bad input (shown to the user without a traceback)."""


class CalibrationError(EdgereconError, ValueError):
    """Malformed or inconsistent calibration; the message names the camera and the problem."""


class DataError(EdgereconError, ValueError):
    """Missing, unreadable or inconsistent input data (frames, datasets, files)."""


class TaskCancelled(EdgereconError):
    """Raised once a task's ``cancel`` event is set (its watchdog gave up on it): at a stage
    boundary of ``pipeline.reconstruct_task``, and inside the dense stage before each depth
    map and filter pass (``dense.reconstruct_dense``), so an abandoned task stops taking
    work; nothing after that point runs."""


@dataclass(frozen=True, kw_only=True, eq=False)
class PointCloud:
    """A coloured point cloud with optional per-point attributes.

    All optional arrays, when present, have one row per point.
    """

    points3D: Points3D
    """(N, 3) float64 positions."""
    colors: Colors | None = None
    """(N, 3) uint8 RGB colours."""
    normals: Normals | None = None
    """(N, 3) float32 unit normals."""
    labels: NDArray[np.int32] | None = None
    """(N,) int32: 0 = background, k >= 1 = foreground object k, -1 = unknown."""
    confidence: NDArray[np.float32] | None = None
    """(N,) float32 in [0, 1] or a count of supporting views, stage-specific."""
    attributes: dict[str, NDArray[Any]] = field(default_factory=dict)
    """Further named (N,) arrays (e.g. ``bg_version``, ``num_views``, ``inferred``: see
    ``INFERRED``), written to PLY."""

    def __post_init__(self) -> None:
        pts = np.ascontiguousarray(np.asarray(self.points3D, dtype=np.float64).reshape(-1, 3))
        object.__setattr__(self, "points3D", pts)
        n = pts.shape[0]
        for name, dtype, width in (
            ("colors", np.uint8, 3),
            ("normals", np.float32, 3),
            ("labels", np.int32, 1),
            ("confidence", np.float32, 1),
        ):
            value = getattr(self, name)
            if value is None:
                continue
            arr = np.asarray(value)
            if name == "colors" and arr.dtype != np.uint8:
                arr = np.clip(np.rint(arr), 0, 255)
            arr = np.ascontiguousarray(arr.astype(dtype, copy=False))
            arr = arr.reshape(-1, 3) if width == 3 else arr.reshape(-1)
            if arr.shape[0] != n:
                raise ValueError(f"PointCloud.{name} has {arr.shape[0]} rows, expected {n}")
            object.__setattr__(self, name, arr)
        for key, value in self.attributes.items():
            if np.asarray(value).shape[:1] != (n,):
                raise ValueError(f"PointCloud attribute {key!r} must have {n} rows")
        flag = self.attributes.get(INFERRED)
        if flag is not None and np.asarray(flag).dtype != np.uint8:
            # One dtype everywhere (PLY ``uchar inferred``), whatever the producer used.
            attrs = dict(self.attributes)
            attrs[INFERRED] = (np.asarray(flag) != 0).astype(np.uint8)
            object.__setattr__(self, "attributes", attrs)

    def __len__(self) -> int:
        return int(self.points3D.shape[0])

    @property
    def num_points(self) -> int:
        return len(self)

    @property
    def inferred(self) -> NDArray[np.bool_]:
        """(N,) True for inferred points (``attributes["inferred"]``), all False without it."""
        flag = self.attributes.get(INFERRED)
        if flag is None:
            return np.zeros(len(self), bool)
        return np.asarray(flag) != 0

    @property
    def num_inferred(self) -> int:
        return int(np.count_nonzero(self.inferred))

    def with_inferred(self, inferred: NDArray[np.bool_] | bool) -> PointCloud:
        """The same cloud with ``attributes["inferred"]`` set (a mask or one value for all)."""
        flag = np.broadcast_to(np.asarray(inferred, bool), (len(self),)).astype(np.uint8)
        return PointCloud(
            points3D=self.points3D,
            colors=self.colors,
            normals=self.normals,
            labels=self.labels,
            confidence=self.confidence,
            attributes={**self.attributes, INFERRED: flag},
        )

    @classmethod
    def empty(cls) -> PointCloud:
        return cls(points3D=np.zeros((0, 3)))

    def select(self, index: NDArray[Any]) -> PointCloud:
        """The sub-cloud at a boolean mask or an index array (all attributes follow)."""

        def pick(a: NDArray[Any] | None) -> NDArray[Any] | None:
            return None if a is None else a[index]

        return PointCloud(
            points3D=self.points3D[index],
            colors=pick(self.colors),
            normals=pick(self.normals),
            labels=pick(self.labels),
            confidence=pick(self.confidence),
            attributes={k: v[index] for k, v in self.attributes.items()},
        )

    def with_labels(self, labels: NDArray[np.int32] | int) -> PointCloud:
        lab = np.full(len(self), labels, np.int32) if np.isscalar(labels) else labels
        return PointCloud(
            points3D=self.points3D,
            colors=self.colors,
            normals=self.normals,
            labels=np.asarray(lab, np.int32),
            confidence=self.confidence,
            attributes=dict(self.attributes),
        )

    @staticmethod
    def concatenate(clouds: Sequence[PointCloud]) -> PointCloud:
        """Concatenate clouds; an attribute present in only some clouds gets defaults
        (grey colour, zero normal, label -1, confidence 0, attribute 0) in the others."""
        clouds = [c for c in clouds if c is not None]
        if not clouds:
            return PointCloud.empty()
        n = [len(c) for c in clouds]

        def cat(name: str, fill: Any, dtype: Any, width: int) -> NDArray[Any] | None:
            if all(getattr(c, name) is None for c in clouds):
                return None
            parts = []
            for c, k in zip(clouds, n, strict=True):
                a = getattr(c, name)
                if a is None:
                    shape = (k, width) if width > 1 else (k,)
                    a = np.full(shape, fill, dtype)
                parts.append(a)
            return np.concatenate(parts)

        keys = sorted({k for c in clouds for k in c.attributes})
        attrs = {}
        for key in keys:
            dtype = next(c.attributes[key].dtype for c in clouds if key in c.attributes)
            attrs[key] = np.concatenate(
                [c.attributes.get(key, np.zeros(k, dtype)) for c, k in zip(clouds, n, strict=True)]
            )
        return PointCloud(
            points3D=np.concatenate([c.points3D for c in clouds]),
            colors=cat("colors", 128, np.uint8, 3),
            normals=cat("normals", 0.0, np.float32, 3),
            labels=cat("labels", UNKNOWN_LABEL, np.int32, 1),
            confidence=cat("confidence", 0.0, np.float32, 1),
            attributes=attrs,
        )


@dataclass(frozen=True, kw_only=True, eq=False)
class FrameSet:
    """The synchronized frames of one timestamp: one image per camera of the rig.

    ``images[i]`` is ``None`` when camera ``i`` has no usable frame at this timestamp (a
    documented degradation: the camera is left out of this task); readers raise ``DataError``
    instead unless asked to tolerate missing frames.
    """

    time_index: int
    """Frame index in the stream (the task's timestamp)."""
    images: tuple[Image | None, ...]
    """One BGR uint8 image per rig camera, in rig order, at the calibration's resolution."""
    timestamp_s: float | None = None
    """Capture time in seconds when known (frame index / fps for videos)."""
    capture_times_s: tuple[float | None, ...] | None = None
    """Per camera, the wall-clock capture time of its frame (live streams; None: unknown)."""

    def __len__(self) -> int:
        return len(self.images)

    @property
    def sync_spread_s(self) -> float | None:
        """Newest minus oldest capture time of the frames present (live streams), else
        None."""
        if self.capture_times_s is None:
            return None
        times = [
            t
            for t, im in zip(self.capture_times_s, self.images, strict=True)
            if t is not None and im is not None
        ]
        return float(max(times) - min(times)) if times else None

    @property
    def available(self) -> list[int]:
        """Indices of the cameras with a frame."""
        return [i for i, im in enumerate(self.images) if im is not None]


@dataclass
class StageTimings:
    """Wall-clock seconds per pipeline stage, in the order the stages ran.

    >>> t = StageTimings()
    >>> with t.stage("features"):
    ...     pass
    >>> list(t.seconds)
    ['features']
    """

    seconds: dict[str, float] = field(default_factory=dict)

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - start

    def add(self, name: str, seconds: float) -> None:
        self.seconds[name] = self.seconds.get(name, 0.0) + float(seconds)

    def merge(self, other: StageTimings, prefix: str = "") -> StageTimings:
        for k, v in other.seconds.items():
            self.add(prefix + k, v)
        return self

    @property
    def total(self) -> float:
        return float(sum(self.seconds.values()))

    def to_dict(self) -> dict[str, float]:
        return {k: round(v, 6) for k, v in self.seconds.items()}
