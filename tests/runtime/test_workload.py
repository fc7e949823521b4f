"""The front-end scales an adjusted task's r by its workload (RuntimeConfig.workload)."""

from __future__ import annotations

import numpy as np
import pytest

from edgerecon.optimize.controller import BisectionController, ControllerConfig
from edgerecon.optimize.workload import WorkloadConfig
from edgerecon.runtime import RuntimeConfig
from edgerecon.runtime.frontend import FixedController, FrontEnd, FrontEndState
from edgerecon.runtime.messages import TaskPlan
from tests.conftest import ring_rig

_WORKLOAD = WorkloadConfig(min_history=2, max_factor=1.5)


def _front(workload=_WORKLOAD, controller=None, restored=None):
    ctrl = controller or BisectionController(
        ControllerConfig(deadline_s=1.0, r_fine=2.0), None, num_cameras=4
    )
    return FrontEnd(
        ring_rig(4), RuntimeConfig(deadline_s=1.0, workload=workload), ctrl, restored=restored
    )


def _plan(scale, phase="adjust", ids=(0, 1, 2, 3)):
    return TaskPlan(time_index=0, scale=scale, camera_ids=ids, phase=phase)


def test_adjusted_tasks_follow_their_workload_within_the_controllers_range():
    fe = _front()
    assert fe.workload is not None
    # Tasks of 20 % foreground: 0.2 s of scene stage, then 0.8 s of MVS at r = 1 (the
    # controller's target: its deadline of 1 s).
    for _ in range(2):
        fe.workload.record(0.2, 0.2, 1.0, 0.8)
    # The golden task and the search run the controller's r whatever the masks.
    assert fe._workload_scale(_plan(1.0, "golden"), 0.4, 0.2) == 1.0
    assert fe._workload_scale(_plan(0.6, "search"), 0.4, 0.2) == 0.6
    assert fe._workload_scale(_plan(1.0), 0.2, 0.2) == pytest.approx(1.0)
    # Twice the foreground: r / sqrt(2); a scene stage that took 0.6 s instead of 0.2 s
    # leaves half the MVS's time: r / sqrt(2) as well.
    assert fe._workload_scale(_plan(1.0), 0.4, 0.2) == pytest.approx(1 / np.sqrt(2), abs=1e-6)
    assert fe._workload_scale(_plan(1.0), 0.2, 0.6) == pytest.approx(1 / np.sqrt(2), abs=1e-6)
    # Half the foreground: r x sqrt(2); at most 1.5x; never above r_fine with every camera,
    # nor above r_max with fewer, nor below r_min.
    assert fe._workload_scale(_plan(1.0), 0.1, 0.2) == pytest.approx(np.sqrt(2), abs=1e-6)
    assert fe._workload_scale(_plan(1.0), 0.01, 0.2) == 1.5
    assert fe._workload_scale(_plan(1.4), 0.01, 0.2) == 2.0
    assert fe._workload_scale(_plan(0.95, ids=(0, 1, 2)), 0.01, 0.2) == 1.0
    assert fe._workload_scale(_plan(0.32), 0.9, 0.9) == 0.3
    # The cost survives a restart through the front-end's state.
    state = FrontEndState.from_dict(fe.state().to_dict())
    assert state.workload_history == fe.workload.history and len(state.workload_history) == 2
    again = _front(restored=state)
    assert again.workload is not None and again.workload.history == fe.workload.history


def test_a_controller_with_time_to_spare_keeps_its_r():
    """At its ceiling with the deadline far away (r_fine = r_max here), a task with a little
    more foreground than usual still fits: r stays (it was 0.996 in an online test)."""
    ctrl = BisectionController(ControllerConfig(deadline_s=20.0), None, num_cameras=4)
    fe = _front(controller=ctrl)
    assert fe.workload is not None
    for _ in range(3):
        fe.workload.record(0.2, 0.2, 1.0, 0.8)
    assert fe._workload_scale(_plan(1.0), 0.21, 0.2) == 1.0


def test_off_and_fixed_configurations_keep_the_planned_scale():
    off = _front(workload=None)
    assert off.workload is None and off._workload_scale(_plan(0.7), 0.9, 0.2) == 0.7
    fixed = _front(controller=FixedController(0.7, (0, 1, 2, 3)))
    assert fixed.workload is not None
    for _ in range(4):
        fixed.workload.record(0.2, 0.2, 0.7, 0.8)
    assert fixed._workload_scale(_plan(0.7, "fixed"), 0.8, 0.2) == 0.7


def test_a_scaled_r_inside_a_skipped_interval_runs_at_its_upper_end():
    """The workload's r never lands where a larger r costs less (the controller's
    ``skip_scales``): up to the interval's upper end, which is as fast and finer."""
    cfg = ControllerConfig(deadline_s=1.0, r_fine=2.0, skip_scales=((0.45, 0.57),))
    fe = _front(controller=BisectionController(cfg, None, num_cameras=4))
    assert fe.workload is not None
    for _ in range(2):
        fe.workload.record(0.2, 0.2, 0.6, 0.8)
    # 0.6 / sqrt(1.25) = 0.537: inside, so 0.57; 0.6 / sqrt(2) = 0.424: below, as it is.
    assert fe._workload_scale(_plan(0.6), 0.25, 0.2) == 0.57
    assert fe._workload_scale(_plan(0.6), 0.4, 0.2) == pytest.approx(0.6 / np.sqrt(2), abs=1e-6)


def test_the_online_controller_skips_the_rigs_dominated_scales():
    """``make_controller`` sets ``skip_scales`` from the rig (``pipeline.dominated_scales``);
    ``skip_dominated_scales = false`` leaves every r."""
    from edgerecon.pipeline import dominated_scales
    from edgerecon.runtime.online import make_controller

    class _Ds:
        rig = ring_rig(4, width=1280, height_px=720, focal_px=1000.0)

    ctrl = make_controller(_Ds(), RuntimeConfig(deadline_s=1.0))  # type: ignore[arg-type]
    assert isinstance(ctrl, BisectionController)
    assert ctrl.config.skip_scales == dominated_scales(_Ds.rig, 0.3, 1.0, 2.0)
    assert len(ctrl.config.skip_scales) == 2
    off = make_controller(  # type: ignore[arg-type]
        _Ds(), RuntimeConfig(deadline_s=1.0, skip_dominated_scales=False)
    )
    assert isinstance(off, BisectionController) and off.config.skip_scales == ()
