"""The runtime fuzzy observer (Algorithm 1), vectorised over a batch of vehicles.

For every vehicle of the batch, at sample k:

    x_hat_k = z_k - E y_k                                                (19)
    z_{k+1} = N(h_k) z_k + L(h_k) y_k + M T1 (g(xi_k) + B u_k) + M G_bar phi(x_hat_k)

with h_k = h(xi_k), xi_k = [1/v_x, r] from the measured y_k. Departures from
the letter of Algorithm 1, each keeping the certificate meaningful:

* the premise is clipped to the design box before h and g are evaluated, and
  ``in_domain`` flags the vehicles whose measured premise left it;
* the reported estimate is x_hat_k + K (y_k - C_bar x_hat_k), with the output
  gain K of the robust design (synth.robust): the faults filtered with the
  current measurement, as an EKF reports x_{k|k}. K = 0 for the paper's
  designs. It is an output map only: the observer state and its certified
  error dynamics are those of eq. (19);
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

#: The measured nonlinear consequent g(xi) of eq. (15) is linear in these monomials of (v_x, r).
G_FEATURES = ("v_x^2", "r/v_x", "v_x r")


def g_feature_matrix(gains: ObserverGains) -> FloatArray:
    """(3, 3) matrix K with g(v_x, r) = K @ [v_x^2, r / v_x, v_x r] (eq. 15, corrected)."""
    k = gains.params.symbols()
    s = k["s"]
    K = np.zeros((3, 3))
    K[0, 0] = -s * k["C_x"] / k["I_e"]  # g_1 = -s C_x v_x^2 / I_e
    K[1, 1] = s * 2.0 * (k["C_r"] * k["l_r"] - k["C_f"] * k["l_f"]) / k["M_v"]  # g_2, r/v_x part
    K[1, 2] = -s  # g_2, -s v_x r part
    K[2, 1] = -s * 2.0 * (k["C_f"] * k["l_f"] ** 2 + k["C_r"] * k["l_r"] ** 2) / k["I_z"]  # g_3
    return K


@dataclass(frozen=True)
class RuntimeGains:
    """Gains stacked for the batched step: z_{k+1}^T = W^T Phi with one feature column per vehicle.

    Phi = [h_1 [z; y]; ...; h_r [z; y]; v_x^2; r/v_x; v_x r; u; phi]   (r (n + 2) + 6, nv)
    W   = [[N_1^T; L_1^T]; ...; [N_r^T; L_r^T]; (M T1 K)^T; (M T1 B)^T; (M G_bar)^T]   (r (n + 2) + 6, n)

    so the whole of Algorithm 1, line 9, is two broadcast products and one GEMM.
    """

    gains: ObserverGains
    WT: FloatArray
    E: FloatArray
    E_is_zero: bool
    K_rows: np.ndarray
    K_T: FloatArray
    n: int
    n_rules: int
    premise_low: FloatArray
    premise_high: FloatArray
    vy_low: float
    vy_high: float

    @classmethod
    def from_gains(cls, gains: ObserverGains) -> RuntimeGains:
        aug = gains.model
        r, n, _ = gains.N.shape
        MT1 = gains.M @ aug.T1
        rule_rows = np.concatenate([gains.N, gains.L], axis=2).transpose(0, 2, 1).reshape(r * (n + 2), n)
        W = np.vstack(
            [
                rule_rows,
                (MT1 @ g_feature_matrix(gains)).T,
                (MT1 @ aug.nts.B).T,
                (gains.M @ aug.G_bar).T,
            ]
        )
        vy_low, vy_high = aug.nts.bounds.lateral_speed_bounds
        K = gains.output_gain
        K_rows = np.flatnonzero(np.any(K != 0.0, axis=1))
        return cls(
            gains=gains,
            WT=np.ascontiguousarray(W.T),
            E=gains.E,
            E_is_zero=not np.any(gains.E),
            K_rows=K_rows,
            K_T=np.ascontiguousarray(K[K_rows].T),
            n=n,
            n_rules=r,
            premise_low=aug.nts.premise_low,
            premise_high=aug.nts.premise_high,
            vy_low=vy_low,
            vy_high=vy_high,
        )


@dataclass(frozen=True)
class StepResult:
    """Output of one observer step for a batch.

    x_hat : (nv, n) reported estimate of x_bar_k: [v_x, v_y, r, T_f, delta_f, ...] (with the output gain)
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

    Internally the batch is laid out vehicles-last (structure of arrays), so
    every elementwise loop runs over the fleet; the returned z_{k+1} is the
    transpose of a contiguous (n, nv) array, which makes the next call's
    transposes free.
    """
    y = np.asarray(y, dtype=float)
    nv = y.shape[0]
    n, n2 = rt.n, rt.n + 2
    width = rt.n_rules * n2
    Phi = np.empty((width + 6, nv))
    yT = np.ascontiguousarray(y.T)  # contiguous rows: every loop below runs at unit stride
    Phi[width + 3 : width + 5] = np.asarray(u, dtype=float).T
    zT = z.T
    # line 8: x_hat_k = z_k - E y_k
    x_hat = z if rt.E_is_zero else z - y @ rt.E.T
    # premise xi = [1/v_x, r], clipped to the design box, flagged when the clip moved it
    lo, hi = rt.premise_low, rt.premise_high
    V_raw, r_raw = 1.0 / yT[0], yT[1]
    V_x = np.minimum(np.maximum(V_raw, lo[0]), hi[0])
    r = np.minimum(np.maximum(r_raw, lo[1]), hi[1])
    in_domain = (V_x == V_raw) & (r == r_raw)
    # memberships of eq. (16): products of the two sector weights
    a = (hi[0] - V_x) * (1.0 / (hi[0] - lo[0]))
    b = (hi[1] - r) * (1.0 / (hi[1] - lo[1]))
    h = np.empty((4, nv))
    np.multiply(a, b, out=h[0])
    np.subtract(a, h[0], out=h[1])
    np.subtract(b, h[0], out=h[2])
    np.subtract(1.0 - a, h[2], out=h[3])
    vy_hat = x_hat[:, VY_INDEX]
    vy_sat = np.minimum(np.maximum(vy_hat, rt.vy_low), rt.vy_high)
    vy_in_bounds = vy_sat == vy_hat
    # line 9 as W^T Phi: rule blend of [z, y], the monomials of g, u, and phi(sat(v_y_hat))
    blend = Phi[:width].reshape(rt.n_rules, n2, nv)
    np.multiply(h[:, None, :], zT[None, :, :], out=blend[:, :n])
    np.multiply(h[:, None, :], yT[None, :, :], out=blend[:, n:])
    v_x = 1.0 / V_x
    np.multiply(v_x, v_x, out=Phi[width])
    np.multiply(r, V_x, out=Phi[width + 1])
    np.multiply(v_x, r, out=Phi[width + 2])
    np.multiply(vy_sat, vy_sat, out=Phi[width + 5])
    z_next = (rt.WT @ Phi).T
    if rt.K_rows.size:
        # the reported estimate: x_hat_k + K (y_k - C_bar x_hat_k) on the rows K acts on
        innovation = y - x_hat[:, ::2][:, :2]
        x_hat = x_hat.copy()
        x_hat[:, rt.K_rows] += innovation @ rt.K_T
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
