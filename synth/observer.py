"""The runtime fuzzy observer (Algorithm 1), vectorised over a batch of vehicles.

For every vehicle of the batch, at sample k:

    x_hat_k = z_k - E y_k                                                (19)
    z_{k+1} = N(h_k) z_k + L(h_k) y_k + M T1 (g(xi_k) + B u_k) + M G_bar phi(x_hat_k)

with h_k = h(xi_k), xi_k = [1/v_x, r] from the measured y_k. Departures from
the letter of Algorithm 1, each keeping the certificate meaningful:

* the premise is clipped to the design box before h and g are evaluated, and
  ``in_domain`` flags the vehicles whose measured premise left it;
* phi is evaluated at v_y_hat saturated to [v_y,min, v_y,max]. For a true v_y
  inside the bounds, phi(v_y) - phi(sat(v_y_hat)) = rho_eff (v_y - v_y_hat)
  with rho_eff = (v_y + sat(v_y_hat)) * (v_y - sat(v_y_hat)) / (v_y - v_y_hat)
  in the convex hull S_rho (the saturation is 1-Lipschitz and moves towards
  v_y), so the DMVT bound of eq. (26) holds even when the estimate strays.

One implementation serves the replay tool, the simulators and the cloud
service: :func:`observer_step` is stateless, :class:`FuzzyObserver` keeps the
state of a fixed batch.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from synth.augmented import VY_INDEX
from synth.gains import ObserverGains
from synth.model import FloatArray


@dataclass(frozen=True)
class RuntimeGains:
    """Gains rearranged for the batched step.

    NL : (n + 2, r * n)  [N_i, L_i] stacked so that [z, y] @ NL gives every rule's update
    MT1 : (n, 3); MT1B : (n, 2); MG : (n,); E : (n, 2)
    """

    gains: ObserverGains
    NL: FloatArray
    MT1: FloatArray
    MT1B: FloatArray
    MG: FloatArray
    E: FloatArray
    n: int
    n_rules: int
    vy_low: float
    vy_high: float

    @classmethod
    def from_gains(cls, gains: ObserverGains) -> RuntimeGains:
        aug = gains.model
        r, n, _ = gains.N.shape
        stacked = np.concatenate([gains.N, gains.L], axis=2)  # (r, n, n + 2)
        NL = np.ascontiguousarray(stacked.transpose(2, 0, 1).reshape(n + 2, r * n))
        MT1 = gains.M @ aug.T1
        vy_low, vy_high = aug.nts.bounds.lateral_speed_bounds
        return cls(
            gains=gains,
            NL=NL,
            MT1=MT1,
            MT1B=MT1 @ aug.nts.B,
            MG=(gains.M @ aug.G_bar)[:, 0],
            E=gains.E,
            n=n,
            n_rules=r,
            vy_low=vy_low,
            vy_high=vy_high,
        )


@dataclass(frozen=True)
class StepResult:
    """Output of one observer step for a batch.

    x_hat : (nv, n) estimate of x_bar_k: [v_x, v_y, r, T_f, delta_f, ...]
    in_domain : (nv,) the measured premise lay in the design box
    vy_in_bounds : (nv,) the estimated v_y lay in [v_y,min, v_y,max]
    """

    x_hat: FloatArray
    in_domain: np.ndarray
    vy_in_bounds: np.ndarray

    @property
    def state(self) -> FloatArray:
        """(nv, 3) estimated [v_x, v_y, r]."""
        return self.x_hat[:, :3]

    @property
    def faults(self) -> FloatArray:
        """(nv, 2) estimated [T_f [N m], delta_f [rad]]."""
        return self.x_hat[:, 3:5]


def initial_observer_state(rt: RuntimeGains, y: ArrayLike, x_hat0: ArrayLike | None = None) -> FloatArray:
    """z_0 such that x_hat_0 = z_0 - E y_0 equals ``x_hat0``, shape (nv, n).

    y : (nv, 2) first measurement; x_hat0 : (nv, n), (nv, 3) or None. A 3-vector
    sets the vehicle state with zero faults; None means [v_x, 0, r] from y.
    """
    y = np.atleast_2d(np.asarray(y, dtype=float))
    nv = y.shape[0]
    x0 = np.zeros((nv, rt.n))
    if x_hat0 is None:
        x0[:, 0] = y[:, 0]
        x0[:, 2] = y[:, 1]
    else:
        given = np.atleast_2d(np.asarray(x_hat0, dtype=float))
        x0[:, : given.shape[1]] = given
    return x0 + y @ rt.E.T


def observer_step(rt: RuntimeGains, z: FloatArray, y: ArrayLike, u: ArrayLike) -> tuple[FloatArray, StepResult]:
    """One step of Algorithm 1 for a batch: returns (z_{k+1}, result at k).

    z : (nv, n) observer state; y : (nv, 2) measured [v_x [m/s], r [rad/s]];
    u : (nv, 2) demanded [T_d [N m], delta_d [rad]]. Inputs must be finite.
    """
    y = np.asarray(y, dtype=float)
    u = np.asarray(u, dtype=float)
    nts = rt.gains.model.nts
    # line 8: x_hat_k = z_k - E y_k
    x_hat = z - y @ rt.E.T
    xi = nts.premise(y[:, 0], y[:, 1])
    in_domain = nts.in_domain(xi)
    xi = nts.clip_premise(xi)
    h = nts.memberships(xi)  # (nv, r)
    v_x = 1.0 / xi[:, 0]
    r = xi[:, 1]
    vy_hat = x_hat[:, VY_INDEX]
    vy_in_bounds = (vy_hat >= rt.vy_low) & (vy_hat <= rt.vy_high)
    phi = np.clip(vy_hat, rt.vy_low, rt.vy_high) ** 2
    # line 9: z_{k+1} = N(h) z + L(h) y + M T1 (g + B u) + M G_bar phi(x_hat)
    per_rule = (np.concatenate([z, y], axis=1) @ rt.NL).reshape(-1, rt.n_rules, rt.n)
    z_next = np.einsum("vi,vij->vj", h, per_rule)
    z_next += nts.g(v_x, r) @ rt.MT1.T + u @ rt.MT1B.T + phi[:, None] * rt.MG
    return z_next, StepResult(x_hat=x_hat, in_domain=in_domain, vy_in_bounds=vy_in_bounds)


class FuzzyObserver:
    """A fixed batch of observers sharing one gain set, with its state."""

    def __init__(self, gains: ObserverGains, y0: ArrayLike, x_hat0: ArrayLike | None = None) -> None:
        self.runtime = RuntimeGains.from_gains(gains)
        self.z = initial_observer_state(self.runtime, y0, x_hat0)

    @property
    def n_vehicles(self) -> int:
        return int(self.z.shape[0])

    def step(self, y: ArrayLike, u: ArrayLike) -> StepResult:
        """Consume y_k, u_k; return the estimate at k and advance to k + 1."""
        self.z, result = observer_step(self.runtime, self.z, np.atleast_2d(y), np.atleast_2d(u))
        return result
