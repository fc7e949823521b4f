"""The front-end scales an adjusted task's r by its masks' area (RuntimeConfig.workload)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from edgerecon.optimize.controller import BisectionController, ControllerConfig
from edgerecon.optimize.workload import WorkloadConfig
from edgerecon.runtime import RuntimeConfig
from edgerecon.runtime.frontend import FixedController, FrontEnd, FrontEndState
from edgerecon.runtime.messages import TaskPlan
from tests.conftest import ring_rig


def _masks(share: float, n: int = 4) -> SimpleNamespace:
    m = np.zeros((10, 10), bool)
    m.flat[: round(100 * share)] = True
    return SimpleNamespace(masks=tuple(m.copy() for _ in range(n)))


_WORKLOAD = WorkloadConfig(min_history=2, max_factor=1.5)


def _front(workload=_WORKLOAD, controller=None, restored=None):
    rig = ring_rig(4)
    ctrl = controller or BisectionController(
        ControllerConfig(deadline_s=1.0, r_fine=2.0), None, num_cameras=4
    )
    config = RuntimeConfig(deadline_s=1.0, workload=workload)
    return FrontEnd(rig, config, ctrl, restored=restored)


def _plan(scale, phase="adjust", ids=(0, 1, 2, 3)):
    return TaskPlan(time_index=0, scale=scale, camera_ids=ids, phase=phase)


def test_adjusted_tasks_follow_the_area_within_the_controllers_range():
    fe = _front()
    # The golden task and the search run the controller's r, and teach the reference.
    assert fe._workload_scale(_plan(1.0, "golden"), _masks(0.2), 0.2) == 1.0
    assert fe._workload_scale(_plan(0.6, "search"), _masks(0.2), 0.2) == 0.6
    # Twice the usual foreground (the same time before the MVS): r / sqrt(2); half of it:
    # r x sqrt(2); at most 1.5x.
    assert fe._workload_scale(_plan(1.0), _masks(0.4), 0.2) == pytest.approx(
        1 / np.sqrt(2), abs=1e-6
    )
    assert fe.workload is not None
    fe.workload._tasks.clear()
    for _ in range(3):
        fe.workload.record(0.2, 0.2)
    assert fe._workload_scale(_plan(1.0), _masks(0.1), 0.2) == pytest.approx(np.sqrt(2), abs=1e-6)
    assert fe._workload_scale(_plan(1.0), _masks(0.01), 0.2) == 1.5
    # A task whose scene stage took the MVS's usual time away runs coarser.
    slow = fe._workload_scale(_plan(1.0), _masks(0.2), 0.6)
    assert slow < 1.0
    # Never above r_fine with every camera, nor above r_max with fewer, nor below r_min.
    assert fe._workload_scale(_plan(1.4), _masks(0.01), 0.2) == 2.0
    assert fe._workload_scale(_plan(0.95, ids=(0, 1, 2)), _masks(0.01), 0.2) == 1.0
    assert fe._workload_scale(_plan(0.32), _masks(0.9), 0.2) == 0.3
    # The reference survives a restart through the front-end's state.
    state = FrontEndState.from_dict(fe.state().to_dict())
    assert state.workload_history == fe.workload.history and len(state.workload_history) == 8
    again = _front(restored=state)
    assert again.workload is not None and again.workload.history == fe.workload.history


def test_off_and_fixed_configurations_keep_the_planned_scale():
    assert _front(workload=None).workload is None
    fixed = _front(controller=FixedController(0.7, (0, 1, 2, 3)))
    for _ in range(4):
        assert fixed._workload_scale(_plan(0.7, "fixed"), _masks(0.2), 0.2) == 0.7
    assert fixed._workload_scale(_plan(0.7, "fixed"), _masks(0.8), 0.2) == 0.7
