"""Bounded statistics for long runs: a log-binned latency histogram."""

from __future__ import annotations

import math

import numpy as np

#: Histogram range and resolution: 1 us to 100 s, 40 bins per decade (quantiles within ~3 %).
_LOW_EXP = 3.0
_HIGH_EXP = 11.0
_BINS_PER_DECADE = 40


class LatencyHistogram:
    """Counts of durations [ns] in log-spaced bins: constant memory, quantiles to about 3 %.

    One thread may :meth:`add` while another reads; a reader sees a consistent-enough
    snapshot for progress lines (counts only grow).
    """

    def __init__(self) -> None:
        self.counts = np.zeros(int((_HIGH_EXP - _LOW_EXP) * _BINS_PER_DECADE) + 1, dtype=np.int64)
        self.total = 0
        self.max_ns = 0

    def add(self, duration_ns: int) -> None:
        value = max(duration_ns, 1)
        index = int((math.log10(value) - _LOW_EXP) * _BINS_PER_DECADE)
        self.counts[min(max(index, 0), self.counts.size - 1)] += 1
        self.total += 1
        self.max_ns = max(self.max_ns, duration_ns)

    def quantile_ms(self, q: float) -> float:
        """The q-quantile [ms] (bin centre, geometric), NaN when empty."""
        if not 0.0 <= q <= 1.0:
            raise ValueError(f"q must be in [0, 1], got {q}")
        counts = self.counts.copy()
        total = int(counts.sum())
        if total == 0:
            return math.nan
        index = int(np.searchsorted(np.cumsum(counts), max(q * total, 1), side="left"))
        centre_exp = _LOW_EXP + (index + 0.5) / _BINS_PER_DECADE
        return float(10.0**centre_exp / 1e6)
