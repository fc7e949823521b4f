"""The latency / quality model, the driver and the summary."""

from __future__ import annotations

import numpy as np
import pytest

from edgerecon.optimize import (
    PipelineModel,
    SimulatorConfig,
    run_simulation,
    synthetic_visibility,
    true_optimum,
)


def test_model_is_monotone_and_matches_its_formula():
    m = PipelineModel(SimulatorConfig(num_cameras=7, base_s=3.0, per_camera_s=1.1))
    assert m.time_s(1.0, 7) == pytest.approx(3.0 + 1.1 * 7)
    assert m.time_s(0.5, 4) == pytest.approx(3.0 + 1.1 * 0.25 * 4)
    assert m.quality(1.0, 7) == pytest.approx(1.0)
    rs = np.linspace(0.3, 1.0, 15)
    for n in range(3, 8):
        t = [m.time_s(r, n) for r in rs]
        q = [m.quality(r, n) for r in rs]
        assert np.all(np.diff(t) > 0) and np.all(np.diff(q) > 0)
    for r in rs:
        assert np.all(np.diff([m.time_s(r, n) for n in range(3, 8)]) > 0)
        assert np.all(np.diff([m.quality(r, n) for n in range(3, 8)]) > 0)


def test_noise_bounds_and_load_changes():
    m = PipelineModel(
        SimulatorConfig(
            time_noise=0.15, quality_noise=0.0, load_steps=((10, 2.0),), drift_per_task=0.0
        )
    )
    rng = np.random.default_rng(0)
    base = m.time_s(0.7, 5)
    ts = np.array([m.sample(0.7, 5, 0, rng)[0] for _ in range(2000)])
    assert ts.min() >= 0.85 * base and ts.max() <= 1.15 * base
    assert abs(ts.mean() / base - 1) < 0.01
    assert m.time_s(0.7, 5, task=10) == pytest.approx(2 * base)
    drift = PipelineModel(SimulatorConfig(drift_per_task=0.01))
    assert drift.time_s(0.7, 5, task=10) == pytest.approx(drift.time_s(0.7, 5) * 1.01**10)


def test_true_optimum_known_answer():
    # T = r^2 N', Q = r (N'/4)^1: with limit 1, N' = 4 -> r = 0.5, Q = 0.5;
    # N' = 3 -> r = 0.577, Q = 0.433: N' = 4 wins
    m = PipelineModel(
        SimulatorConfig(
            num_cameras=4,
            base_s=0.0,
            per_camera_s=1.0,
            quality_scale_exponent=1.0,
            quality_camera_exponent=1.0,
        )
    )
    opt = true_optimum(m, 1.0, r_min=0.3)
    assert opt.num_cameras == 4 and opt.scale == pytest.approx(0.5, abs=2e-4)
    assert not true_optimum(m, 0.1).feasible


def test_quality_table_from_camera_coverage():
    with pytest.raises(ValueError, match="non-decreasing"):
        SimulatorConfig(num_cameras=4, quality_by_cameras={3: 0.9, 4: 0.8})
    m = PipelineModel(SimulatorConfig(num_cameras=4, quality_by_cameras={3: 0.7, 4: 1.0}))
    assert m.quality(1.0, 3) == pytest.approx(0.7)


def test_summary_counts_and_rows():
    res = run_simulation(7.5, 120, seed=0)
    s = res.summary
    assert s.tasks == len(res.rows) == 120
    assert s.converged_task is not None
    assert s.tasks_converged == 120 - s.converged_task
    assert s.misses == sum(r.time_s > r.deadline_s for r in res.rows)
    assert all(r.phase == "adjust" for r in res.rows[s.converged_task :])
    assert (
        s.search_steps == sum(r.phase != "adjust" for r in res.rows[: s.converged_task])
        or s.num_searches > 1
    )
    assert res.rows[0].phase == "golden" and res.rows[0].quality == 1.0
    d = res.rows[3].to_dict()
    assert set(d) >= {"task", "phase", "scale", "num_cameras", "time_s", "quality", "miss"}


def test_synthetic_visibility_is_structured():
    vis, centers, dirs = synthetic_visibility(12, 3000, seed=0)
    assert vis.shape == (3000, 12) and centers.shape == (12, 3) and dirs.shape == (12, 3)
    per_point = vis.sum(axis=1)
    assert 1 < per_point.mean() < 8
    # neighbouring cameras share far more points than opposite ones
    share = (vis[:, :, None] & vis[:, None, :]).sum(axis=0)
    assert share[0, 1] > 5 * max(share[0, 6], 1)


def test_config_validation():
    with pytest.raises(ValueError, match="num_cameras"):
        SimulatorConfig(num_cameras=2)
    with pytest.raises(ValueError, match="load_steps"):
        SimulatorConfig(load_steps=((5, 0.0),))
    with pytest.raises(ValueError, match="num_tasks"):
        run_simulation(5.0, 0)
