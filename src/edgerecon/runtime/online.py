"""``run_online``: assemble the online system (controller, scene model, engine, session)."""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

from edgerecon.io.dataset import Dataset
from edgerecon.optimize.controller import BisectionController, ControllerConfig
from edgerecon.runtime.config import RuntimeConfig
from edgerecon.runtime.engine import EmbeddedEngine, SceneModel, learn_scene_model
from edgerecon.runtime.frontend import FixedController
from edgerecon.runtime.messages import BackgroundUpdate, TaskMetrics
from edgerecon.runtime.session import STATE_FORMAT, RunSummary, Session, SessionOptions
from edgerecon.types import EdgereconError

logger = logging.getLogger(__name__)


def make_controller(
    dataset: Dataset,
    config: RuntimeConfig,
    *,
    fixed: tuple[float, tuple[int, ...] | None] | None = None,
    controller_config: ControllerConfig | None = None,
    saved_state: dict[str, Any] | None = None,
) -> BisectionController | FixedController:
    """The optimizer (Algorithm 1) or, with ``fixed=(scale, camera_ids)``, one configuration
    for every task (None camera ids = all)."""
    n = len(dataset.rig)
    if fixed is not None:
        scale, ids = fixed
        return FixedController(scale, tuple(range(n)) if ids is None else tuple(ids))
    if saved_state is not None and saved_state.get("format") == "edgerecon-controller":
        return BisectionController.from_dict(saved_state)
    cc = controller_config or ControllerConfig(deadline_s=config.deadline_s)
    return BisectionController(cc, None, n)


def run_online(
    dataset: Dataset,
    config: RuntimeConfig,
    options: SessionOptions,
    out_dir: str | Path,
    *,
    engine: str = "embedded",
    address: str | None = None,
    fixed: tuple[float, tuple[int, ...] | None] | None = None,
    controller_config: ControllerConfig | None = None,
    scene: SceneModel | None = None,
    on_task: Callable[[TaskMetrics], None] | None = None,
    on_ready: Callable[[SceneModel], None] | None = None,
) -> tuple[RunSummary, list[TaskMetrics]]:
    """Run the online system on ``dataset`` and return its summary and per-task metrics."""
    out = Path(out_dir)
    saved = None
    if options.resume and (out / "state.json").exists():
        state = json.loads((out / "state.json").read_text())
        if state.get("format") != STATE_FORMAT:
            raise EdgereconError(f"{out / 'state.json'}: not an edgerecon run state")
        saved = state.get("controller")
    controller = make_controller(
        dataset, config, fixed=fixed, controller_config=controller_config, saved_state=saved
    )
    if scene is None:
        first = options.frames.indices(dataset.num_frames)[:1]
        scene = learn_scene_model(dataset, config.foreground, first[0] if first else 0)
    if on_ready is not None:
        on_ready(scene)
    if engine == "embedded":
        eng: Any = EmbeddedEngine(dataset, config, controller, scene)
    elif engine == "ray":
        from edgerecon.runtime.ray_engine import RayEngine

        eng = RayEngine(dataset, config, controller, scene, address=address)
    else:
        raise EdgereconError(f"unknown engine {engine!r}: use 'embedded' or 'ray'")
    try:
        session = Session(dataset, eng, options, out, deadline_s=config.deadline_s, on_task=on_task)
        if options.resume:
            previous = session.previous_background()
            if previous is not None:
                cloud, version = previous
                eng.push_background(BackgroundUpdate(version=version, cloud=cloud, seconds=0.0))
        summary = session.run()
        status = eng.status()
        summary.backgrounds_pushed = max(
            summary.backgrounds_pushed, int(status.get("backgrounds_received", 0))
        )
        return summary, session.metrics
    finally:
        eng.close()
