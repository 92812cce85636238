"""Drift-free pacing on absolute deadlines, and the statistics a paced loop reports.

Tick k is due at t_0 + k * period on ``time.monotonic_ns``. The loop sleeps
until each deadline; a tick that starts late does its work at once (catching
up), so a slow tick delays the ticks after it but never moves the schedule:
after n ticks the elapsed time is n * period plus the last tick's lateness,
whatever happened in between. ``sleep(0.01)`` in a loop, by contrast, drifts by
the work time of every tick.

Zenoh-free; used by the publisher and the benchmarks.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

#: A tick that starts this much after its deadline counts as late [ns].
LATE_THRESHOLD_NS = 1_000_000


@dataclass(frozen=True)
class PacingStats:
    """What a paced loop achieved.

    ticks : ticks run; elapsed_s : from the first deadline to the start of the last tick [s];
    rate_hz : (ticks - 1) / elapsed_s; lateness_*_ms : how long after its deadline a tick started [ms];
    late : ticks that started more than 1 ms late; overruns : ticks that started after the *next*
    deadline (the loop had fallen a whole period behind); max_lag_ms : the largest lateness.
    """

    ticks: int
    elapsed_s: float
    rate_hz: float
    lateness_p50_ms: float
    lateness_p99_ms: float
    max_lag_ms: float
    late: int
    overruns: int


class DeadlinePacer:
    """Sleep until absolute deadlines t_0 + k * period; record each tick's lateness.

    ``clock`` returns nanoseconds (default ``time.monotonic_ns``); ``sleep`` takes
    seconds. Lateness is kept in a ring of ``history`` ticks for the percentiles;
    the late and overrun counts cover the whole run.
    """

    def __init__(
        self,
        period_s: float,
        *,
        clock: Callable[[], int] = time.monotonic_ns,
        sleep: Callable[[float], None] = time.sleep,
        history: int = 200_000,
    ) -> None:
        if not (math.isfinite(period_s) and period_s > 0):
            raise ValueError(f"period_s must be finite and > 0, got {period_s}")
        self.period_ns = round(period_s * 1e9)
        self._clock = clock
        self._sleep = sleep
        self.start_ns: int | None = None
        self.ticks = 0
        self.late = 0
        self.overruns = 0
        self.max_lag_ns = 0
        self.last_tick_ns = 0
        self._lateness = np.zeros(history, dtype=np.int64)

    def deadline_ns(self, k: int) -> int:
        """Deadline of tick k on the pacer's clock [ns]."""
        if self.start_ns is None:
            raise RuntimeError("the pacer has not started")
        return self.start_ns + k * self.period_ns

    def start(self) -> int:
        """Fix t_0 = now; tick 0 is due at once. Returns t_0 [ns]."""
        self.start_ns = self._clock()
        self.ticks = 0
        return self.start_ns

    def wait(self) -> int:
        """Sleep until the next tick's deadline and start it; return its lateness [ns] (>= 0)."""
        if self.start_ns is None:
            self.start()
        deadline = self.deadline_ns(self.ticks)
        now = self._clock()
        while now < deadline:
            self._sleep((deadline - now) / 1e9)
            now = self._clock()
        lateness = now - deadline
        if lateness > LATE_THRESHOLD_NS:
            self.late += 1
        if lateness >= self.period_ns:
            self.overruns += 1
        self.max_lag_ns = max(self.max_lag_ns, lateness)
        self._lateness[self.ticks % self._lateness.size] = lateness
        self.ticks += 1
        self.last_tick_ns = now
        return lateness

    def stats(self) -> PacingStats:
        """Statistics of the ticks so far."""
        if self.start_ns is None or self.ticks == 0:
            return PacingStats(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 0)
        recent = self._lateness[: min(self.ticks, self._lateness.size)] / 1e6
        elapsed_s = (self.last_tick_ns - self.start_ns) / 1e9
        return PacingStats(
            ticks=self.ticks,
            elapsed_s=elapsed_s,
            rate_hz=(self.ticks - 1) / elapsed_s if elapsed_s > 0 else 0.0,
            lateness_p50_ms=float(np.percentile(recent, 50)),
            lateness_p99_ms=float(np.percentile(recent, 99)),
            max_lag_ms=self.max_lag_ns / 1e6,
            late=self.late,
            overruns=self.overruns,
        )
