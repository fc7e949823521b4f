"""The front-end role: each task's critical path, the online evaluation, the optimizer.

Per task: SfM with the optimizer's configuration (r, pi(N')) while the back-end computes the
masks; then the sparse split with the masks it receives (or computes itself when the back-end
is lost), foreground MVS in the foreground regions only, and the merge with the newest
background it holds. The critical path ends when the merged cloud is ready; then the front-end
scores the task's foreground sparse cloud against the back-end's golden reference (the online
quality estimate) and feeds (T, Q) to the controller.

Plain Python, usable without a cluster; the Ray engine wraps it in an actor.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from edgerecon.config import MIN_CAMERAS, ReconstructionConfig
from edgerecon.geometry.camera import Rig
from edgerecon.optimize.controller import BisectionController
from edgerecon.optimize.selection import camera_mapping, visibility_from_points
from edgerecon.pipeline import foreground_views, prepare_task_views, reconstruct_foreground
from edgerecon.quality.online import OnlineQualityConfig, online_quality
from edgerecon.runtime.config import RuntimeConfig
from edgerecon.runtime.messages import (
    BackgroundUpdate,
    GoldenReply,
    MasksReply,
    TaskMetrics,
    TaskPlan,
)
from edgerecon.scene.background import BackgroundState
from edgerecon.scene.foreground import ForegroundResult, RigForeground
from edgerecon.scene.merge import merge_clouds
from edgerecon.sparse import reconstruct_sparse
from edgerecon.types import FrameSet, PointCloud, StageTimings

logger = logging.getLogger(__name__)

#: Waits for a reply: ``provider(timeout_s)`` returns the reply or None (late or unavailable).
MasksProvider = Callable[[float], MasksReply | None]
GoldenProvider = Callable[[float], GoldenReply | None]

#: Fewer sparse points than this and camera selection also uses the dense foreground points.
_MIN_SELECTION_POINTS = 200


@dataclass(frozen=True, kw_only=True, eq=False)
class TaskOutput:
    """What a task publishes: its merged cloud and its metrics."""

    metrics: TaskMetrics
    merged: PointCloud
    foreground: PointCloud


class FixedController:
    """A controller that always returns one configuration (for baselines, e.g. the golden
    pipeline every task, and for comparing engines task by task)."""

    def __init__(self, scale: float, camera_ids: tuple[int, ...]) -> None:
        self.scale = float(scale)
        self.ids = tuple(camera_ids)
        self.search_steps = 0
        self.total_search_steps = 0

    def next_config(self) -> TaskPlan:
        return TaskPlan(time_index=-1, scale=self.scale, camera_ids=self.ids, phase="fixed")

    def observe(self, time_s: float, quality: float | None = None) -> None:
        del time_s, quality

    def set_camera_mapping(self, mapping: Any, restart: bool = False) -> None:
        del mapping, restart

    def to_dict(self) -> dict[str, Any]:
        return {"format": "edgerecon-fixed", "scale": self.scale, "camera_ids": list(self.ids)}


class FrontEnd:
    """Front-end node role (see module docstring)."""

    def __init__(
        self,
        rig: Rig,
        config: RuntimeConfig,
        controller: BisectionController | FixedController,
        *,
        model_states: Sequence[BackgroundState] | None = None,
    ) -> None:
        self.rig = rig
        self.config = config
        self.controller = controller
        self._local_fg: RigForeground | None = None
        self._lock = threading.Lock()
        self._background = PointCloud.empty()
        self._bg_version = 0
        self._bg_states: tuple[BackgroundState, ...] | None = (
            None if model_states is None else tuple(model_states)
        )
        self._mapping_ready = isinstance(controller, FixedController)
        self.backgrounds_received = 0
        self.eval_threshold = config.eval_threshold_for(rig)

    # ------------------------------------------------------------------ background pushes
    def push_background(self, update: BackgroundUpdate) -> int:
        """Take a newer background (older or duplicate versions are ignored). Returns the
        version now held."""
        with self._lock:
            if update.version > self._bg_version:
                self._background = update.cloud
                self._bg_version = update.version
                if update.model_states is not None:
                    self._bg_states = update.model_states
                self.backgrounds_received += 1
            return self._bg_version

    @property
    def bg_version(self) -> int:
        return self._bg_version

    def background(self) -> tuple[PointCloud, int]:
        with self._lock:
            return self._background, self._bg_version

    # ------------------------------------------------------------------ planning
    def next_plan(self, time_index: int) -> TaskPlan:
        cfg = self.controller.next_config()
        ids = tuple(int(i) for i in cfg.camera_ids)
        return TaskPlan(
            time_index=time_index, scale=float(cfg.scale), camera_ids=ids, phase=str(cfg.phase)
        )

    # ------------------------------------------------------------------ the task
    def process(
        self,
        frames: FrameSet,
        plan: TaskPlan,
        masks: MasksProvider,
        golden: GoldenProvider,
        *,
        task: int = 0,
    ) -> TaskOutput:
        """Run one task (critical path, then online evaluation and the optimizer step)."""
        timings = StageTimings()
        start = time.perf_counter()
        cfg = ReconstructionConfig(
            scale=plan.scale, camera_ids=plan.camera_ids, sparse_config=self.config.sparse
        )
        scene_sfm = self.config.sparse_scope == "scene"
        if scene_sfm:  # the paper's order: SfM of the whole frames while masks are computed
            with timings.stage("sfm"):
                views = prepare_task_views(frames, self.rig, cfg)
                sparse = reconstruct_sparse(views, self.config.sparse)
        degraded, reason = False, ""
        with timings.stage("wait_masks"):
            reply = masks(self.config.masks_wait_s)
        if reply is None:
            degraded, reason = True, "no masks from the back-end"
            with timings.stage("local_masks"):
                fg = self._local_foreground(frames)
        else:
            fg = reply.foreground
            # Back to normal: the next outage starts from the back-end's newest snapshot.
            self._local_fg = None
        if not scene_sfm:  # SfM of the foreground only
            with timings.stage("sfm"):
                views = prepare_task_views(frames, self.rig, cfg)
                sparse = reconstruct_sparse(
                    foreground_views(
                        views, self.rig, fg.masks, self.config.split.fg_mask_dilation_px
                    ),
                    self.config.sparse,
                )
        fg_rec = reconstruct_foreground(
            views, self.rig, sparse, fg, self.config.dense, self.config.split
        )
        for name, seconds in fg_rec.timings.seconds.items():
            timings.add(name, seconds)
        background, bg_version = self.background()
        with timings.stage("merge"):
            merged = merge_clouds(
                fg_rec.cloud,
                background,
                bg_version=bg_version,
                scene_scale=self.rig.scene_scale(),
                hull=fg.hull,
            )
        critical = time.perf_counter() - start

        # ---- after the critical path: online evaluation and the optimizer step
        quality: float | None = None
        if not degraded:
            ref = golden(self.config.golden_wait_s)
            if ref is None:
                reason = "no golden reference from the back-end"
            else:
                quality = online_quality(
                    fg_rec.fg_sparse.points3D,
                    ref.fg_points3D,
                    OnlineQualityConfig(threshold=self.eval_threshold),
                ).value
        if plan.phase == "golden" and not self._mapping_ready:
            self._set_mapping(sparse.visibility_matrix(len(self.rig)), fg_rec.cloud)
        self.controller.observe(critical, quality)
        labels = fg_rec.labels
        metrics = TaskMetrics(
            task=task,
            time_index=frames.time_index,
            status="ok",
            phase=plan.phase,
            scale=plan.scale,
            num_cameras=len(views),
            camera_ids=[v.camera_id for v in views],
            critical_path_s=round(critical, 6),
            stages=timings.to_dict(),
            deadline_s=self.config.deadline_s,
            deadline_met=critical <= self.config.deadline_s,
            online_fscore=quality,
            bg_version=bg_version,
            degraded=degraded,
            degraded_reason=reason,
            num_sparse=sparse.num_points,
            num_sparse_fg=int(np.count_nonzero(labels > 0)),
            num_fg_points=len(fg_rec.cloud),
            num_merged_points=len(merged),
            num_objects=int(labels.max()) if labels.size and labels.max() > 0 else 0,
            search_steps=int(getattr(self.controller, "total_search_steps", 0)),
            wall_time=time.time(),
        )
        return TaskOutput(metrics=metrics, merged=merged, foreground=fg_rec.cloud)

    def _local_foreground(self, frames: FrameSet) -> ForegroundResult:
        """Masks computed on the front-end (degraded mode), with the newest snapshot of the
        background models it holds (the initial one, or one pushed with a background)."""
        if self._local_fg is None:
            if self._bg_states is None:
                raise RuntimeError("no masks from the back-end and no background model snapshot")
            self._local_fg = RigForeground.from_states(
                self.rig, self._bg_states, self.config.foreground
            )
        return self._local_fg.segment(frames)

    def _set_mapping(self, visibility: np.ndarray, fg_cloud: PointCloud) -> None:
        """pi(N') from the golden task: its sparse visibility, topped up with the dense
        foreground's visibility when the sparse cloud is thin (wide-baseline rigs)."""
        vis = visibility
        if len(vis) < _MIN_SELECTION_POINTS and len(fg_cloud):
            extra = visibility_from_points(fg_cloud.points3D, self.rig.cameras, fg_cloud.normals)
            vis = np.vstack([vis, extra])
        mapping = camera_mapping(
            vis,
            camera_centers=self.rig.centers,
            viewing_directions=np.array([c.viewing_direction for c in self.rig]),
            sizes=range(len(self.rig), MIN_CAMERAS - 1, -1),
        )
        self.controller.set_camera_mapping(mapping)
        self._mapping_ready = True
        logger.info("front-end: camera mapping pi(N') from %d visibility rows", len(vis))
