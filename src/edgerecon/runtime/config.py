"""Configuration of the online system (both roles and the session)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from edgerecon.config import ReconstructionConfig
from edgerecon.dense import DenseConfig
from edgerecon.geometry.camera import Rig
from edgerecon.optimize.workload import WorkloadConfig
from edgerecon.pipeline import SPARSE_SCOPES, SplitPipelineConfig, task_configs
from edgerecon.quality.frames import FrameCheckConfig
from edgerecon.scene.foreground import ForegroundConfig
from edgerecon.scene.still import StillConfig
from edgerecon.sparse import SparseConfig

#: The largest ``RuntimeConfig.deadline_share`` (a deadline of 10 golden tasks).
MAX_DEADLINE_SHARE = 10.0

#: Values of ``RuntimeConfig.online_quality``.
ONLINE_QUALITIES = ("silhouette", "golden")


@dataclass(frozen=True, kw_only=True)
class RuntimeConfig:
    """Settings of the front-end, the back-end and the online session."""

    deadline_s: float = math.nan
    """User deadline Δt on the average critical-path time of a task, seconds (NaN with
    ``deadline_share``: the run sets it before its first task)."""
    deadline_share: float | None = None
    """The deadline as a share of the original pipeline's time (r = 1, every camera, the
    whole scene: the paper's baseline) on this rig and machine, measured on the run's first
    timestamp before any task (``run --deadline 40%``; ``runtime.online.measure_original``);
    it replaces ``deadline_s``. A resumed run keeps the measurement it started with. None:
    ``deadline_s`` as given."""
    eval_threshold: float | None = None
    """Distance threshold d of the online F-score, in rig units; None = ``eval_threshold_rel``
    x the rig's median camera distance."""
    eval_threshold_rel: float = 0.005
    """d relative to the rig's median camera distance (4 m rig -> 2 cm) when not given."""
    online_quality: str = "silhouette"
    """The online quality estimate the controller feeds on: "silhouette" = the task's dense
    foreground against every camera's foreground masks, computed by the front-end right
    after the critical path (``quality.online.silhouette_quality``; Pearson 0.83-0.95 with
    the offline foreground F); "golden" = the paper's: the task's foreground sparse points
    against the golden configuration's, which the back-end reconstructs for every task
    (Pearson 0.2-0.5 on wide-baseline rigs, and late references degrade tasks)."""
    adjust_target: float = 0.95
    """After the search the controller steers the average task time to this share of the
    deadline (the paper: 1.0; measured there on the simulator: half the tasks miss; 0.95
    keeps the average within the deadline under timing noise, see docs/OPTIMIZER.md)."""
    fine_foreground: bool = True
    """When the golden configuration leaves part of the deadline unused, the minor
    adjustment raises r above 1 (every camera): the foreground's depth maps finer than the
    golden configuration's, up to the frames' own pixels (``ControllerConfig.r_fine``,
    ``pipeline.task_configs``; rigs whose golden foreground densifies at level 0, under
    1280 px, have nothing finer). False: r stops at 1, as in the paper."""
    skip_dominated_scales: bool = True
    """The controller never runs an r at which the foreground costs more than at a larger
    r (``pipeline.dominated_scales``: just below where the plane sweep's pyramid level
    drops to a coarser one, on 1280-wide frames r 0.45-0.565 and 1.0-1.13;
    ``ControllerConfig.skip_scales``). False: every r in the range runs (the paper)."""
    workload: WorkloadConfig | None = field(default_factory=WorkloadConfig)
    """Each adjusted task's r scaled by its masks' area and the time its scene stage left,
    against the recent tasks' (computed after its scene stage, before its MVS;
    ``optimize.workload``): a task with more foreground, or less time left, runs coarser,
    one with less finer, so that its time stays near the deadline; not coarser when it fits
    at the controller's r. None: every task runs the controller's r (the paper)."""
    still: StillConfig | None = field(default_factory=StillConfig)
    """Still foreground (``scene.still``): each background rebuild also densifies its frames'
    whole foreground at the golden configuration (the snapshot); a task then densifies only
    its mask pixels that changed since the snapshot's frames, and keeps the snapshot's points
    elsewhere. None: every task densifies its whole foreground, the rebuilds the background
    alone."""
    golden_timeout_s: float | None = None
    """How long the front-end waits, after publishing a task's cloud, for the back-end's
    golden reference of the online estimate; None = the deadline, at least 2 s."""
    task_timeout_s: float | None = None
    """Watchdog of every task (front-end and back-end): a task still running after this many
    seconds is abandoned and recorded as failed, and a back-end busy on one task that long
    is restarted; None = max(``watchdog_factor`` x the deadline, ``watchdog_min_s``)."""
    watchdog_factor: float = 10.0
    """The default watchdog as a multiple of the deadline."""
    watchdog_min_s: float = 30.0
    """The default watchdog's floor, seconds (a golden task may take several deadlines)."""
    frame_check: FrameCheckConfig = field(default_factory=FrameCheckConfig)
    """Which frames are unusable (black, saturated, textureless): such cameras are left out
    of the task, and a task left with fewer than 3 cameras gives an empty result."""
    backend_retry_s: float = 2.0
    """While the back-end is lost, how often the front-end checks whether it is back."""
    background_updates: bool = True
    """Rebuild the background in the back-end's idle time and push it to the front-end."""
    background_min_interval_s: float = 0.0
    """Least time between the starts of two background rebuilds."""
    calib_check_s: float = 60.0
    """The back-end checks the calibration against the frames of a background rebuild
    (``quality.calibration``, as ``edgerecon calib``: a camera knocked during the run), after
    the first rebuild and then at most every this many seconds, in the rebuild's process,
    the last three rebuilds' frame sets pooled (a camera they cannot check: with the
    earlier checks' matches, the newest 7 frame sets, and a check at every rebuild while it
    is not checked; ``quality.calibration.pooled_verdict``); a verdict that names a
    camera (or finds the
    frames do not fit) gives one warning (one frame set's: once the next check agrees), and
    the summary keeps the last verdict. 0 = never."""
    background_scale: float = 1.0
    """Image scale of background rebuilds (the back-end has time: golden by default)."""
    background_process: bool = True
    """Rebuild the background in a process of its own (a thread of the back-end's process
    holding the interpreter lock while descheduled stalls the front-end's critical path in
    the embedded engine)."""
    rebuild_timeout_s: float | None = None
    """A background rebuild still running after this many seconds has its process killed
    (``background_process = false``: its thread stopped, ``runtime.interrupt``); the next
    rebuild starts a new one from the newest frames. None =
    max(10 x the watchdog, 300 s): a rebuild under the idle scheduling class waits for the
    cores the two roles leave, and must not be killed for that."""
    background_nice: int = 10
    """OS niceness of the background-rebuild thread (Linux), so that the current task's
    work (and golden references) is served first."""
    background_idle: bool = True
    """Run the background-rebuild process under the OS's idle scheduling class (Linux
    ``SCHED_IDLE``, on top of ``background_nice``): it gets a core only when the two roles
    leave one idle. At nice 10 alone it still took a share of the front-end's parallel
    depth maps: hd4 / hd4p at 40 % ran r 1.53 / 1.48 at deadlines of 1.47 / 1.54 s with
    nice 10, 1.57 / 1.62 at 1.45 / 1.55 s with both, with as many background rebuilds (2-3
    in 20 tasks). False: nice alone (other systems, or a rebuild that must keep pace)."""
    sparse: SparseConfig = field(default_factory=SparseConfig)
    """Sparse stage of both roles."""
    sparse_scope: str = "hull"
    """What the sparse stage of the task (and of the golden reference) covers: "foreground"
    = only the dilated foreground masks, so the front-end segments first, then runs SfM on
    the masked crops (its cost follows the foreground's area; the split and pi(N') need
    nothing else); "scene" = the paper's order: SfM of the whole frames, then the split;
    "hull" (default) = as "foreground" with the paper's online estimate; otherwise no SfM on
    a task's critical path when the visual hull bounds the foreground's depth search
    (``pipeline.reconstruct_task``): the same foreground cloud without the SfM's 0.2-0.25 s
    per task (hd4, caliscope_charuco: about a third of the online golden task); a
    golden-configuration task runs the SfM of its foreground crops after its cloud, for
    pi(N') (``sfm_mapping``)."""
    dense: DenseConfig = field(default_factory=DenseConfig)
    """Foreground MVS on the front-end."""
    background_dense: DenseConfig = field(default_factory=DenseConfig)
    """Background MVS on the back-end."""
    split: SplitPipelineConfig = field(default_factory=SplitPipelineConfig)
    foreground: ForegroundConfig = field(default_factory=ForegroundConfig)

    def with_original(self, seconds: float) -> RuntimeConfig:
        """This configuration with ``deadline_s`` = ``deadline_share`` x ``seconds``, the
        original pipeline's measured time (unchanged without a share)."""
        if self.deadline_share is None:
            return self
        if not (seconds > 0 and math.isfinite(seconds)):
            raise ValueError(f"the original pipeline's time must be > 0 s, got {seconds!r}")
        return dataclasses.replace(self, deadline_s=round(self.deadline_share * seconds, 3))

    def __post_init__(self) -> None:
        if self.deadline_share is not None:
            if not 0 < self.deadline_share <= MAX_DEADLINE_SHARE:
                raise ValueError(
                    f"RuntimeConfig.deadline_share must be in (0, {MAX_DEADLINE_SHARE:g}], got "
                    f"{self.deadline_share!r}"
                )
        elif not (self.deadline_s > 0 and math.isfinite(self.deadline_s)):
            raise ValueError(
                f"RuntimeConfig.deadline_s must be > 0 (or deadline_share given), got "
                f"{self.deadline_s!r}"
            )
        if not 0 < self.adjust_target <= 1.5:
            raise ValueError(
                f"RuntimeConfig.adjust_target must be in (0, 1.5], got {self.adjust_target}"
            )
        if self.online_quality not in ONLINE_QUALITIES:
            raise ValueError(
                f"RuntimeConfig.online_quality must be one of {ONLINE_QUALITIES}, "
                f"got {self.online_quality!r}"
            )
        for name in ("eval_threshold", "golden_timeout_s", "task_timeout_s", "rebuild_timeout_s"):
            v = getattr(self, name)
            if v is not None and not v > 0:
                raise ValueError(f"RuntimeConfig.{name} must be > 0 or None, got {v!r}")
        if not (self.calib_check_s >= 0 and math.isfinite(self.calib_check_s)):
            raise ValueError(f"RuntimeConfig.calib_check_s must be >= 0, got {self.calib_check_s}")
        if not 0 < self.background_scale <= 1:
            raise ValueError(
                f"RuntimeConfig.background_scale must be in (0, 1], got {self.background_scale}"
            )
        if self.sparse_scope not in SPARSE_SCOPES:
            raise ValueError(
                f"RuntimeConfig.sparse_scope must be one of {SPARSE_SCOPES}, "
                f"got {self.sparse_scope!r}"
            )
        if not (self.watchdog_factor >= 1 and self.watchdog_min_s > 0):
            raise ValueError(
                "RuntimeConfig.watchdog_factor must be >= 1 and watchdog_min_s > 0, got "
                f"{self.watchdog_factor}, {self.watchdog_min_s}"
            )

    def task_configs(
        self, scale: float, rig: Rig, camera_ids: Sequence[int] | None = None
    ) -> tuple[ReconstructionConfig, SplitPipelineConfig]:
        """``pipeline.task_configs`` of a task of image scale ``scale`` with these settings
        (the front-end's tasks, the back-end's snapshots, the benchmarks)."""
        return task_configs(
            scale,
            rig,
            camera_ids=camera_ids,
            sparse_config=self.sparse,
            dense_config=self.dense,
            split_config=self.split,
        )

    def eval_threshold_for(self, rig: Rig) -> float:
        """The online (and offline) F-score threshold d for ``rig``, in its units."""
        if self.eval_threshold is not None:
            return self.eval_threshold
        return self.eval_threshold_rel * median_camera_distance(rig)

    @property
    def watchdog_s(self) -> float:
        """Seconds after which a task is abandoned (see ``task_timeout_s``)."""
        if self.task_timeout_s is not None:
            return self.task_timeout_s
        return max(self.watchdog_factor * self.deadline_s, self.watchdog_min_s)

    @property
    def rebuild_limit_s(self) -> float:
        """Seconds after which a background rebuild's process is killed (see
        ``rebuild_timeout_s``)."""
        if self.rebuild_timeout_s is not None:
            return self.rebuild_timeout_s
        return max(10.0 * self.watchdog_s, 300.0)

    @property
    def golden_wait_s(self) -> float:
        return (
            self.golden_timeout_s
            if self.golden_timeout_s is not None
            else max(2.0, self.deadline_s)
        )


def median_camera_distance(rig: Rig) -> float:
    """Median distance from the cameras to the point their optical axes pass closest to (a
    natural length scale of a rig)."""
    c = rig.centers
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for ci, cam in zip(c, rig, strict=True):
        d = cam.viewing_direction
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ ci
    try:
        target = np.linalg.solve(A, b)
    except np.linalg.LinAlgError:
        target = c.mean(axis=0)
    return float(np.median(np.linalg.norm(c - target, axis=1)))
