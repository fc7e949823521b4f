"""The run's state and its output folder: one owner, saved atomically, restored together.

:class:`RunState` is everything ``--resume`` needs, in one record (``state.json``): the
dataset's identity and the frame range, the deadline (and, for a deadline given as a share,
the original pipeline's time it came from), the number of tasks committed and the
front-end's state (controller with its configuration and pi(N'), where pi came from, the
background version as (back-end epoch, counter), the last back-end epoch). It is written after
each task, after the task's cloud and its metrics line: ``state.json`` is the commit point,
and a metrics line beyond it (a crash between the two writes, or a torn line) is cut off and
that task redone.

:class:`OutputFolder` guards ``--out``: an exclusive lock (a second run on the same folder
is refused, naming the holder; the lock dies with its process, kill -9 included), a non-empty
folder that is not this run is refused unless ``--overwrite``, and a resume must match the
saved dataset and frame range. All of it is checked before any heavy work.

One change of the dataset is resumed: some cameras' poses, in the same world frame (what
``edgerecon calib --write`` stores when a run said a camera moved). The run goes on with the
new rig (:class:`Recalibration`, in the run state and the summary): the rig before is kept as
``rig.<k>.json`` (``rig.json`` is the rig in use), and the saved background, built with the
poses before, is dropped (the back-end builds the next one with the new rig; the tasks until
then merge with none). Any other change of the calibration (another camera's lens or size,
more than half the cameras moved, another world frame) is refused as before.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import hashlib
import json
import logging
import os
import shutil
import socket
import time
import zipfile
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry.camera import Rig
from edgerecon.io.calibration import read_rig_json
from edgerecon.io.dataset import Dataset
from edgerecon.io.ply import atomic_write_bytes, atomic_write_text, read_ply, write_ply
from edgerecon.runtime.frontend import FrontEndState
from edgerecon.runtime.messages import TaskMetrics
from edgerecon.types import EdgereconError, PointCloud, StageTimings

logger = logging.getLogger(__name__)

STATE_FORMAT = "edgerecon-run-state"
STATE_VERSION = 2

#: What a run writes in its output folder (``--overwrite`` removes these and nothing else).
RUN_FILES = (
    "metrics.jsonl",
    "state.json",
    "summary.json",
    "background.ply",
    "backgrounds",
    "tasks",
    "rig.json",
    "rig.repaired.json",
    "report",
    "views.npz",
)
#: The move detector's reference view of each camera (``quality.frames.MovedCameras``):
#: ``--resume`` compares the first frames after a stop with them.
VIEWS_FILE = "views.npz"
LOCK_NAME = ".lock"
#: Every background version a task merged with, once: ``backgrounds/v<epoch>.<counter>.ply``.
BACKGROUNDS = "backgrounds"
#: A task's foreground (the merged cloud's labelled part) and the indices of its background's
#: points the foreground overrode (``scene.merge.overridden``), under ``tasks/<time>/``.
TASK_FOREGROUND = "fg.ply"
TASK_DROPPED = "bg_dropped.npy"
#: The header comment of a task's foreground that names its background version.
BACKGROUND_COMMENT = "background"


def background_file(version: tuple[int, int]) -> str:
    """File name of the background of ``version`` (back-end epoch, counter) in
    ``BACKGROUNDS``."""
    return f"v{int(version[0])}.{int(version[1])}.ply"


def background_comment(version: tuple[int, int]) -> str:
    """The header comment of a task's foreground that names its background ``version``."""
    return f"{BACKGROUND_COMMENT} v{int(version[0])}.{int(version[1])}"


def comment_background(comments: Sequence[str]) -> tuple[int, int] | None:
    """The background version a task's foreground names (``background_comment``), None
    when none of ``comments`` does."""
    for c in comments:
        word, _, value = c.partition(" ")
        epoch, dot, counter = value.strip().removeprefix("v").partition(".")
        if word == BACKGROUND_COMMENT and dot and epoch.isdigit() and counter.isdigit():
            return int(epoch), int(counter)
    return None


#: ``rig.json``: the rig the run's tasks use now; ``rig.<k>.json``: the rig before the k-th
#: recalibration (:class:`Recalibration`).
RIG_FILE = "rig.json"
#: The rig the back-end's last calibration check found fitting the frames, when the run's
#: calibration did not (written when the run ends; ``edgerecon calib --adopt`` takes it).
REPAIRED_RIG_FILE = "rig.repaired.json"
#: A camera whose centre moved less than this share of the rig's size and that turned less
#: than ``_SAME_ANGLE_RAD`` keeps its pose (a rig file written again holds its float64 poses
#: to ~1e-12 of the rig's size).
_SAME_CENTRE = 1e-6
_SAME_ANGLE_RAD = 1e-6


def previous_rig_file(k: int) -> str:
    """The run folder's file of the rig before the ``k``-th recalibration (0: the first)."""
    return f"rig.{int(k)}.json"


def rig_fingerprint(rig: Rig, *, frame: bool = True) -> str:
    """SHA-256 (16 hex digits) of every camera's name, size, K, distortion and pose, and the
    rig's unit, up direction, local origin and reference system (``frame=False``: without
    them, as run states saved before 2026-12-07 have it)."""
    h = hashlib.sha256()
    if frame:
        h.update(repr((rig.unit, tuple(rig.up), tuple(rig.origin), rig.crs)).encode())
    for cam in rig:
        h.update(cam.name.encode())
        h.update(np.asarray(cam.size, np.int64).tobytes())
        for a in (cam.K, cam.dist, cam.R, cam.t):
            h.update(np.round(np.asarray(a, np.float64), 9).tobytes())
    return h.hexdigest()[:16]


def describe_changes(changes: Iterable[tuple[str, float, float]], unit: str | None = None) -> str:
    """Cameras' pose changes (name, centre shift, degrees; ``pose_changes``) in words."""
    u = f" {unit}" if unit else ""
    return ", ".join(
        f"{name} ({f'moved {m:.3g}{u}, ' if round(m, 6) > 0 else ''}turned {a:.2f} degrees)"
        for name, m, a in changes
    )


@dataclass(frozen=True, kw_only=True)
class Recalibration:
    """A ``--resume`` whose dataset's rig changed the poses of some cameras since the run's
    last task (``edgerecon calib --write``): tasks numbered ``from_task`` and later use the new
    rig; the run folder's ``previous_rig`` holds the rig before."""

    from_task: int
    cameras: tuple[str, ...]
    moved: tuple[float, ...]
    """Each camera's centre shift, in rig units."""
    turned_deg: tuple[float, ...]
    """Each camera's rotation, in degrees."""
    previous_rig: str

    def describe(self, unit: str | None = None) -> str:
        """E.g. "cam_2 (moved 0.0135 m, turned 2.91 degrees)", "cam1 (turned 2.00 degrees)"."""
        return describe_changes(zip(self.cameras, self.moved, self.turned_deg, strict=True), unit)

    def to_dict(self) -> dict[str, Any]:
        return {
            "from_task": self.from_task,
            "cameras": list(self.cameras),
            "moved": list(self.moved),
            "turned_deg": list(self.turned_deg),
            "previous_rig": self.previous_rig,
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> Recalibration:
        return cls(
            from_task=int(d["from_task"]),
            cameras=tuple(str(x) for x in d["cameras"]),
            moved=tuple(float(x) for x in d["moved"]),
            turned_deg=tuple(float(x) for x in d["turned_deg"]),
            previous_rig=str(d["previous_rig"]),
        )


def recalibrations_row(
    items: Sequence[Mapping[str, Any]], unit: str | None = None
) -> tuple[str, str]:
    """The summary table's row of a run's recalibrations (``RunSummary.recalibrations``; the
    rig's ``unit``), for ``run`` and ``report``."""
    said = [
        f"from task {r['from_task']}: " + Recalibration.from_dict(r).describe(unit) for r in items
    ]
    return ("cameras placed again at a --resume", "; ".join(said) or "-")


def pose_changes(before: Rig, after: Rig) -> list[tuple[str, float, float]]:
    """The cameras whose pose differs between two calibrations of one rig in the same world
    frame, as (name, centre shift in rig units, rotation in degrees). Raises
    :class:`EdgereconError` saying why ``after`` is not such a recalibration of ``before``:
    other cameras, another lens or image size, another unit, up direction or local origin,
    or more than half the cameras (or all but one) moved (another world frame)."""
    if before.names != after.names:
        raise EdgereconError(f"cameras {list(after.names)} instead of {list(before.names)}")
    for what in ("unit", "up", "origin", "crs"):
        if getattr(before, what) != getattr(after, what):
            raise EdgereconError(f"another {what} ({getattr(after, what)!r})")
    size = max(before.scene_scale(), 1e-12)
    changed = []
    for a, b in zip(before, after, strict=True):
        if a.size != b.size or not (
            np.allclose(a.K, b.K, rtol=1e-9, atol=1e-9)
            and np.allclose(a.dist, b.dist, rtol=1e-9, atol=1e-12)
        ):
            raise EdgereconError(f"{a.name}'s lens or image size changed")
        moved = float(np.linalg.norm(a.center - b.center))
        cos = (np.trace(a.R @ b.R.T) - 1.0) / 2.0
        angle = float(np.arccos(np.clip(cos, -1.0, 1.0)))
        if moved > _SAME_CENTRE * size or angle > _SAME_ANGLE_RAD:
            changed.append((a.name, moved, float(np.degrees(angle))))
    kept = len(before) - len(changed)
    if kept < 2 or kept < len(before) / 2:
        raise EdgereconError(f"{len(changed)} of {len(before)} cameras moved: another world frame")
    return changed


def task_dir(folder: str | os.PathLike[str], time_index: int) -> Path:
    """Where a run writes the files of the task at ``time_index``."""
    return Path(folder) / "tasks" / f"{time_index:06d}"


@dataclass(frozen=True, kw_only=True)
class DatasetIdentity:
    """What makes two datasets the same for ``--resume``: the folder, the cameras and their
    calibration (a fingerprint), and the number of frames."""

    root: str
    name: str
    num_frames: int
    cameras: tuple[str, ...]
    rig_fingerprint: str
    """``rig_fingerprint``: the cameras' sizes, lenses and poses, the rig's frame and unit."""

    @classmethod
    def of(cls, dataset: Dataset) -> DatasetIdentity:
        return cls(
            root=str(Path(dataset.root).resolve()),
            name=dataset.name,
            num_frames=int(dataset.num_frames),
            cameras=tuple(dataset.rig.names),
            rig_fingerprint=rig_fingerprint(dataset.rig),
        )

    def to_dict(self) -> dict[str, Any]:
        return {**self.__dict__, "cameras": list(self.cameras)}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> DatasetIdentity:
        return cls(
            root=str(d["root"]),
            name=str(d["name"]),
            num_frames=int(d["num_frames"]),
            cameras=tuple(d["cameras"]),
            rig_fingerprint=str(d["rig_fingerprint"]),
        )

    def difference(self, other: DatasetIdentity) -> str | None:
        """What differs from ``other`` (None: the same dataset)."""
        if self.cameras != other.cameras:
            return f"cameras {list(other.cameras)} instead of {list(self.cameras)}"
        if self.rig_fingerprint != other.rig_fingerprint:
            return "a different calibration"
        if self.root != other.root:
            return f"folder {other.root} instead of {self.root}"
        if self.num_frames != other.num_frames:
            return f"{other.num_frames} frames instead of {self.num_frames}"
        return None


@dataclass(frozen=True)
class OriginalTiming:
    """The original pipeline (r = 1, every camera, the whole scene: the paper's baseline)
    measured on one timestamp of the run's data, where the front-end runs (this process;
    a Ray run on a cluster: the front-end's node), before the run's first task
    (``runtime.online.measure_original``): the reference of ``run --deadline 40%`` and of
    the summary's online / original ratio."""

    time_index: int
    seconds: float
    """The product's own stage timings, added up (``timings.json``'s total)."""
    stages: dict[str, float]
    node: str | None = None
    """The Ray node it was timed on (a run on a cluster); None: the run's own process."""

    @classmethod
    def of(
        cls, time_index: int, timings: StageTimings, *, node: str | None = None
    ) -> OriginalTiming:
        """From a reconstruction's stage timings."""
        return cls(
            time_index=int(time_index),
            seconds=round(timings.total, 4),
            stages={k: round(float(v), 4) for k, v in timings.seconds.items()},
            node=node,
        )

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "time_index": self.time_index,
            "seconds": self.seconds,
            "stages": self.stages,
        }
        if self.node is not None:
            d["node"] = self.node
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> OriginalTiming:
        return cls(
            time_index=int(d["time_index"]),
            seconds=float(d["seconds"]),
            stages={str(k): float(v) for k, v in dict(d.get("stages", {})).items()},
            node=None if d.get("node") is None else str(d["node"]),
        )


@dataclass(frozen=True, kw_only=True)
class RunState:
    """The one record ``--resume`` restores (see module docstring)."""

    dataset: DatasetIdentity
    frames: tuple[int, int | None, int]
    """``--frames`` as (start, stop, step)."""
    policy: str
    deadline_s: float
    tasks_done: int
    """Tasks committed: the first ``tasks_done`` lines of metrics.jsonl."""
    frontend: FrontEndState
    original: OriginalTiming | None = None
    """The original pipeline's measured time, when the run measured it (``--deadline P%``):
    a resumed run keeps its deadline."""
    recalibrations: tuple[Recalibration, ...] = ()
    """The resumes that went on with cameras placed again (oldest first)."""

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": STATE_FORMAT,
            "version": STATE_VERSION,
            "dataset": self.dataset.to_dict(),
            "frames": list(self.frames),
            "policy": self.policy,
            "deadline_s": self.deadline_s,
            "tasks_done": self.tasks_done,
            "frontend": self.frontend.to_dict(),
            "original": None if self.original is None else self.original.to_dict(),
            "recalibrations": [r.to_dict() for r in self.recalibrations],
            "saved_at": time.time(),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> RunState:
        if d.get("format") != STATE_FORMAT:
            raise EdgereconError("not an edgerecon run state")
        if d.get("version") != STATE_VERSION:
            raise EdgereconError(
                f"run state version {d.get('version')} (this edgerecon reads {STATE_VERSION}): "
                "start the run again with --overwrite"
            )
        start, stop, step = d["frames"]
        return cls(
            dataset=DatasetIdentity.from_dict(d["dataset"]),
            frames=(int(start), None if stop is None else int(stop), int(step)),
            policy=str(d["policy"]),
            deadline_s=float(d["deadline_s"]),
            tasks_done=int(d["tasks_done"]),
            frontend=FrontEndState.from_dict(d["frontend"]),
            original=None if d.get("original") is None else OriginalTiming.from_dict(d["original"]),
            recalibrations=tuple(Recalibration.from_dict(r) for r in d.get("recalibrations", ())),
        )

    def save(self, folder: Path) -> None:
        atomic_write_text(folder / "state.json", json.dumps(self.to_dict()) + "\n", sync=True)

    @classmethod
    def load(cls, folder: Path) -> RunState:
        path = folder / "state.json"
        try:
            return cls.from_dict(json.loads(path.read_text()))
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise EdgereconError(f"{path}: unreadable run state ({exc})") from None


class OutputFolder:
    """``--out`` of one run, locked for the run's lifetime (see module docstring)."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self._lock: IO[str] | None = None
        self.recalibration: Recalibration | None = None
        """What :meth:`prepare` found: the resumed run goes on with cameras placed again."""

    # ------------------------------------------------------------------ lock
    def acquire(self, command: str = "") -> OutputFolder:
        """Create the folder (an unwritable one is an error now, not after the work) and
        take its lock, or refuse naming the run that holds it."""
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            f = open(self.path / LOCK_NAME, "a+", encoding="utf-8")
        except OSError as exc:
            raise EdgereconError(f"--out {self.path}: cannot write there ({exc})") from None
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.seek(0)
            holder = f.read().strip() or "another process"
            f.close()
            raise EdgereconError(
                f"--out {self.path} is in use by another run ({holder}): wait for it to end "
                "or choose another --out"
            ) from None
        f.seek(0)
        f.truncate()
        f.write(
            f"pid {os.getpid()} on {socket.gethostname()} since "
            f"{time.strftime('%Y-%m-%d %H:%M:%S')}" + (f": {command}" if command else "")
        )
        f.flush()
        self._lock = f
        return self

    def release(self) -> None:
        if self._lock is not None:
            with contextlib.suppress(OSError):
                fcntl.flock(self._lock.fileno(), fcntl.LOCK_UN)
            self._lock.close()
            self._lock = None

    def __enter__(self) -> OutputFolder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    # ------------------------------------------------------------------ contents
    def entries(self) -> list[str]:
        return sorted(p.name for p in self.path.iterdir() if p.name != LOCK_NAME)

    def prepare(
        self,
        *,
        resume: bool,
        overwrite: bool,
        identity: DatasetIdentity,
        frames: tuple[Any, ...],
        rig: Rig | None = None,
    ) -> RunState | None:
        """Check the folder's contents against what this run will do; returns the saved
        state to resume from (None: a fresh run in an empty folder). ``rig``: the dataset's
        rig (``identity``'s), which a resume may go on with when only some cameras' poses
        changed (:attr:`recalibration`; see the module docstring)."""
        entries = self.entries()
        has_state = (self.path / "state.json").exists()
        self.recalibration = None
        if resume and has_state:
            state = RunState.load(self.path)
            diff = state.dataset.difference(identity)
            same_else = dataclasses.replace(identity, rig_fingerprint=state.dataset.rig_fingerprint)
            recalibrated = (
                diff is not None and rig is not None and state.dataset.difference(same_else) is None
            )
            if diff is not None and not recalibrated:
                raise EdgereconError(
                    f"--resume: {self.path} holds a run of {state.dataset.name} "
                    f"({state.dataset.root}); this dataset has {diff}"
                )
            start, stop, step = state.frames
            new_start, new_stop, new_step = frames
            stop_ok = new_stop is None or (stop is not None and new_stop >= stop)
            if (new_start, new_step) != (start, step) or not stop_ok:
                raise EdgereconError(
                    f"--resume: the run in {self.path} was started with --frames "
                    f"{_frames_text(state.frames)}; resume it with the same start and step "
                    f"(its end may grow), got {_frames_text(frames)}"
                )
            if recalibrated:
                assert rig is not None
                state = self._recalibrate(state, identity, rig)
            return state
        if resume and not entries:
            logger.warning("--resume: %s holds no run yet: starting one", self.path)
            return None
        if resume:
            raise EdgereconError(
                f"--resume: {self.path} holds no run state (state.json): nothing to resume; "
                "use --overwrite to start a new run there"
            )
        if entries and not overwrite:
            what = "a run" if has_state else f"{len(entries)} entries ({', '.join(entries[:4])})"
            raise EdgereconError(
                f"--out {self.path} is not empty (it holds {what}): use --resume to continue "
                "that run, --overwrite to replace it, or another folder"
            )
        for name in RUN_FILES:
            p = self.path / name
            if p.is_dir():
                shutil.rmtree(p)
            else:
                p.unlink(missing_ok=True)
        for p in self.path.glob("rig.*.json"):  # the rigs before recalibrations
            p.unlink(missing_ok=True)
        return None

    def _recalibrate(self, state: RunState, identity: DatasetIdentity, rig: Rig) -> RunState:
        """A resume whose dataset's calibration changed: go on when only some cameras'
        poses did (``pose_changes``), committed before any task: the rig before kept as
        ``rig.<k>.json``, the saved background dropped, then the state saved with the new
        identity (the commit point; the session writes the new ``rig.json``). Raises when
        the change is another."""
        where = f"--resume: {self.path} holds a run of {state.dataset.name}; this dataset has"
        path = self.path / RIG_FILE
        try:
            before = read_rig_json(path)
        except (OSError, EdgereconError) as exc:
            raise EdgereconError(
                f"{where} a different calibration, and the run's own rig ({path}) cannot be "
                f"read ({exc}): start again with --overwrite"
            ) from None
        saved = state.dataset.rig_fingerprint
        if saved not in (rig_fingerprint(before), rig_fingerprint(before, frame=False)):
            raise EdgereconError(
                f"{where} a different calibration, and {path} is not the rig of the run's "
                "last task: start again with --overwrite"
            )
        try:
            changes = pose_changes(before, rig)
        except EdgereconError as exc:
            raise EdgereconError(
                f"{where} a different calibration ({exc}): start again with --overwrite, or "
                "resume with the calibration the run started with"
            ) from None
        previous = previous_rig_file(len(state.recalibrations))
        recalibration = None
        if changes:
            recalibration = Recalibration(
                from_task=state.tasks_done,
                cameras=tuple(c[0] for c in changes),
                moved=tuple(round(c[1], 6) for c in changes),
                turned_deg=tuple(round(c[2], 4) for c in changes),
                previous_rig=previous,
            )
            shutil.copyfile(path, self.path / f".{previous}.tmp")
            os.replace(self.path / f".{previous}.tmp", self.path / previous)
            (self.path / "background.ply").unlink(missing_ok=True)
        state = dataclasses.replace(
            state,
            dataset=identity,
            recalibrations=state.recalibrations
            + (() if recalibration is None else (recalibration,)),
        )
        state.save(self.path)  # the commit point: a later resume is a plain one
        self.recalibration = recalibration
        if recalibration is not None:
            logger.warning(
                "--resume with a new calibration of %s: tasks from %d on use it (the rig "
                "before is kept as %s); the saved background was built with the poses "
                "before: dropped, the back-end builds the next",
                recalibration.describe(rig.unit),
                recalibration.from_task,
                previous,
            )
        return state

    # ------------------------------------------------------------------ metrics
    def read_metrics(self, committed: int) -> list[TaskMetrics]:
        """The first ``committed`` records of metrics.jsonl; anything after them (a torn
        last line, a line written just before a crash) is cut off, and those tasks run
        again."""
        path = self.path / "metrics.jsonl"
        if not path.exists():
            if committed:
                raise EdgereconError(
                    f"{path} is missing but the run state counts {committed} tasks"
                )
            return []
        data = path.read_bytes()
        records: list[TaskMetrics] = []
        offset = 0
        while len(records) < committed:
            end = data.find(b"\n", offset)
            line = data[offset:] if end < 0 else data[offset:end]
            try:
                records.append(TaskMetrics.from_dict(json.loads(line)))
            except (ValueError, TypeError) as exc:
                raise EdgereconError(
                    f"{path}: line {len(records) + 1} of {committed} committed ones does not "
                    f"parse ({exc}); the run cannot be resumed (use --overwrite)"
                ) from None
            if end < 0:
                raise EdgereconError(f"{path}: only {len(records)} of {committed} lines")
            offset = end + 1
        if offset < len(data):
            logger.warning(
                "%s: cutting off %d bytes after the %d committed tasks (torn or uncommitted)",
                path,
                len(data) - offset,
                committed,
            )
            with open(path, "r+b") as f:
                f.truncate(offset)
                os.fsync(f.fileno())
        return records

    def append_metrics(self, m: TaskMetrics) -> None:
        """Append one line and fsync: a crash loses at most the task in progress."""
        path = self.path / "metrics.jsonl"
        with open(path, "a", encoding="utf-8") as f:
            f.write(json.dumps(m.to_dict()) + "\n")
            f.flush()
            os.fsync(f.fileno())

    def read_background(self) -> PointCloud | None:
        path = self.path / "background.ply"
        return read_ply(path) if path.exists() else None

    def write_background(self, cloud: PointCloud, version: tuple[int, int], **ply: Any) -> None:
        """Save the background of ``version`` in ``BACKGROUNDS`` (the tasks that merged with it
        refer to it) and as ``background.ply`` (the newest, for ``--resume``: a hard link to
        the same file where the file system has them, else a copy). ``ply``: ``write_ply``'s
        ``unit`` and ``up``."""
        path = write_ply(self.path / BACKGROUNDS / background_file(version), cloud, **ply)
        newest = self.path / "background.ply"
        tmp = newest.with_name(f".{newest.name}.{os.getpid()}.link")
        tmp.unlink(missing_ok=True)
        try:
            os.link(path, tmp)
        except OSError:
            shutil.copyfile(path, tmp)
        os.replace(tmp, newest)

    def ensure_background(
        self, cloud: PointCloud | None, version: tuple[int, int], **ply: Any
    ) -> None:
        """On resume: the restored background saved under its version too, when a run
        written before ``BACKGROUNDS`` existed (or an interrupted write) left it out."""
        if cloud is not None and not (self.path / BACKGROUNDS / background_file(version)).exists():
            self.write_background(cloud, version, **ply)

    def write_views(
        self,
        views: Mapping[str, NDArray[np.uint8]],
        time_index: int,
        steady: Mapping[str, NDArray[np.uint8]] | None = None,
        moves: Mapping[str, int] | None = None,
    ) -> None:
        """The cameras' reference views (grey thumbnails by camera name) as of the task at
        ``time_index``, and ``steady``: those of the cameras whose frames are turned back
        onto a view (``quality.frames.Stabiliser``), with ``moves``: how many moves of
        each the run said (a knock's 1, a sway's more), in ``VIEWS_FILE`` (written
        atomically)."""
        names, steady_names = list(views), list(steady or {})
        arrays: dict[str, Any] = {
            f"view{k}": np.asarray(views[n], np.uint8) for k, n in enumerate(names)
        }
        arrays.update(
            {
                f"steady{k}": np.asarray((steady or {})[n], np.uint8)
                for k, n in enumerate(steady_names)
            }
        )
        arrays.update(
            names=np.array(names, dtype=str),
            steady_names=np.array(steady_names, dtype=str),
            steady_moves=np.array([(moves or {}).get(n, 0) for n in steady_names], np.int64),
            time_index=np.int64(time_index),
        )

        def write(f: IO[bytes]) -> None:
            np.savez(f, **arrays)

        atomic_write_bytes(self.path / VIEWS_FILE, write)

    def read_views(
        self,
    ) -> (
        tuple[int, dict[str, NDArray[np.uint8]], dict[str, NDArray[np.uint8]], dict[str, int]]
        | None
    ):
        """What :meth:`write_views` wrote: (its time index, the views by camera name, the
        steadied cameras' views, their moves said: none in a file from before they were
        kept); None when there is none or it cannot be read (said: the
        moves across the stop then go unseen, the run does not stop for it)."""
        path = self.path / VIEWS_FILE
        if not path.exists():
            return None
        try:
            with np.load(path, allow_pickle=False) as z:
                names = [str(n) for n in z["names"]]
                views = {n: np.asarray(z[f"view{k}"], np.uint8) for k, n in enumerate(names)}
                steady_names = [str(n) for n in z["steady_names"]] if "steady_names" in z else []
                steady = {
                    n: np.asarray(z[f"steady{k}"], np.uint8) for k, n in enumerate(steady_names)
                }
                counts = z["steady_moves"] if "steady_moves" in z else []
                moves = {n: int(c) for n, c in zip(steady_names, counts, strict=False)}
                return int(z["time_index"]), views, steady, moves
        except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
            logger.warning(
                "%s cannot be read (%s): a camera moved while the run was stopped is not seen "
                "from its frames (the calibration checks still find it)",
                path,
                exc,
            )
            return None

    def write_task_cloud(
        self,
        time_index: int,
        foreground: PointCloud,
        dropped: NDArray[np.int64],
        version: tuple[int, int],
        **ply: Any,
    ) -> None:
        """The task's part of its merged cloud: the foreground as merged (labels, background
        version), its background version (a header comment) and the background points it
        overrode. ``viewer.rundir.RunFolder.cloud`` composes the merged cloud from them and
        the version's file; a background is stored once, not with every task."""
        d = task_dir(self.path, time_index)
        atomic_write_bytes(d / TASK_DROPPED, lambda f: np.save(f, np.asarray(dropped, np.int64)))
        write_ply(d / TASK_FOREGROUND, foreground, comments=[background_comment(version)], **ply)


def _frames_text(frames: tuple[Any, ...]) -> str:
    start, stop, step = frames
    return f"{start}:{'' if stop is None else stop}:{step}"
