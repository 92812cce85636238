import math

import numpy as np
import pytest

from edge_client.pacing import DeadlinePacer
from edge_client.stats import LatencyHistogram

PERIOD_NS = 10_000_000


class FakeClock:
    """A monotonic clock in ns that moves only when slept on or when work is simulated."""

    def __init__(self) -> None:
        self.now = 1_000_000_000
        self.sleep_overshoot_ns = 50_000

    def __call__(self) -> int:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += round(seconds * 1e9) + self.sleep_overshoot_ns

    def work(self, ns: int) -> None:
        self.now += ns


def test_deadlines_do_not_drift_whatever_the_work():
    """With 0-9 ms of work per tick and 50 us sleep overshoot, tick k still starts within 50 us of t0 + k s."""
    clock = FakeClock()
    pacer = DeadlinePacer(0.01, clock=clock, sleep=clock.sleep)
    start = pacer.start()
    rng = np.random.default_rng(0)
    for k in range(1000):
        lateness = pacer.wait()
        assert clock.now - (start + k * PERIOD_NS) == lateness <= 50_000
        clock.work(int(rng.integers(0, 9_000_000)))
    stats = pacer.stats()
    assert stats.ticks == 1000 and stats.late == 0 and stats.overruns == 0
    assert stats.rate_hz == pytest.approx(100.0, rel=1e-4)


def test_a_slow_tick_is_counted_and_caught_up_without_moving_the_schedule():
    clock = FakeClock()
    pacer = DeadlinePacer(0.01, clock=clock, sleep=clock.sleep)
    start = pacer.start()
    for k in range(100):
        pacer.wait()
        clock.work(35_000_000 if k == 10 else 1_000_000)  # tick 10 takes 35 ms
    stats = pacer.stats()
    # ticks 11, 12, 13 start late (25, 15, 5 ms); 11 and 12 after their next deadline too
    assert stats.late == 3 and stats.overruns == 2
    assert stats.max_lag_ms == pytest.approx(25.0, abs=0.1)
    assert pacer.last_tick_ns - (start + 99 * PERIOD_NS) <= 50_000


def test_sleep_drift_is_what_absolute_deadlines_avoid():
    """The naive loop (sleep(period) after the work) runs slow by the work time; the pacer does not."""
    clock = FakeClock()
    start = clock()
    for _ in range(100):
        clock.work(2_000_000)
        clock.sleep(0.01)
    naive_rate = 100 / ((clock() - start) / 1e9)
    assert naive_rate < 0.85 * 100


def test_pacer_rejects_bad_periods():
    for period in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="period_s"):
            DeadlinePacer(period)


def test_latency_histogram_quantiles_within_its_resolution():
    rng = np.random.default_rng(0)
    samples = rng.lognormal(mean=np.log(400_000), sigma=0.8, size=20_000).astype(np.int64)  # ~0.4 ms
    hist = LatencyHistogram()
    for value in samples:
        hist.add(int(value))
    for q in (0.5, 0.9, 0.99):
        assert hist.quantile_ms(q) == pytest.approx(np.quantile(samples, q) / 1e6, rel=0.06)
    assert hist.total == samples.size and hist.max_ns == samples.max()
    assert math.isnan(LatencyHistogram().quantile_ms(0.5))
