"""The back-end role: the golden reference and background rebuilds.

Per task (in arrival order, always the newest first: a stale queued task is dropped), the
front-end hands the back-end the frames with the foreground it computed (:class:`TaskWork`;
the masks are computed once, by the front-end, which needs them first). When the online
quality is the paper's golden estimate, the back-end's *task thread* reconstructs the golden
configuration's sparse cloud (r = 1, all cameras) on the same masks and publishes its
foreground points. A separate *background thread*, at a lower OS priority, rebuilds the
background (dense MVS of the latest frames outside the foreground, or of the empty scene when
the dataset has a background clip) whenever the task thread is idle, and pushes each finished
background to the front-end with a version number. The front-end never waits for it.

Every background carries a :class:`BgVersion` (the epoch the front-end gave this back-end,
and a counter). A stage that raises on a timestamp publishes a failed reply (the front-end
records why) and the back-end goes on with the next one; ``ping`` reports how long the
current task has been running, so an engine can restart a back-end stuck on one.

The class is plain Python (usable without any cluster); the Ray engine wraps it in an actor.
"""

from __future__ import annotations

import functools
import logging
import multiprocessing
import os
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any, TypeVar

import numpy as np

from edgerecon.config import ReconstructionConfig
from edgerecon.geometry.camera import Rig
from edgerecon.pipeline import (
    fine_scale_limit,
    prepare_task_views,
    reconstruct_static,
    reconstruct_task,
    task_sparse,
)
from edgerecon.quality.calibration import POOLED_FRAME_SETS, CheckPool, pooled_verdict
from edgerecon.runtime.config import RuntimeConfig
from edgerecon.runtime.interrupt import AbandonedThreads, Runner, ThreadAbandoned
from edgerecon.runtime.messages import (
    BackgroundUpdate,
    BgVersion,
    GoldenReply,
    TaskWork,
    describe_exception,
)
from edgerecon.scene.foreground import ForegroundResult
from edgerecon.scene.split import split_sparse
from edgerecon.scene.still import StillSnapshot, make_snapshot
from edgerecon.types import EdgereconError, FrameSet, Mask, PointCloud

logger = logging.getLogger(__name__)

#: Seconds between two checks of tasks' frames after a moved camera was named without a
#: repair that fits (``BackEnd._check_calibration``).
_CHASE_S = 2.0

T = TypeVar("T")

PushFn = Callable[[BackgroundUpdate | StillSnapshot], object]

#: Replies kept for late readers (a front-end that timed out and asks again).
_KEEP_REPLIES = 8

#: The calibration check's frame sets held at most (pixels over all cameras: 3 sets of 4
#: cameras at 1920x1080, ~75 MB; one set of a larger rig).
_CALIB_POOL_PIXELS = 25_000_000


def _pixels(sets: deque[FrameSet]) -> int:
    return sum(im.shape[0] * im.shape[1] for fs in sets for im in fs.images if im is not None)


class BackendFault(RuntimeError):
    """Raised inside the back-end by fault injection (tests and drills)."""


class BackEnd:
    """Back-end node role. Thread-safe; call :meth:`start` once and :meth:`stop` at the end."""

    def __init__(
        self,
        rig: Rig,
        config: RuntimeConfig,
        *,
        push: PushFn | None = None,
        initial_background: FrameSet | None = None,
        epoch: int = 1,
    ) -> None:
        self.rig = rig
        self.config = config
        self._push = push
        self._lock = threading.Condition()
        self._pending: TaskWork | None = None
        self._busy = False
        self._task_started = 0.0
        self.epoch = epoch
        self._golden: OrderedDict[int, GoldenReply] = OrderedDict()
        self._latest: tuple[FrameSet, ForegroundResult] | None = None
        # The snapshots of the still foreground (``_snapshot_due``).
        self._still_report: tuple[int, int] | None = None
        self._snap_time: int | None = None
        self._snap_judged = True
        self._snap_backoff = 1
        self._snap_skipped = 0
        self._initial_background = initial_background
        self._bg_version = 0
        self._bg_source_done: int | None = None
        self._last_bg_start = -np.inf
        self._stop = False
        self._stall_until = 0.0
        self._crashed: str | None = None
        self._threads: list[threading.Thread] = []
        self.abandoned = AbandonedThreads()
        """Threads of rebuilds stopped past ``rebuild_limit_s`` (``background_process =
        false``) that still run (blocked in a native call)."""
        self._rebuilds = Runner("backend-rebuild")  # in this process: a thread kept for them
        self._worker = (
            _RebuildWorker(config.background_nice, config.background_idle)
            if config.background_updates and config.background_process
            else None
        )
        self.stats: dict[str, Any] = {
            "tasks": 0,
            "dropped": 0,
            "backgrounds": 0,
            "background_seconds": 0.0,
            "snapshots": 0,
            "snapshots_skipped": 0,
            "calibration": None,
        }
        # The calibration checks (``RuntimeConfig.calib_check_s``): when the next is due, the
        # last verdict, and the one a warning or a note was last given for.
        self._calib_due = 0.0
        self._calib_sets: deque[FrameSet] = deque(maxlen=3)
        self._calib_pool: CheckPool | None = None
        self._calib_since: int | None = None
        """A camera's view moved at this time index (``check_calibration``): the next check
        reads frame sets from then on only."""
        self._calib_moved: tuple[str, ...] = ()
        """The cameras whose views moved then: a check that names them is confirmed."""
        self._calib_suspects: tuple[str, ...] = ()
        """Those of them that moved after a check that fit with every camera checked: the
        only cameras that can be off (``pooled_verdict``'s ``suspects``)."""
        self._calib_floor: int | None = None
        """The newest move's time index: frame sets from before it are not checked again."""
        self._calib_lock = threading.Lock()
        """Held by a check (a rebuild's, or one started at once after a move)."""
        self._calib_now: threading.Thread | None = None
        """The check started when a task brought frames from after a move (``_serve``)."""
        self._calib_chase_at: float | None = None
        """A moved camera named without a repair that fits: when (``time.monotonic``) the
        next task's frames are checked at once, pooled with those before."""
        self._calib_last: tuple[bool | None, tuple[str, ...]] | None = None
        self._calib_said: tuple[bool | None, tuple[str, ...]] | None = None

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> BackEnd:
        for name, target in (("backend-task", self._task_loop), ("backend-bg", self._bg_loop)):
            th = threading.Thread(target=target, name=name, daemon=True)
            th.start()
            self._threads.append(th)
        return self

    def stop(self, timeout: float = 30.0) -> None:
        with self._lock:
            self._stop = True
            self._lock.notify_all()
        if self._worker is not None:
            self._worker.close()
        for th in self._threads:
            th.join(timeout)

    @property
    def task_thread(self) -> threading.Thread | None:
        """The thread that serves the tasks (the one a back-end stuck on a task is stuck
        in; None before :meth:`start`)."""
        return self._threads[0] if self._threads else None

    # ------------------------------------------------------------------ requests
    def submit(self, work: TaskWork) -> None:
        """Queue a task; a task still waiting is replaced (only the newest matters)."""
        with self._lock:
            if self._pending is not None:
                self.stats["dropped"] += 1
            self._pending = work
            self._lock.notify_all()

    def golden(self, time_index: int, timeout: float) -> GoldenReply | None:
        """The golden reference of ``time_index``, waiting up to ``timeout`` (None if not ready)."""
        return self._wait(self._golden, time_index, timeout)

    def ping(self) -> dict[str, Any]:
        """Cheap health report: alive, busy, stalled, backgrounds pushed."""
        with self._lock:
            return {
                "alive": self._crashed is None and all(t.is_alive() for t in self._threads),
                "busy": self._busy or self._pending is not None,
                "task_age_s": time.monotonic() - self._task_started if self._busy else 0.0,
                "epoch": self.epoch,
                "stalled": time.monotonic() < self._stall_until,
                "bg_version": [self.epoch, self._bg_version],
                "error": self._crashed,
                "abandoned_threads": self.abandoned.running(),
                **self.stats,
            }

    def inject_fault(self, kind: str, seconds: float = 0.0) -> None:
        """Drills: ``"stall"`` blocks the task thread for ``seconds``; ``"crash"`` kills it."""
        with self._lock:
            if kind == "stall":
                self._stall_until = time.monotonic() + seconds
            elif kind == "crash":
                self._crashed = "injected crash"
            else:
                raise ValueError(f"unknown fault {kind!r}: use 'stall' or 'crash'")
            self._lock.notify_all()

    def check_calibration(self, since: int, cameras: Sequence[str]) -> None:
        """Check the calibration at once (whatever ``calib_check_s`` says) on the first
        task's frames from time index ``since`` on (``_check_now``), and on frame sets from
        then on only: ``cameras``' views moved then (``quality.frames.MovedCameras``), and
        the frame sets before show the rig as it was. A check that names those cameras is
        confirmed at once (their frames and their matches with the others agree); when the
        last check fit with every camera checked, they are the only cameras a repair
        changes (``suspects``). Nothing when the checks are off (``calib_check_s = 0``)."""
        last = self.stats.get("calibration") or {}
        fitted = last.get("fits") is True and not last.get("unchecked")
        with self._lock:
            self._calib_since = since
            self._calib_floor = max(since, self._calib_floor or since)
            self._calib_moved = tuple(sorted(set(cameras) | set(self._calib_moved)))
            if fitted or self._calib_suspects:
                self._calib_suspects = tuple(sorted(set(cameras) | set(self._calib_suspects)))
            self._calib_due = 0.0

    def _check_now(self, frames: FrameSet) -> None:
        """The check after a move, started at once on the first frames from after it, in a
        thread of this process at the rebuilds' priority (the rebuild's process may be
        busy for many seconds with a background from frames before the move). One at a
        time; a check that fails is logged. (In the embedded engine this is the front-end's
        process: the check's Python parts share its interpreter lock for a second or two.)"""
        if self._calib_now is not None and self._calib_now.is_alive():
            return

        def run() -> None:
            try:
                os.setpriority(
                    os.PRIO_PROCESS, threading.get_native_id(), self.config.background_nice
                )
            except (AttributeError, OSError, PermissionError):  # not Linux / not allowed
                pass
            try:
                self._check_calibration(frames, direct=True)
            except Exception as exc:  # the rebuilds' checks go on
                logger.warning(
                    "back-end: the calibration check failed: %s", describe_exception(exc)
                )

        self._calib_now = threading.Thread(target=run, name="backend-calib-check", daemon=True)
        self._calib_now.start()

    def _wait(self, store: OrderedDict[int, Any], key: int, timeout: float) -> Any:
        deadline = time.monotonic() + max(0.0, timeout)
        with self._lock:
            while key not in store:
                if self._crashed is not None or self._stop:
                    return None
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                self._lock.wait(remaining)
            return store[key]

    def _publish(self, store: OrderedDict[int, Any], key: int, value: Any) -> None:
        with self._lock:
            store[key] = value
            while len(store) > _KEEP_REPLIES:
                store.popitem(last=False)
            self._lock.notify_all()

    # ------------------------------------------------------------------ task thread
    def _task_loop(self) -> None:
        while True:
            with self._lock:
                while self._pending is None and not self._stop and self._crashed is None:
                    self._lock.wait(0.5)
                if self._stop or self._crashed is not None:
                    return
                work, self._pending = self._pending, None
                self._busy = True
                self._task_started = time.monotonic()
            assert work is not None  # the wait above ends only with a pending task
            try:
                self._serve(work)
            except BackendFault:
                return
            except ThreadAbandoned:  # stuck past the watchdog: the engine replaced this node
                logger.warning(
                    "back-end: task %d stopped (stuck past the watchdog)", work.frames.time_index
                )
                return
            except Exception as exc:  # a bug outside the stages must not kill the node either
                logger.exception("back-end: task %d failed: %s", work.frames.time_index, exc)
            finally:
                with self._lock:
                    self._busy = False
                    self._lock.notify_all()

    def _check_faults(self) -> None:
        while True:
            with self._lock:
                if self._crashed is not None:
                    raise BackendFault(self._crashed)
                wait = self._stall_until - time.monotonic()
                if wait <= 0 or self._stop:
                    return
                self._lock.wait(min(wait, 0.5))

    def _serve(self, work: TaskWork) -> None:
        """Keep the frames for the background rebuilds, then (when asked) the golden
        reference of one timestamp; a stage that raises publishes a failed reply (a bad frame
        must not kill the node)."""
        frames, fg = work.frames, work.foreground
        t = frames.time_index
        self._check_faults()
        if all(im is not None for im in frames.images):
            # Backgrounds are rebuilt from complete frame sets only (no camera left out).
            with self._lock:
                self._latest = (frames, fg)
                self._still_report = work.still_uses
                since, chase = self._calib_since, self._calib_chase_at
            if self.config.calib_check_s > 0 and (
                (since is not None and t >= since)
                or (chase is not None and time.monotonic() >= chase)
            ):
                self._check_now(frames)
        if work.golden:
            try:
                self._publish(self._golden, t, self._golden_reference(frames, fg))
            except Exception as exc:
                error = f"golden reference: {describe_exception(exc)}"
                logger.error("back-end: time %d: %s", t, error)
                self._publish(
                    self._golden,
                    t,
                    GoldenReply(
                        time_index=t, fg_points3D=None, num_points=0, seconds=0.0, error=error
                    ),
                )
        self.stats["tasks"] += 1

    def _golden_reference(self, frames: FrameSet, fg: ForegroundResult) -> GoldenReply:
        t1 = time.perf_counter()
        golden = ReconstructionConfig(sparse_config=self.config.sparse)
        sparse = task_sparse(
            prepare_task_views(frames, self.rig, golden),
            self.rig,
            None if self.config.sparse_scope == "scene" else fg.masks,  # as the front-end's
            self.config.split.fg_mask_dilation_px,
            self.config.sparse,
        )
        split = split_sparse(
            sparse.points3D,
            sparse.visibility_matrix(len(self.rig)),
            self.rig.cameras,
            fg.label_images(),
        )
        return GoldenReply(
            time_index=frames.time_index,
            fg_points3D=sparse.points3D[split.foreground],
            num_points=sparse.num_points,
            seconds=time.perf_counter() - t1,
        )

    # ------------------------------------------------------------------ background thread
    def _bg_loop(self) -> None:
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), self.config.background_nice)
        except (AttributeError, OSError, PermissionError):  # not Linux / not allowed
            pass
        while True:
            with self._lock:
                while not self._stop and self._crashed is None and not self._bg_ready():
                    self._lock.wait(0.5)
                if self._stop or self._crashed is not None:
                    return
                source = self._bg_source()
                self._last_bg_start = time.monotonic()
            try:
                self._rebuild(*source)
            except Exception as exc:
                if self._stop:  # the run ended under it: its process is shut down
                    logger.debug("back-end: background rebuild ended with the run (%s)", exc)
                    return
                if isinstance(exc, RebuildTimeout):
                    logger.error("back-end: %s", exc)
                else:
                    logger.exception("back-end: background rebuild failed: %s", exc)

    def _bg_ready(self) -> bool:
        if not self.config.background_updates or self._busy or self._pending is not None:
            return False
        if time.monotonic() - self._last_bg_start < self.config.background_min_interval_s:
            return False
        if self._initial_background is not None:
            return True
        return self._latest is not None and self._latest[0].time_index != self._bg_source_done

    def _bg_source(self) -> tuple[FrameSet, ForegroundResult | None]:
        if self._initial_background is not None:
            frames, self._initial_background = self._initial_background, None
            return frames, None
        assert self._latest is not None
        frames, fg = self._latest
        self._bg_source_done = frames.time_index
        return frames, fg

    def _rebuild(self, frames: FrameSet, fg: ForegroundResult | None) -> None:
        """One rebuild: the snapshot of the still foreground (``scene.still``; the tasks use
        it at once), the background, then the calibration check when due
        (``calib_check_s``; after the background, which the tasks wait for). After a camera's
        view moved (``check_calibration``) the check of frames from then on comes first: a
        background from the moved camera's calibrated pose is not what the tasks wait for,
        and ``--adopt-repairs`` takes the repair as soon as the check confirms it."""
        with self._lock:
            urgent = self._calib_since is not None and frames.time_index >= self._calib_since
        if urgent:
            self._check_calibration(frames)
        t0 = time.perf_counter()
        if self.config.still is not None and fg is not None and self._snapshot_due():
            try:
                still = self._bounded(still_snapshot, self.rig, self.config, frames, fg)
            except RebuildTimeout:
                raise
            except Exception as exc:  # the background is still rebuilt
                if self._stop:  # the run ended under it (its process killed): ends quietly
                    raise
                logger.warning(
                    "back-end: the still foreground of time %d failed: %s",
                    frames.time_index,
                    describe_exception(exc),
                )
            else:
                if still is not None:
                    self._snap_time, self._snap_judged = frames.time_index, False
                    self.stats["snapshots"] += 1
                    logger.info(
                        "back-end: the foreground of time %d densified (still foreground): "
                        "%d points in %.1f s",
                        frames.time_index,
                        len(still.cloud),
                        time.perf_counter() - t0,
                    )
                    self._send(still, f"the still foreground of time {frames.time_index}")
        masks = None if fg is None else fg.masks
        cloud = self._bounded(rebuild_background, self.rig, self.config, frames, masks)
        with self._lock:
            self._bg_version += 1
            version = BgVersion(self.epoch, self._bg_version)
        seconds = time.perf_counter() - t0
        self.stats["backgrounds"] += 1
        self.stats["background_seconds"] += seconds
        logger.info(
            "back-end: background %s from time %d: %d points in %.1f s",
            version,
            frames.time_index,
            len(cloud),
            seconds,
        )
        self._send(
            BackgroundUpdate(version=version, cloud=cloud, seconds=seconds), f"background {version}"
        )
        if not urgent:
            self._check_calibration(frames)

    def _check_calibration(self, frames: FrameSet, *, direct: bool = False) -> None:
        with self._calib_lock:
            self._check_calibration_locked(frames, direct)

    def _check_calibration_locked(self, frames: FrameSet, direct: bool) -> None:
        """The calibration against the frames of this rebuild and the two before (pooled),
        when due (``calib_check_s``); a camera they cannot check (few features shared with
        the others) is checked on the matches of the earlier checks too, up to
        ``POOLED_FRAME_SETS`` frame sets (``pooled_verdict``), and the checks come at every
        rebuild while a camera is not checked (each reads one frame set more). A
        verdict is said when the check pooled two or more frame sets, or when two checks in a
        row give it (the first, of one frame set, is checked again at the next rebuild): a
        warning when a camera is named or the frames do not fit, a note when it fits again
        after one. After a camera's view moved (``check_calibration``) only frame sets from
        the move on are checked and pooled; a check that names that camera is confirmed at
        once, and one that names it without a repair that fits is followed by another on a
        task's frames ``_CHASE_S`` later. ``direct``: in this thread (a check started by a
        move, ``_check_now``), not in the rebuild's process, whenever it is called."""
        every = self.config.calib_check_s
        if every <= 0:
            return
        with self._lock:
            floor = self._calib_floor
        if floor is not None and frames.time_index < floor:
            return  # frames from before a camera's view moved: the rig as it was
        self._calib_sets.append(frames)
        while len(self._calib_sets) > 1 and _pixels(self._calib_sets) > _CALIB_POOL_PIXELS:
            self._calib_sets.popleft()  # a rig of many large cameras: fewer sets held
        with self._lock:
            since, self._calib_since = self._calib_since, None
            moved, suspects = self._calib_moved, self._calib_suspects
            if direct:
                # A chase is this check: the verdict sets the next one when one is due (a
                # check that fails or cannot judge must not start one at every task).
                self._calib_chase_at = None
        if since is not None:
            # A camera's view moved at ``since``: what was seen before shows the rig as it
            # was, and one check's verdict waits for the next one's again.
            for _ in range(len(self._calib_sets)):
                fs = self._calib_sets.popleft()
                if fs.time_index >= since:
                    self._calib_sets.append(fs)
            if self._calib_pool is not None:
                obs = self._calib_pool.observed
                after = [k for k, t in enumerate(obs.times) if t >= since]
                self._calib_pool = CheckPool(obs.subset(after)) if after else None
            self._calib_last = None
        if not direct and time.monotonic() < self._calib_due:
            return
        self._calib_due = time.monotonic() + every
        try:
            # The last three rebuilds' frame sets, pooled (as ``edgerecon calib``).
            check = functools.partial(pooled_verdict, suspects=suspects)
            args = (self.rig, list(self._calib_sets), self._calib_pool)
            verdict, self._calib_pool = check(*args) if direct else self._bounded(check, *args)
        except RebuildTimeout:
            raise
        except Exception as exc:  # a check that fails is not the run's problem
            if self._stop:  # the run ended under it (its process killed): ends quietly
                raise
            logger.warning("back-end: the calibration check failed: %s", describe_exception(exc))
            return
        self.stats["calibration"] = verdict
        key = (verdict["fits"], tuple(verdict["off"]))
        # One frame set's matches vary: its verdict counts when the next check agrees (it
        # comes at the next rebuild); pooled ones count at once.
        confirmed = (
            key == self._calib_last
            or len(verdict["times"]) > 1
            or bool(moved and verdict["fits"] is False and tuple(sorted(verdict["off"])) == moved)
        )
        if verdict["fits"] is True or "repaired_rig" in verdict:
            with self._lock:  # the moved cameras' frames were checked: told
                if self._calib_since is None:
                    self._calib_moved = self._calib_suspects = ()
                self._calib_chase_at = None
        elif moved and verdict["fits"] is False:
            # A moved camera named without a repair that fits (one frame set's matches may
            # not place it: utrecht4cam's cam2 rolled 3 degrees): a task's frames again
            # after _CHASE_S (a view that changed a little), pooled, up to the pool's 7.
            pool = self._calib_pool
            more = pool is None or len(pool.times) < POOLED_FRAME_SETS
            with self._lock:
                self._calib_chase_at = time.monotonic() + _CHASE_S if more else None
        verdict["confirmed"] = confirmed
        self._calib_last = key
        if not confirmed and key != self._calib_said and verdict["fits"] is not None:
            self._calib_due = 0.0
        if verdict["unchecked"]:
            # A camera not checked yet: one frame set more at each rebuild (the pool's
            # matches are kept; caliscope_charuco's cam_1 is checked once the board is up).
            self._calib_due = 0.0
        if not confirmed or key == self._calib_said or verdict["fits"] is None:
            return
        if verdict["fits"] is False:
            logger.warning(
                "%s; from these frames: %s%s",
                verdict["message"],
                verdict.get("repair", "-"),
                " (the run writes that rig to rig.repaired.json in its folder when it ends: "
                "`edgerecon calib --dataset DIR --adopt OUT/rig.repaired.json`, or `calib "
                "--write` on recorded frames; `--resume` then goes on with it)"
                if "repaired_rig" in verdict
                else "",
            )
        elif self._calib_said is not None:
            logger.warning("back-end: %s", verdict["message"])
        self._calib_said = key

    def _snapshot_due(self) -> bool:
        """Whether this rebuild makes a snapshot of the still foreground: every rebuild while
        the tasks use them; after one that no task used, every 2nd, then 4th, at most every
        8th rebuild (people who gesture to all sides: a snapshot costs the rebuild's
        process a task's worth of work at the finest r), back to every one once one is used."""
        if not self._snap_judged:
            report = self._still_report
            used = report is not None and report[0] == self._snap_time and report[1] > 0
            self._snap_backoff = 1 if used else min(2 * self._snap_backoff, 8)
            self._snap_judged = True
        self._snap_skipped += 1
        if self._snap_skipped < self._snap_backoff:
            self.stats["snapshots_skipped"] += 1
            return False
        self._snap_skipped = 0
        return True

    def _send(self, update: BackgroundUpdate | StillSnapshot, what: str) -> None:
        if self._push is not None:
            try:
                self._push(update)
            except Exception as exc:  # the front-end may be gone; keep serving
                logger.warning("back-end: pushing %s failed: %s", what, exc)

    def _bounded(self, fn: Callable[..., T], *args: Any) -> T:
        """``fn(*args)`` in the rebuild's process (``background_process``), else in a thread
        of its own: still running after ``rebuild_limit_s``, the process is killed or the
        thread stopped (Python code ends at once, a native call when it returns;
        ``runtime.interrupt``) and :class:`RebuildTimeout` raised, so that the next rebuild
        can start."""
        limit = self.config.rebuild_limit_s
        if self._worker is not None:
            return self._worker.call(fn, *args, timeout_s=limit)
        run = self._rebuilds.call(lambda: fn(*args), limit)
        if run.timed_out:
            self.abandoned.abandon(run.thread, "a background rebuild past its limit", grace_s=0.0)
            raise RebuildTimeout(
                f"background rebuild still running after {limit:.0f} s: its thread was "
                "stopped (the next rebuild starts from the newest frames)"
            )
        if run.error is not None:
            raise run.error
        return run.value  # type: ignore[return-value]


def rebuild_background(
    rig: Rig,
    config: RuntimeConfig,
    frames: FrameSet,
    masks: tuple[Mask | None, ...] | None,
) -> PointCloud:
    """One background rebuild: the golden-scale reconstruction of ``frames`` outside their
    (dilated) foreground ``masks`` (None: the whole images, e.g. the empty-scene clip)."""
    return reconstruct_static(
        frames,
        rig,
        masks,
        scale=config.background_scale,
        sparse_config=config.sparse,
        dense_config=config.background_dense,
        split_config=config.split,
    ).cloud


def still_snapshot(
    rig: Rig, config: RuntimeConfig, frames: FrameSet, fg: ForegroundResult | None
) -> StillSnapshot | None:
    """The whole foreground of ``frames`` (its masks ``fg``) densified with every camera at
    the finest r a task may run (``RuntimeConfig.fine_foreground``; else the golden
    configuration): the snapshot of the still foreground (``scene.still``); None when
    ``RuntimeConfig.still`` is off or there is no foreground. The task's own composition
    (``pipeline.reconstruct_task``, without a background)."""
    if config.still is None or fg is None or not any(m is not None and m.any() for m in fg.masks):
        return None
    # As fine as any task may run (``fine_foreground``: finer than the golden task): kept
    # points must not be coarser than those the task would have densified.
    scale = fine_scale_limit(rig, config.dense, config.split) if config.fine_foreground else 1.0
    cfg, split = config.task_configs(scale, rig)
    result = reconstruct_task(
        frames,
        rig,
        fg,
        cfg,
        background=PointCloud.empty(),
        split_config=split,
        sparse_scope=config.sparse_scope,
    )
    return make_snapshot(
        frames.time_index,
        result.foreground.cloud,
        frames.images,
        fg.masks,
        fg.cameras,
        config.still,
    )


def _lower_priority(nice: int, idle: bool = False) -> None:
    from edgerecon.runtime.memory import start_heap_trimmer, tune_malloc

    tune_malloc()  # the parent's MALLOC_ARENA_MAX / MALLOC_MMAP_THRESHOLD_, or the defaults
    start_heap_trimmer()
    try:
        os.nice(nice)
    except OSError:  # not allowed: run at the same priority
        pass
    if idle and hasattr(os, "sched_setscheduler") and hasattr(os, "SCHED_IDLE"):
        try:  # before any thread starts: numba's workers inherit it
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
        except OSError:
            pass


#: Seconds a new rebuild process has to start (spawn and imports) before it is killed.
_START_S = 300.0


class RebuildTimeout(EdgereconError):
    """A background rebuild ran past ``RuntimeConfig.rebuild_limit_s``; its process was
    killed."""


def _kill_pool(pool: ProcessPoolExecutor) -> None:
    """Kill the processes of ``pool`` (a task running there cannot be cancelled) and let it
    go."""
    processes = getattr(pool, "_processes", None) or {}
    for process in list(processes.values()):
        try:
            process.kill()
        except (OSError, ValueError):  # already gone
            pass
    pool.shutdown(wait=False, cancel_futures=True)


class _RebuildWorker:
    """Background rebuilds in a process of their own, at a lower OS priority.

    A low-priority *thread* of the front-end's process stalls the critical path: the OS
    deschedules it while it holds the interpreter lock, and the front-end waits for the lock
    (priority inversion; the scene stage measured 0.51 -> 0.73 s with a rebuild thread at
    nice 10 beside it on caliscope_charuco). A process has its own interpreter. It starts
    with the first rebuild (spawned: the parent has threads) and is started again if it
    dies."""

    def __init__(self, nice: int, idle: bool = False) -> None:
        self._nice = nice
        self._idle = idle
        self._pool: ProcessPoolExecutor | None = None
        self._lock = threading.Lock()

    def call(self, fn: Callable[..., T], *args: Any, timeout_s: float | None = None) -> T:
        """``fn(*args)`` in the worker process. Still running after ``timeout_s``: the
        process is killed and :class:`RebuildTimeout` raised (the next call starts a new
        one), so a rebuild that hangs does not stop the backgrounds for the rest of the
        run."""
        with self._lock:
            fresh = self._pool is None
            if self._pool is None:
                self._pool = ProcessPoolExecutor(
                    max_workers=1,
                    mp_context=multiprocessing.get_context("spawn"),
                    initializer=_lower_priority,
                    initargs=(self._nice, self._idle),
                )
            pool = self._pool
        if fresh:  # the process's start (spawn, imports) is not the rebuild's time
            self._wait(pool, pool.submit(os.getpid), _START_S, "did not start")
        return self._wait(pool, pool.submit(fn, *args), timeout_s, "still running")

    def _wait(
        self, pool: ProcessPoolExecutor, future: Future[T], limit: float | None, what: str
    ) -> T:
        try:
            return future.result(timeout=limit)
        except BrokenProcessPool:
            with self._lock:
                if self._pool is pool:
                    self._pool = None  # the next rebuild starts a new process
            raise
        except TimeoutError:
            with self._lock:
                if self._pool is pool:
                    self._pool = None
            _kill_pool(pool)
            raise RebuildTimeout(
                f"background rebuild {what} after {limit:.0f} s: its process was killed "
                "(the next rebuild starts a new one from the newest frames)"
            ) from None

    def close(self) -> None:
        """Stop the worker: a rebuild or check still running there is killed (nothing
        takes its result once the back-end stops; left alone it held the back-end's stop
        for up to its join timeout and went on using a core after the run)."""
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            _kill_pool(pool)
