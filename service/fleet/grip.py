"""The tyre-grip gate: the combined acceleration a vehicle's measurements show, per row, against the profile's limit.

The observer's model has linear tyres (docs/math.md section 1). Braking or
accelerating hard in a turn uses the tyres' grip in both directions at once,
the forces saturate well before either alone would, and the model's error
then reads as a fault on both channels (docs/math.md 12.4: 1-10x WARN on the
multi-body vehicle). What a vehicle sends shows it: the longitudinal
acceleration dv_x/dt and the lateral one v_x r (the steady-state part of
v_y' + v_x r). :class:`GripGate` tracks both per row with a second-order
low-pass (two first-order stages of time constant :data:`FILTER_S`: the
measured v_x's noise, 0.05 m/s at 100 Hz, differenced sample to sample would be
7 m/s^2, 0.7 g), and flags the rows whose combined acceleration

    u = |(a_x, a_y)| / g

is above ``limit_g`` while they brake or accelerate (|a_x| / g above
``longitudinal_g``), or above ``cornering_g`` in any case. Measured on the
multi-body vehicle: steady cornering holds the model's lateral fit to 0.8 g,
braking or accelerating in a turn does not beyond about 0.55 g combined.
:class:`service.fleet.alarms.FaultLevels` holds a flagged row's levels
unjudged (as it holds a sample outside the certified domain) for the
profile's ``grip_hold_s`` after the last flagged sample.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Standard gravity [m/s^2]: the unit of the limit.
G_MPS2 = 9.80665
#: The time constant of each of the two low-pass stages [s]: together about 0.2 s of delay.
FILTER_S = 0.1
#: A row whose samples are further apart than this (a gap, a restart) starts its filter afresh [s].
MAX_GAP_S = 0.25
_MAX_GAP_NS = round(MAX_GAP_S * 1e9)
#: The last sample time of a row that has none (or was reset): any sample's is more than MAX_GAP_S after it.
_NEVER_NS = np.iinfo(np.int64).min // 4


@dataclass(frozen=True)
class GripLimits:
    """Where the gate flags a sample [g]: combined acceleration above ``limit_g`` with |a_x| above
    ``longitudinal_g``, or above ``cornering_g``."""

    limit_g: float
    longitudinal_g: float
    cornering_g: float


class GripGate:
    """Per-row combined acceleration from (v_x, r) samples, and which rows are beyond the ``limits``.

    ``limits`` None switches the gate off (:meth:`update` flags nothing and keeps no state). Rows are vehicle
    slots; a row appears at most once per call.
    """

    def __init__(self, capacity: int, limits: GripLimits | None) -> None:
        self.limits = limits
        #: per row (a column each): the filtered v_x [m/s] and v_x r [m/s^2] (stage one), a_x and a_y [m/s^2]
        #: (stage two); rows as columns, so that one take gathers all four
        self.state = np.zeros((4, capacity))
        #: per row: the last sample's time [ns]; _NEVER_NS: the next sample starts the filter afresh
        self.t_ns = np.full(capacity, _NEVER_NS, dtype=np.int64)

    def configure(self, limits: GripLimits | None) -> None:
        self.limits = limits

    def grow(self, capacity: int) -> None:
        extra = capacity - self.t_ns.shape[0]
        if extra > 0:
            self.state = np.concatenate([self.state, np.zeros((4, extra))], axis=1)
            self.t_ns = np.concatenate([self.t_ns, np.full(extra, _NEVER_NS, dtype=np.int64)])

    def reset(self, rows: np.ndarray) -> None:
        """The filters of ``rows`` start afresh from their next sample (a new vehicle, a restart)."""
        self.t_ns[rows] = _NEVER_NS

    def acceleration_g(self, rows: np.ndarray) -> np.ndarray:
        """The combined acceleration u = |(a_x, a_y)| / g of ``rows`` after their last sample [g]."""
        s = self.state.take(rows, axis=1)
        return np.hypot(s[2], s[3]) / G_MPS2

    def update(self, rows: np.ndarray, v_x: np.ndarray, r: np.ndarray, t_ns: np.ndarray) -> np.ndarray:
        """Feed one sample per row; return (k,) bool, the rows beyond the limits.

        rows : (k,) slots; v_x : (k,) [m/s]; r : (k,) [rad/s]; t_ns : (k,) sample times [ns]. A row's first
        sample, or one after a gap of more than :data:`MAX_GAP_S`, starts its filter at rest in a_x and at the
        sample's v_x r; a sample no later than the row's last leaves it unchanged.
        """
        limits = self.limits
        if limits is None or not rows.shape[0]:
            return np.zeros(rows.shape[0], dtype=bool)
        dt_ns = t_ns - self.t_ns.take(rows)
        s = self.state.take(rows, axis=1)
        a_y_in = v_x * r
        if dt_ns.min() <= 0 or dt_ns.max() > _MAX_GAP_NS:
            new = self._update_some(rows, s, v_x, a_y_in, t_ns, dt_ns)
        else:  # the common tick: every row one period on
            new = self._step(s, v_x, a_y_in, dt_ns * 1e-9)
            self.state[:, rows] = new
            self.t_ns[rows] = t_ns
        u2 = new[2] * new[2]
        u2 += new[3] * new[3]
        g2 = G_MPS2 * G_MPS2
        beyond = u2 > min(limits.limit_g, limits.cornering_g) ** 2 * g2
        if not beyond.any():  # the common tick: nobody near the limits
            return beyond
        return (beyond & (new[2] * new[2] > limits.longitudinal_g**2 * g2)) | (u2 > limits.cornering_g**2 * g2)

    @staticmethod
    def _step(s: np.ndarray, v_x: np.ndarray, a_y_in: np.ndarray, dt: np.ndarray) -> np.ndarray:
        """The filters' step: (4, k) state ``s``, inputs v_x and v_x r (k,), time steps dt (k,) [s] > 0; the new
        state (4, k). Backward-Euler first-order stages, x <- x + a (input - x), a = dt / (tau + dt); each stage
        on its two rows at once (a tick of few vehicles costs what its numpy calls cost)."""
        a = dt / (dt + FILTER_S)
        new = np.empty_like(s)
        first, second = new[:2], new[2:]
        first[0] = v_x
        first[1] = a_y_in
        first -= s[:2]
        first *= a
        first += s[:2]
        np.subtract(first[0], s[0], out=second[0])  # the first stage's dv_x, over dt: a_x into the second
        second[0] /= dt
        second[1] = first[1]
        second -= s[2:]
        second *= a
        second += s[2:]
        return new

    def _update_some(
        self, rows: np.ndarray, s: np.ndarray, v_x: np.ndarray, a_y_in: np.ndarray, t_ns: np.ndarray, dt_ns: np.ndarray
    ) -> np.ndarray:
        """:meth:`update` where some rows start afresh or do not move on: (4, k) the rows' new state."""
        restart = dt_ns > _MAX_GAP_NS
        forward = dt_ns > 0
        moving = forward & ~restart
        new = s.copy()  # a stale sample changes nothing
        new[:, moving] = self._step(s[:, moving], v_x[moving], a_y_in[moving], dt_ns[moving] * 1e-9)
        new[:, restart] = np.stack([v_x[restart], a_y_in[restart], np.zeros(int(restart.sum())), a_y_in[restart]])
        self.state[:, rows] = new
        self.t_ns[rows] = np.where(forward, t_ns, self.t_ns.take(rows))
        return new
