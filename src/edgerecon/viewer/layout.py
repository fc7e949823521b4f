"""What the viewer shows, as pure functions: the first view of a rig, the task panel and the
chart's series (no viewer library; tested alone)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from edgerecon.geometry.camera import Rig
from edgerecon.runtime.messages import TaskMetrics
from edgerecon.viewer.colors import unit_to_metres

#: Vertical field of view of the browser's camera when a client first connects.
INITIAL_FOV_DEG = 60.0


def timeline(
    tasks: list[TaskMetrics],
) -> tuple[NDArray[np.float64], ...]:
    """(task, latency s, deadline s, online F, offline F) arrays for the chart; NaN where a
    task has no value (failed tasks, no estimate)."""
    x = np.array([m.task for m in tasks], np.float64)
    lat = np.array([m.critical_path_s if m.status == "ok" else np.nan for m in tasks])
    dl = np.array([m.deadline_s or np.nan for m in tasks], np.float64)
    fon = np.array([np.nan if m.online_fscore is None else m.online_fscore for m in tasks])
    foff = np.array([np.nan if m.offline_fscore is None else m.offline_fscore for m in tasks])
    return x, lat, dl, fon, foff


def task_panel(
    m: TaskMetrics, rig: Rig | None, num_points: int, drawn: int, newest: TaskMetrics
) -> str:
    """Markdown of one task's panel (what the viewer shows next to the cloud)."""
    if m.status != "ok":
        state = f"FAILED: {m.error}"
    elif m.degraded:
        state = "degraded" + (f" ({m.degraded_reason})" if m.degraded_reason else "")
    else:
        state = "ok"
    names = (
        ", ".join(rig.names[i] for i in m.camera_ids if 0 <= i < len(rig))
        if rig is not None
        else ", ".join(str(i) for i in m.camera_ids)
    )
    of = f" of {len(rig)}" if rig is not None else ""
    met = "met" if m.deadline_met else "**missed**"

    def f(v: float | None) -> str:
        return "-" if v is None else f"{v:.3f}"

    lag = "" if newest.task == m.task else f" (newest: task {newest.task})"
    rows = [
        ("time index", str(m.time_index)),
        ("state", state),
        ("phase", m.phase or "-"),
        ("r (image scale)", f"{m.scale:.2f}" + (" (finer than golden)" if m.scale > 1 else "")),
        ("N' (cameras)", f"{m.num_cameras}{of}: {names}"),
        ("latency", f"{m.critical_path_s:.2f} s / deadline {m.deadline_s:.2f} s ({met})"),
        ("F online", f(m.online_fscore)),
        ("F offline (ground truth)", f(m.offline_fscore)),
        ("background", f"v{m.bg_version}"),
        ("points", f"{num_points:,} (drawn {drawn:,})"),
    ]
    table = "\n".join(f"| {k} | {v} |" for k, v in rows)
    return f"**task {m.task}**{lag}\n\n| | |\n|---|---|\n{table}\n"


@dataclass(frozen=True, kw_only=True)
class ViewPose:
    """Where the browser's camera starts (metres, world frame)."""

    position: NDArray[np.float64]
    look_at: NDArray[np.float64]
    up: NDArray[np.float64]
    fov_deg: float
    """Vertical field of view, degrees."""


def initial_view(rig: Rig) -> ViewPose:
    """The first view of a rig: above and outside it, between its first camera and that
    camera's nearest neighbour, a little farther out than the rig, looking at the point the cameras look at, with the rig's up."""
    to_m = unit_to_metres(rig.unit)
    up = np.asarray(rig.up, np.float64)
    up = up / (np.linalg.norm(up) or 1.0)
    centers = rig.centers * to_m
    target = _look_target(rig) * to_m
    flat = centers - target
    flat -= np.outer(flat @ up, up)
    flat /= np.maximum(np.linalg.norm(flat, axis=1), 1e-12)[:, None]
    # Between the first camera and its nearest neighbour (around the scene), so that no
    # camera's frustum stands right in front of the view.
    others = flat[1:] @ flat[0]
    out = flat[0] + (flat[1 + int(np.argmax(others))] if len(others) else 0.0)
    if np.linalg.norm(out) < 1e-6:
        out = flat[0]
    out = out / np.linalg.norm(out)
    cam_h = float(np.max((centers - target) @ up))
    position = target + out * 1.3 * np.max(np.linalg.norm(centers - target, axis=1))
    position = position + up * max(cam_h * 1.3, 0.4 * rig.scene_scale() * to_m)
    return ViewPose(position=position, look_at=target, up=up, fov_deg=INITIAL_FOV_DEG)


def _look_target(rig: Rig) -> NDArray[np.float64]:
    """The point closest to all optical axes (least squares): what the rig looks at."""
    a = np.zeros((3, 3))
    b = np.zeros(3)
    for cam in rig:
        d = np.asarray(cam.viewing_direction, np.float64)
        d /= np.linalg.norm(d)
        p = np.eye(3) - np.outer(d, d)
        a += p
        b += p @ cam.center
    if np.linalg.cond(a) > 1e8:
        dirs = np.array([c.viewing_direction for c in rig])
        return np.asarray(
            rig.centers.mean(axis=0) + dirs.mean(axis=0) * rig.scene_scale(), np.float64
        )
    return np.asarray(np.linalg.solve(a, b), np.float64)
