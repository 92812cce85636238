"""The thresholds calibration sets: a Gaussian tail for the false-alarm rate, the held peak, the floor."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.stats

from service.calibration import FAULT_OVER_WARN, PEAK_MARGIN, REQUIRED_SHARE_FLOOR, fault_thresholds

KW = {"sample_period_s": 0.01, "persistence_s": 0.5}


def test_warn_is_the_gaussian_tail_for_the_stated_false_alarm_rate():
    estimate = np.random.default_rng(0).normal(0.0, 5.0, 120_000)  # 20 minutes of a healthy estimate
    t = fault_thresholds(estimate, 30.0, false_alarms_per_1000_h=1.0, required_bias=60.0, **KW)
    # one chance per 0.5 s window: 7,200 an hour; 1 per 1,000 h -> P(|e| >= WARN) = 1e-3 / 7200
    z = scipy.stats.norm.isf(1e-3 / 7200 / 2)
    assert t.sigma == pytest.approx(5.0, rel=0.01)
    assert t.warn == pytest.approx(z * t.sigma, rel=2e-3) and t.warn >= z * t.sigma
    assert t.fault == pytest.approx(FAULT_OVER_WARN * t.warn, rel=2e-3)
    assert t.smallest_fault_bias == pytest.approx(t.fault + 2 * t.sigma, rel=2e-3)
    assert not t.hides_required_fault
    # ten times more false alarms allowed: a lower threshold
    looser = fault_thresholds(estimate, 30.0, false_alarms_per_1000_h=10.0, required_bias=60.0, **KW)
    assert looser.warn < t.warn


def test_a_held_excursion_and_the_required_fault_floor_raise_warn():
    estimate = np.random.default_rng(1).normal(0.0, 1.0, 60_000)
    estimate[1000:1060] = 12.0  # 0.6 s held at 12: longer than the persistence time
    t = fault_thresholds(estimate, float("nan"), false_alarms_per_1000_h=1.0, required_bias=10.0, **KW)
    assert t.healthy_peak >= 11.5 and t.warn >= PEAK_MARGIN * t.healthy_peak
    quiet = np.random.default_rng(2).normal(0.0, 0.0005, 60_000)
    floor = fault_thresholds(quiet, float("nan"), false_alarms_per_1000_h=1.0, required_bias=0.02, **KW)
    assert floor.warn == pytest.approx(REQUIRED_SHARE_FLOOR * 0.02) and not floor.hides_required_fault


def test_a_threshold_that_hides_the_required_fault_is_said():
    estimate = np.random.default_rng(3).normal(0.0, 30.0, 60_000)
    t = fault_thresholds(estimate, 10.0, false_alarms_per_1000_h=1.0, required_bias=88.0, **KW)
    assert t.smallest_fault_bias > 88.0 and t.hides_required_fault
