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
        #: per row: the filtered v_x [m/s] and v_x r [m/s^2] (stage one), a_x and a_y [m/s^2] (stage two)
        self.state = np.zeros((capacity, 4))
        #: per row: the last sample's time [ns]; 0 before the first (a fresh filter)
        self.t_ns = np.zeros(capacity, dtype=np.int64)
        self.fresh = np.ones(capacity, dtype=bool)

    def configure(self, limits: GripLimits | None) -> None:
        self.limits = limits

    def grow(self, capacity: int) -> None:
        extra = capacity - self.t_ns.shape[0]
        if extra > 0:
            self.state = np.concatenate([self.state, np.zeros((extra, 4))])
            self.t_ns = np.concatenate([self.t_ns, np.zeros(extra, dtype=np.int64)])
            self.fresh = np.concatenate([self.fresh, np.ones(extra, dtype=bool)])

    def reset(self, rows: np.ndarray) -> None:
        """The filters of ``rows`` start afresh from their next sample (a new vehicle, a restart)."""
        self.fresh[rows] = True

    def acceleration_g(self, rows: np.ndarray) -> np.ndarray:
        """The combined acceleration u = |(a_x, a_y)| / g of ``rows`` after their last sample [g]."""
        s = self.state[rows]
        return np.hypot(s[:, 2], s[:, 3]) / G_MPS2

    def update(self, rows: np.ndarray, v_x: np.ndarray, r: np.ndarray, t_ns: np.ndarray) -> np.ndarray:
        """Feed one sample per row; return (k,) bool, the rows beyond the limits.

        rows : (k,) slots; v_x : (k,) [m/s]; r : (k,) [rad/s]; t_ns : (k,) sample times [ns]. A row's first
        sample, or one after a gap of more than :data:`MAX_GAP_S`, starts its filter at rest in a_x and at the
        sample's v_x r; a sample no later than the row's last leaves it unchanged.
        """
        limits = self.limits
        if limits is None:
            return np.zeros(rows.shape[0], dtype=bool)
        dt_ns = t_ns - self.t_ns[rows]
        restart = self.fresh[rows] | (dt_ns > _MAX_GAP_NS)
        forward = dt_ns > 0
        s = self.state[rows]
        dt = np.where(forward, dt_ns, 1) * 1e-9
        # backward-Euler first-order stages: x <- x + a (input - x), a = dt / (tau + dt); 0 for a stale sample
        a = np.where(forward, dt / (FILTER_S + dt), 0.0)[:, None]
        first = s[:, :2] + a * (np.column_stack([v_x, v_x * r]) - s[:, :2])
        ax_in = (first[:, 0] - s[:, 0]) / dt
        second = s[:, 2:] + a * (np.column_stack([ax_in, first[:, 1]]) - s[:, 2:])
        new = np.concatenate([first, second], axis=1)
        if restart.any():
            a_y = v_x[restart] * r[restart]
            new[restart] = np.column_stack([v_x[restart], a_y, np.zeros_like(a_y), a_y])
        self.state[rows] = new
        self.t_ns[rows] = np.where(forward | restart, t_ns, self.t_ns[rows])
        self.fresh[rows] = False
        u = np.hypot(new[:, 2], new[:, 3])
        return ((u > limits.limit_g * G_MPS2) & (np.abs(new[:, 2]) > limits.longitudinal_g * G_MPS2)) | (
            u > limits.cornering_g * G_MPS2
        )
