"""Small run folders written the way the session writes them (no pipeline run needed)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from edgerecon.io.calibration import save_rig
from edgerecon.io.ply import write_ply
from edgerecon.runtime.messages import TaskMetrics
from edgerecon.types import PointCloud
from edgerecon.viewer.rundir import task_cloud_path
from tests.conftest import ring_rig

#: Colour of the test clouds' foreground (pure red: nothing else in the viewer is).
FG_RGB = (220, 20, 20)
BG_RGB = (40, 60, 220)


def scene_cloud(shift: float = 0.0, inferred: bool = False, n_fg: int = 6000) -> PointCloud:
    """A person-sized box (foreground, object 1) standing on a floor patch (background) at
    the origin of ``ring_rig`` (metres, z up), shifted along x by ``shift``."""
    rng = np.random.default_rng(0)
    fg = rng.uniform([-0.25, -0.25, 0.0], [0.25, 0.25, 1.8], (n_fg, 3))
    fg[:, 0] += shift
    floor = np.stack(np.meshgrid(np.linspace(-1.5, 1.5, 60), np.linspace(-1.5, 1.5, 60)), -1)
    bg = np.column_stack([floor.reshape(-1, 2), np.zeros(60 * 60)])
    pts = np.vstack([fg, bg])
    labels = np.r_[np.ones(len(fg), np.int32), np.zeros(len(bg), np.int32)]
    colors = np.vstack([np.tile(FG_RGB, (len(fg), 1)), np.tile(BG_RGB, (len(bg), 1))])
    attrs = {"bg_version": np.r_[np.ones(len(fg)), np.full(len(bg), 1)].astype(np.int32)}
    if inferred:
        attrs["inferred"] = (np.arange(len(pts)) % 2).astype(np.uint8)
    return PointCloud(points3D=pts, colors=colors, labels=labels, attributes=attrs)


def task_metrics(task: int, **kw: object) -> TaskMetrics:
    values: dict[str, object] = dict(
        task=task,
        time_index=2 * task,
        status="ok",
        phase="search" if task < 3 else "adjust",
        scale=1.0 - 0.1 * task,
        num_cameras=4,
        camera_ids=[0, 1, 2, 4],
        critical_path_s=1.0 + 0.25 * task,
        stages={"sfm": 0.5, "fg_dense.depth": 0.4 + 0.25 * task},
        deadline_s=1.5,
        deadline_met=1.0 + 0.25 * task <= 1.5,
        online_fscore=0.9 - 0.05 * task,
        offline_fscore=0.8 - 0.05 * task,
        bg_version=task // 2,
        wall_time=1000.0 + 2.0 * task,
    )
    values.update(kw)
    return TaskMetrics(**values)  # type: ignore[arg-type]


def append_task(run: Path, m: TaskMetrics, cloud: PointCloud | None) -> None:
    """What the session does after a task: the cloud first, then the metrics line."""
    if cloud is not None:
        write_ply(task_cloud_path(run, m.time_index), cloud)
    with open(run / "metrics.jsonl", "a", encoding="utf-8") as f:
        f.write(json.dumps(m.to_dict()) + "\n")


def write_run(run: Path, num_tasks: int = 4, *, finished: bool = True) -> Path:
    """A run folder with ``num_tasks`` tasks of ``ring_rig(5)``."""
    run.mkdir(parents=True, exist_ok=True)
    save_rig(run / "rig.json", ring_rig(5))
    for k in range(num_tasks):
        append_task(run, task_metrics(k), scene_cloud(shift=0.1 * k))
    if finished:
        (run / "summary.json").write_text(json.dumps({"tasks": num_tasks, "wall_s": 8.0}))
    return run
