"""The run length of Page's CUSUM on Gaussian samples, and the threshold that gives a chosen one.

Page's one-sided statistic g_j = max(0, g_{j-1} + z_j - k) on samples z_j ~ N(shift, 1) crosses h after a
run length whose mean (ARL) is computed with the Markov-chain method of Brook and Evans (1972): the
statistic's range [0, h) cut into :data:`ARL_STATES` states, exact up to the discretisation, for any drift k
(Basseville and Nikiforov, *Detection of Abrupt Changes*, 1993, section 5.2). A two-sided test runs two such
statistics, so its false-alarm rate is twice one side's. Used by the alarms' CUSUM rule
(service.fleet.cusum) and by the effectiveness stage's bias-jump test (synth.effectiveness).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import scipy.optimize
import scipy.special

#: States of the Brook-Evans chain on [0, h).
ARL_STATES = 100


def one_sided_arl(k: float, h: float, shift: float = 0.0, states: int = ARL_STATES) -> float:
    """Average run length [samples] of g_j = max(0, g_{j-1} + z_j - k) from 0 to g > h, z ~ N(shift, 1).

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
    """h of a two-sided CUSUM of drift ``k`` [sigma] whose in-control run length is ``arl_blocks`` [samples].

    Two one-sided statistics, each with run length 2 arl_blocks (the alarm rates add). 0 when even h = 0 is
    rarer than asked (a sample beyond k sigma is itself rarer than one in 2 arl_blocks).
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


class PageTest:
    """Two-sided Page CUSUM on standard normal samples, one pair of statistics per (row, channel) of a batch.

    g+ = max(0, g+ + z - k), g- = max(0, g- - z - k), a detection when max(g+, g-) > h, with h from
    :func:`cusum_threshold` so that on white N(0, 1) samples the mean time between detections is ``arl_samples``;
    the pair restarts from zero after a detection (its detections are the renewals the run length counts).

    rows, channels : the batch's shape; drift : k [standard deviations]; arl_samples : the design's mean run
    length on white noise [samples].
    """

    def __init__(self, rows: int, channels: int, drift: float, arl_samples: float) -> None:
        self.drift = drift
        self.h = cusum_threshold(drift, arl_samples)
        #: (rows, channels, 2): g+ and g-
        self.g = np.zeros((rows, channels, 2))

    def grow(self, rows: int) -> None:
        """Room for ``rows`` rows; the new ones at rest."""
        extra = rows - self.g.shape[0]
        if extra > 0:
            self.g = np.concatenate([self.g, np.zeros((extra, *self.g.shape[1:]))])

    def reset(self, rows: np.ndarray) -> None:
        self.g[rows] = 0.0

    def update(self, rows: np.ndarray, z: np.ndarray, active: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One sample z (k, channels) per row of ``rows`` (distinct); where not ``active`` (k, channels) the
        statistics rest at zero. Returns where the evidence began this sample (both statistics were zero and one is
        not now) and where a change was detected, (k, channels) bool each."""
        g = self.g[rows]
        resting = np.maximum(g[:, :, 0], g[:, :, 1]) == 0.0
        # g+ = max(0, g+ + z - k), g- = max(0, g- - z - k)
        g[:, :, 0] = np.where(active, np.maximum(0.0, g[:, :, 0] + z - self.drift), 0.0)
        g[:, :, 1] = np.where(active, np.maximum(0.0, g[:, :, 1] - z - self.drift), 0.0)
        peak = np.maximum(g[:, :, 0], g[:, :, 1])
        detected = peak > self.h
        g[detected] = 0.0
        self.g[rows] = g
        return resting & (peak > 0.0), detected
