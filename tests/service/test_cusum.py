"""The CUSUM alarm rule: its run lengths, its false-alarm rate on white noise, its delay, its levels."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from service.fleet.alarms import FAULT, OK, WARN, FaultLevels, LevelDetector
from service.fleet.cusum import CusumDetector, blocks_per_false_alarm
from service.profiles import AlarmThresholds
from synth.cusum import cusum_threshold, one_sided_arl

PERIOD_NS = 10_000_000


def test_the_run_lengths_match_the_published_table():
    # Page's CUSUM, k = 0.5: in control and under a shift of one sigma (Montgomery, Table 9.3; Brook and Evans)
    assert one_sided_arl(0.5, 4.0) == pytest.approx(336, rel=0.01)
    assert one_sided_arl(0.5, 5.0) == pytest.approx(930, rel=0.01)
    assert one_sided_arl(0.5, 4.0, shift=1.0) == pytest.approx(8.38, rel=0.01)
    assert one_sided_arl(0.5, 5.0, shift=1.0) == pytest.approx(10.4, rel=0.01)
    # h is the inverse: two sides of run length 2 x 1,000 blocks each
    h = cusum_threshold(0.5, 1000.0)
    assert one_sided_arl(0.5, h) == pytest.approx(2000.0, rel=1e-3)
    # a drift so large that a single block mean beyond it is rarer than asked: h = 0
    assert cusum_threshold(6.0, 1000.0) == 0.0


def cusum_alarms(rate_per_1000_h: float, block_s: float = 0.01) -> AlarmThresholds:
    """WARN tuned for a shift of 1 sigma (k = 0.5), FAULT out of reach; sigma = 1; clear at once."""
    return AlarmThresholds(
        rule="cusum",
        torque_warn_nm=1.0,
        torque_fault_nm=1e6,
        steer_warn_rad=1.0,
        steer_fault_rad=1e6,
        torque_block_sigma_nm=1.0,
        steer_block_sigma_rad=1.0,
        cusum_block_s=block_s,
        cusum_false_alarms_per_1000_h=rate_per_1000_h,
        clear_after_s=0.0,
        warmup_s=0.0,
    )


def test_on_white_noise_the_false_alarm_rate_is_the_design_rate():
    # designed for one false alarm per 1,000 blocks (two sides together): 3.6e5 per 1,000 h of 10 ms blocks
    rate = 3.6e5
    assert blocks_per_false_alarm(rate, 0.01) == pytest.approx(1000.0)
    rows, steps = 400, 25_000
    levels = FaultLevels(rows, cusum_alarms(rate))
    assert isinstance(levels.torque, CusumDetector) and isinstance(levels.steer, CusumDetector)
    rng = np.random.default_rng(7)
    index = np.arange(rows)
    raised = np.zeros(2, dtype=np.int64)
    previous = np.zeros((2, rows), dtype=np.int8)
    for k in range(steps):
        levels.update(index, rng.standard_normal((rows, 2)), np.full(rows, k * PERIOD_NS, dtype=np.int64))
        now = np.stack([levels.torque.level, levels.steer.level])
        raised += ((previous == OK) & (now >= WARN)).sum(axis=1)
        previous = now.copy()
    expected = rows * steps / 1000.0  # 10,000 per channel
    # a raised level takes a block or two to clear, time in which a crossing is not a new raise: within 4 %
    assert raised / expected == pytest.approx([1.0, 1.0], rel=0.04)
    assert (raised < expected * 1.01).all()


def test_a_shift_of_the_tuned_size_is_caught_as_the_run_length_says_and_the_level_clears_after():
    alarms = cusum_alarms(3.6e3).model_copy(update={"torque_fault_nm": 3.0, "clear_after_s": 0.2})
    rows = 2000
    levels = FaultLevels(rows, alarms)
    rng = np.random.default_rng(3)
    index = np.arange(rows)
    t = 0
    # calm first: no vehicle at WARN after 2 s of noise (designed: one false alarm per 100,000 blocks)
    for _ in range(200):
        levels.update(index, rng.standard_normal((rows, 2)), np.full(rows, t, dtype=np.int64))
        t += PERIOD_NS
    calm = int((levels.torque.level > OK).sum())
    assert calm <= 20
    detector = levels.torque
    assert isinstance(detector, CusumDetector)
    # a shift of one sigma (the WARN threshold) on the torque channel: the delay is the one-sided run length
    # from zero under that shift, for vehicles whose statistic was at zero when the shift began
    at_zero = detector.statistic(index)[0] == 0.0
    delay = np.full(rows, -1)
    for k in range(200):
        values = rng.standard_normal((rows, 2))
        values[:, 0] += 1.0
        levels.update(index, values, np.full(rows, t, dtype=np.int64))
        t += PERIOD_NS
        delay[(delay < 0) & (levels.torque.level >= WARN)] = k + 1
    assert (delay > 0).all()
    expected = one_sided_arl(0.5, float(detector.h[0]), shift=1.0)
    assert float(np.mean(delay[at_zero])) == pytest.approx(expected, rel=0.08)
    # the steering channel saw noise only; FAULT (tuned for 3 sigma) stays rare under a 1 sigma shift
    assert int((levels.steer.level > OK).sum()) <= 20
    # the shift ends: every level clears within a second
    for _ in range(100):
        levels.update(index, rng.standard_normal((rows, 2)), np.full(rows, t, dtype=np.int64))
        t += PERIOD_NS
    assert int((levels.torque.level > OK).sum()) <= 20


def test_a_large_shift_raises_fault_and_a_rule_change_keeps_the_levels():
    alarms = cusum_alarms(1.0).model_copy(update={"torque_fault_nm": 2.0, "steer_fault_rad": 2.0, "clear_after_s": 1.0})
    levels = FaultLevels(3, alarms)
    index = np.arange(3)
    values = np.zeros((3, 2))
    values[0, 0] = 5.0  # vehicle 0: a torque fault of five sigma
    values[1, 1] = -5.0  # vehicle 1: a steering fault the other way
    for k in range(50):
        levels.update(index, values, np.full(3, k * PERIOD_NS, dtype=np.int64))
    assert levels.torque.level.tolist() == [FAULT, OK, OK]
    assert levels.steer.level.tolist() == [OK, FAULT, OK]
    # back to the threshold rule: the same levels, now held by LevelDetector
    levels.configure(AlarmThresholds(torque_warn_nm=1.0, torque_fault_nm=2.0, steer_warn_rad=1.0, steer_fault_rad=2.0))
    assert isinstance(levels.torque, LevelDetector)
    assert levels.torque.level.tolist() == [FAULT, OK, OK] and levels.steer.level.tolist() == [OK, FAULT, OK]
    # and to the CUSUM again
    levels.configure(alarms)
    assert isinstance(levels.steer, CusumDetector) and levels.steer.level.tolist() == [OK, FAULT, OK]
    # a restart forgets the statistics, not the levels
    levels.restart(index, np.zeros(3, dtype=np.int64))
    assert isinstance(levels.torque, CusumDetector)
    assert not levels.torque.statistic(index).any() and levels.torque.level.tolist() == [FAULT, OK, OK]


def test_the_cusum_rule_needs_the_healthy_sigmas():
    with pytest.raises(ValidationError, match="needs torque_block_sigma_nm and steer_block_sigma_rad"):
        AlarmThresholds(rule="cusum")
    with pytest.raises(ValidationError):
        AlarmThresholds(rule="cusum", torque_block_sigma_nm=1.0, steer_block_sigma_rad=0.001, cusum_block_s=0.0)
    with pytest.raises(ValidationError):
        AlarmThresholds(rule="glr")
