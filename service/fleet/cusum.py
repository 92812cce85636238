"""A sequential change-detection rule for the fault channels: the two-sided CUSUM (Page, 1954).

The threshold rule (:class:`service.fleet.alarms.LevelDetector`) raises a
level when |f_hat| stays above a threshold T for a persistence time. The CUSUM
rule accumulates the evidence instead (Basseville and Nikiforov, *Detection of
Abrupt Changes*, 1993, section 2.2): on the means m_j of the fault estimate
over blocks of ``cusum_block_s`` (the estimate is a filtered signal; its block
means are close to independent), normalised by their healthy standard
deviation sigma_b,

    g+_j = max(0, g+_{j-1} + m_j / sigma_b - k),   g-_j = max(0, g-_{j-1} - m_j / sigma_b - k),

and a level is raised when max(g+, g-) > h. Each level L (WARN, FAULT) has its
own pair: tuned for a shift of the threshold rule's T_L, k = T_L / (2 sigma_b)
(the drift of Page's rule for a change of T_L), and h set so that the
in-control average run length on Gaussian block means gives the profile's
false-alarm rate, two sides together. After a crossing the level's statistic
restarts from zero (so its crossings are the renewals the run length counts),
and the level drops one step once its statistic has not crossed for
``clear_after_s``: a fault renews the evidence every run length under it (a
fraction of a second for a fault of the tuned size or more), noise does not.

The run length is computed with the Markov-chain method of Brook and Evans
(1972) and h by root finding (:mod:`synth.cusum`, shared with the
effectiveness stage's bias-jump test): exact up to the discretisation, for
any k.
"""

from __future__ import annotations

import math

import numpy as np

from synth.cusum import cusum_threshold

_NOT_HOLDING = np.iinfo(np.int64).min
_NONE = np.zeros(0, dtype=np.intp)
_NONE.flags.writeable = False
OK, WARN, FAULT = 0, 1, 2


def blocks_per_false_alarm(false_alarms_per_1000_h: float, block_s: float) -> float:
    """The in-control run length [blocks] of a false-alarm rate per 1,000 hours of estimates."""
    return 1000.0 / false_alarms_per_1000_h * 3600.0 / block_s


class CusumDetector:
    """Two-level two-sided CUSUM on block means of one fault channel, one row per vehicle slot.

    thresholds : (WARN, FAULT) of the threshold rule [N m or rad], the shifts each level is tuned for;
    sigma : the healthy block means' standard deviation [N m or rad]; block_n : samples per block; block_s : a
    block's duration [s]; false_alarms_per_1000_h : the in-control rate each level is designed for;
    clear_after_ns : how long a level's statistic must go without crossing before the level drops one step. Same
    interface as :class:`service.fleet.alarms.LevelDetector` (``level``, ``grow``, ``reset``, ``update``).
    """

    def __init__(
        self,
        capacity: int,
        thresholds: tuple[float, float],
        sigma: float,
        block_n: int,
        false_alarms_per_1000_h: float,
        block_s: float,
        clear_after_ns: int,
    ) -> None:
        if not (sigma > 0 and math.isfinite(sigma)):
            raise ValueError(f"the CUSUM needs a positive healthy sigma, got {sigma}")
        self.sigma, self.block_n, self.clear_after_ns = sigma, max(1, int(block_n)), clear_after_ns
        self.thresholds = thresholds
        arl = blocks_per_false_alarm(false_alarms_per_1000_h, block_s)
        #: drift k and threshold h per level, in units of sigma
        self.drift = np.array([t / (2.0 * sigma) for t in thresholds])
        self.h = np.array([cusum_threshold(round(float(k), 9), arl) for k in self.drift])
        self.level = np.zeros(capacity, dtype=np.int8)
        self._sum = np.zeros(capacity)
        self._count = np.zeros(capacity, dtype=np.int64)
        self._g = np.zeros((2, 2, capacity))  # level (WARN, FAULT) x side (+, -)
        self._crossed_t_ns = np.full((2, capacity), _NOT_HOLDING, dtype=np.int64)

    def grow(self, capacity: int) -> None:
        extra = capacity - self.level.shape[0]
        if extra <= 0:
            return
        self.level = np.concatenate([self.level, np.zeros(extra, dtype=np.int8)])
        self._sum = np.concatenate([self._sum, np.zeros(extra)])
        self._count = np.concatenate([self._count, np.zeros(extra, dtype=np.int64)])
        self._g = np.concatenate([self._g, np.zeros((2, 2, extra))], axis=2)
        pad = np.full((2, extra), _NOT_HOLDING, dtype=np.int64)
        self._crossed_t_ns = np.concatenate([self._crossed_t_ns, pad], axis=1)

    def reset(self, rows: np.ndarray, keep_level: bool = False) -> None:
        """Forget the statistics of ``rows`` (after an observer restart); optionally the level too."""
        self._sum[rows] = 0.0
        self._count[rows] = 0
        self._g[:, :, rows] = 0.0
        self._crossed_t_ns[:, rows] = _NOT_HOLDING
        if not keep_level:
            self.level[rows] = OK

    def statistic(self, rows: np.ndarray) -> np.ndarray:
        """max(g+, g-) per level of ``rows``, (2, k) [sigma]."""
        return np.asarray(self._g[:, :, rows].max(axis=1))

    def update(self, rows: np.ndarray, values: np.ndarray, t_ns: np.ndarray) -> np.ndarray:
        """Feed one sample per row; at each row's block end update its statistics and level. Returns the
        indices (into rows) whose level changed."""
        self._sum[rows] += values
        self._count[rows] += 1
        ended = self._count[rows] >= self.block_n
        if not ended.any():
            return _NONE
        idx = np.flatnonzero(ended)
        r = rows[idx]
        z = self._sum[r] / (self._count[r] * self.sigma)
        self._sum[r] = 0.0
        self._count[r] = 0
        t = t_ns[idx]
        g = self._g[:, :, r]
        k = self.drift[:, None]
        g[:, 0] = np.maximum(0.0, g[:, 0] + z[None, :] - k)
        g[:, 1] = np.maximum(0.0, g[:, 1] - z[None, :] - k)
        stat = g.max(axis=1)
        crossed = stat > self.h[:, None]
        g[crossed[:, None, :].repeat(2, axis=1)] = 0.0
        self._g[:, :, r] = g
        last = np.where(crossed, t[None, :], self._crossed_t_ns[:, r])
        self._crossed_t_ns[:, r] = last
        quiet = (last == _NOT_HOLDING) | (t[None, :] - last >= self.clear_after_ns)
        old = self.level[r]
        new = np.maximum(old, np.where(crossed[1], FAULT, np.where(crossed[0], WARN, OK))).astype(np.int8)
        new[(new == FAULT) & quiet[1] & ~crossed[1]] = WARN
        new[(new == WARN) & quiet[0] & ~crossed[0]] = OK
        self.level[r] = new
        return np.asarray(idx[new != old], dtype=np.intp)
