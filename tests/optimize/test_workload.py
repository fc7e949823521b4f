"""The per-task scale from the masks' area and the time left (optimize.workload)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from edgerecon.optimize.workload import WorkloadConfig, WorkloadScaler, mask_area


def test_factor_follows_the_area_against_the_recent_mean():
    s = WorkloadScaler(WorkloadConfig(window=4, min_history=3, max_factor=1.5))
    assert s.reference() is None
    for _ in range(2):
        s.record(0.1)
        assert s.factor(0.4) == 1.0  # too few tasks to tell what is usual
    s.record(0.1)
    assert s.reference() == pytest.approx((0.1, 0.0))
    assert s.factor(0.1) == pytest.approx(1.0)
    # Twice the usual foreground: r / sqrt(2), the foreground's work ~ area x r^2 stays.
    assert s.factor(0.2) == pytest.approx(1 / math.sqrt(2))
    assert s.factor(0.05) == pytest.approx(math.sqrt(2))
    # Clamped both ways; no foreground at all: the largest step up.
    assert s.factor(10.0) == pytest.approx(1 / 1.5)
    assert s.factor(0.0) == pytest.approx(1.5)
    assert s.factor(None) == 1.0
    # The reference is the last `window` tasks.
    for _ in range(4):
        s.record(0.3)
    assert [t[0] for t in s.history] == [0.3] * 4
    assert s.factor(0.3) == pytest.approx(1.0)


def test_factor_follows_the_time_left_for_the_mvs():
    s = WorkloadScaler(WorkloadConfig(min_history=2, max_factor=2.0))
    s.record(0.2, 0.3, 1.0, 0.6)
    s.record(0.2, 0.5, 1.0, 0.6)  # usually 0.4 s before the MVS: 0.6 s of a 1 s target left
    assert s.reference() == pytest.approx((0.2, 0.4))
    assert s.factor(0.2, 0.4, 1.0) == pytest.approx(1.0)
    # A slow scene stage leaves 0.3 s: half the usual MVS time, r / sqrt(2).
    assert s.factor(0.2, 0.7, 1.0) == pytest.approx(1 / math.sqrt(2))
    # ... and with twice the area on top, a quarter of the usual work per pixel: r / 2.
    assert s.factor(0.4, 0.7, 1.0) == pytest.approx(0.5)
    # Nothing left: the coarsest step; without a target only the area counts.
    assert s.factor(0.2, 1.5, 1.0) == pytest.approx(0.5)
    assert s.factor(0.2, 0.7) == pytest.approx(1.0)
    # A target the usual tasks already spend before their MVS tells nothing about time.
    assert s.factor(0.2, 0.7, 0.42) == pytest.approx(1.0)


def test_a_task_that_fits_at_the_controllers_r_is_not_made_coarser():
    s = WorkloadScaler(WorkloadConfig(min_history=2, max_factor=2.0))
    # 0.6 s of MVS for 20 % of the pixels at r = 1: 3 s per unit of area x r^2.
    s.record(0.2, 0.2, 1.0, 0.6)
    s.record(0.2, 0.2, 1.0, 0.6)
    assert s.predicted_mvs(0.4, 1.0) == pytest.approx(1.2)
    assert s.predicted_mvs(0.2, 2.0) == pytest.approx(2.4)
    # Target 1 s: twice the area does not fit (0.2 + 1.2 s), r / sqrt(2) (the relative factor).
    assert s.factor(0.4, 0.2, 1.0, 1.0) == pytest.approx(1 / math.sqrt(2))
    # Target 5 s (a deadline far above what the tasks take): it fits at r, r stays.
    assert s.factor(0.4, 0.2, 5.0, 1.0) == 1.0
    # The relative factor still makes lighter tasks finer (the controller's ceiling caps).
    assert s.factor(0.1, 0.2, 5.0, 1.0) > 1.0


def test_history_restores_and_ignores_bad_entries():
    s = WorkloadScaler(
        WorkloadConfig(window=3, min_history=2),
        history=[(0.2, 0.1, 1.0, 0.5), (math.nan, 0.1, 1.0, 0.5), (0.4, 0.3, 1.2, 0.9), (1.0,)],
    )
    assert s.history == ((0.2, 0.1, 1.0, 0.5), (0.4, 0.3, 1.2, 0.9))
    s.record(None)
    s.record(math.inf)
    s.record(-1.0)
    s.record(0.3, math.nan, 1.0, math.nan)  # unknown times count as none spent
    assert s.history[-1] == (0.3, 0.0, 1.0, 0.0) and len(s.history) == 3
    again = WorkloadScaler(s.config, s.history)
    assert again.factor(0.3, 0.2, 1.0, 1.0) == pytest.approx(s.factor(0.3, 0.2, 1.0, 1.0))
    # exponent 0: the scaler never changes r.
    off = WorkloadScaler(WorkloadConfig(exponent=0.0), [(0.1, 0.1, 1.0, 0.5)] * 8)
    assert off.factor(1.0, 0.5, 1.0, 1.0) == 1.0 and off.predicted_mvs(0.1, 1.0) is None


@pytest.mark.parametrize(
    "kw", [{"window": 0}, {"min_history": 9}, {"exponent": -1.0}, {"max_factor": 0.9}]
)
def test_config_checks(kw):
    with pytest.raises(ValueError):
        WorkloadConfig(**kw)


def test_mask_area_over_the_task_cameras():
    a = np.zeros((10, 10), bool)
    a[:5] = True  # 0.5
    b = np.zeros((4, 5), bool)
    b[0, :2] = True  # 0.1
    masks = [a, None, b, np.ones((2, 2), bool)]
    assert mask_area(masks, [0, 2]) == pytest.approx(0.3)
    assert mask_area(masks, [0, 1, 2]) == pytest.approx(0.3)  # no mask: left out
    assert mask_area(masks, [1]) is None
    assert mask_area(masks, [3]) == 1.0
