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
(1972), the statistic's range [0, h) cut into :data:`ARL_STATES` states, and
h by root finding (scipy): exact up to the discretisation, for any k.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import scipy.optimize
import scipy.special

#: States of the Brook-Evans chain on [0, h).
ARL_STATES = 100
_NOT_HOLDING = np.iinfo(np.int64).min
_NONE = np.zeros(0, dtype=np.intp)
_NONE.flags.writeable = False
OK, WARN, FAULT = 0, 1, 2


def one_sided_arl(k: float, h: float, shift: float = 0.0, states: int = ARL_STATES) -> float:
    """Average run length [blocks] of g_j = max(0, g_{j-1} + z_j - k) from 0 to g > h, z ~ N(shift, 1).

    Brook and Evans: the range [0, h) in ``states`` cells of width w, the chain's transition from cell i
    (midpoint c_i, and 0 for the first) to cell j is P(c_i + z - k in cell j), to 0 is P(c_i + z - k <= w/2);
    ARL = (I - R)^-1 1, from the first cell.
    """
    if h <= 0.0:
        return 1.0 / max(float(scipy.special.ndtr(shift - k)), 1e-300)
    w = h / states
    centres = (np.arange(states) + 0.5) * w
    centres[0] = 0.0
    upper = (np.arange(states) + 1.0) * w
    lower = upper - w
    # P(lower_j <= c_i + z - k < upper_j), z ~ N(shift, 1); the first cell takes everything at or below w
    hi = scipy.special.ndtr(upper[None, :] - centres[:, None] + k - shift)
    lo = scipy.special.ndtr(lower[None, :] - centres[:, None] + k - shift)
    lo[:, 0] = 0.0
    transitions = hi - lo
    arl = np.linalg.solve(np.eye(states) - transitions, np.ones(states))
    return float(arl[0])


@lru_cache(maxsize=256)
def cusum_threshold(k: float, arl_blocks: float) -> float:
    """h of a two-sided CUSUM of drift ``k`` [sigma] whose in-control run length is ``arl_blocks``.

    Two one-sided statistics, each with run length 2 arl_blocks (the alarm rates add). 0 when even h = 0 is
    rarer than asked (a block mean beyond k sigma is itself rarer than one in 2 arl_blocks).
    """
    target = 2.0 * arl_blocks
    if one_sided_arl(k, 0.0) >= target:
        return 0.0

    def gap(h: float) -> float:
        return math.log(one_sided_arl(k, h)) - math.log(target)

    high = 1.0
    while gap(high) < 0.0:
        high *= 2.0
        if high > 1e4:
            raise ValueError(f"no CUSUM threshold gives a run length of {arl_blocks:g} blocks at drift {k:g}")
    return float(scipy.optimize.brentq(gap, 0.0, high, xtol=1e-5))


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
