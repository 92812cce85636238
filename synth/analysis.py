"""Frozen-premise analysis of a robust design against the Kalman filter of the same model.

At a fixed operating point (v_x, r, and v_y = 0 so that the rho term of the
nonlinear consequent vanishes) the observer's error dynamics are linear and
time-invariant: e_{k+1} = N(h) e_k + B(h) d_k, and the reported faults are
f_hat + K_f (y - C x_hat). Their steady-state covariance is a discrete
Lyapunov equation. The Kalman filter of the same linear model and the same
noise model (synth.robust.noise_inputs) is the best any linear filter can do
there, so the comparison separates what the design's structure costs (one
gain polytope for the whole domain, a certified decay rate) from what the
nonlinear plant and the scenarios add.

Each estimator's fault-error covariance is split by input: sensor noise only
(what remains once a fault is constant) and the rest (wind and fault drift:
how closely faults are tracked).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from synth.augmented import N_FAULTS, N_STATES
from synth.gains import ObserverGains
from synth.robust import noise_inputs


@dataclass(frozen=True)
class FrozenResponse:
    """Steady-state RMS of one estimator's reported fault errors at a frozen premise.

    ``*_noise``: from sensor noise alone; ``*_total``: from every input of the
    noise model. ``cost``: the weighted total, comparable with the design's
    guaranteed H2 cost. ``slowest_pole``: largest |eigenvalue| of the error dynamics.
    """

    torque_noise_nm: float
    steer_noise_rad: float
    torque_total_nm: float
    steer_total_rad: float
    cost: float
    slowest_pole: float


def _response(
    N: np.ndarray,
    K: np.ndarray,
    C: np.ndarray,
    B_fixed: np.ndarray,
    B_noise: np.ndarray,
    Sigma_v: np.ndarray,
    C_z: np.ndarray,
) -> FrozenResponse:
    """Reported error (I - K C) e_k - K v_k with e_{k+1} = N e_k + [B_fixed, B_noise] d_k (e_k independent of v_k)."""
    n = N.shape[0]
    M = np.eye(n) - K @ C
    KV = K @ Sigma_v @ Sigma_v @ K.T
    W_noise = scipy.linalg.solve_discrete_lyapunov(N, B_noise @ B_noise.T)
    W_all = W_noise + scipy.linalg.solve_discrete_lyapunov(N, B_fixed @ B_fixed.T)
    F_noise = M @ W_noise @ M.T + KV
    F_all = M @ W_all @ M.T + KV
    f = slice(N_STATES, N_STATES + N_FAULTS)
    return FrozenResponse(
        torque_noise_nm=float(np.sqrt(F_noise[f, f][0, 0])),
        steer_noise_rad=float(np.sqrt(F_noise[f, f][1, 1])),
        torque_total_nm=float(np.sqrt(F_all[f, f][0, 0])),
        steer_total_rad=float(np.sqrt(F_all[f, f][1, 1])),
        cost=float(np.trace(C_z @ F_all @ C_z.T)),
        slowest_pole=float(np.max(np.abs(np.linalg.eigvals(N)))),
    )


def frozen_comparison(gains: ObserverGains, v_x: float, r: float = 0.0) -> tuple[FrozenResponse, FrozenResponse]:
    """The observer and the Kalman filter at a frozen premise, under the design's noise model.

    At a frozen premise the error dynamics are linear and time-invariant, so each estimator's steady state has a
    closed form; the Kalman filter of the same linear model is the best any linear filter does there.

    Parameters
    ----------
    gains : ObserverGains
        The observer (its noise model is used for both).
    v_x : float
        Longitudinal speed of the premise [m/s].
    r : float, default 0.0
        Yaw rate of the premise [rad/s].

    Returns
    -------
    observer, kalman : FrozenResponse
        Steady-state RMS fault errors, weighted cost and slowest pole of each.
    """
    aug = gains.model
    inputs = noise_inputs(aug, gains.options.noise)
    C = aug.C_bar
    h = aug.nts.memberships(aug.nts.premise(v_x, r))
    N = np.einsum("i,ijk->jk", h, gains.N)
    L = np.einsum("i,ijk->jk", h, gains.L)
    observer = _response(N, gains.output_gain, C, inputs.B_fixed, -L @ inputs.Sigma_v, inputs.Sigma_v, inputs.C_z)
    # the steady-state Kalman filter of the same model: predictor gain A K_k, filter gain K_k
    A = aug.A_bar_at(h)
    R_v = inputs.Sigma_v @ inputs.Sigma_v
    P = scipy.linalg.solve_discrete_are(A.T, C.T, inputs.B_fixed @ inputs.B_fixed.T, R_v)
    K_k = P @ C.T @ np.linalg.inv(C @ P @ C.T + R_v)
    L_k = A @ K_k
    kalman = _response(A - L_k @ C, K_k, C, inputs.B_fixed, -L_k @ inputs.Sigma_v, inputs.Sigma_v, inputs.C_z)
    return observer, kalman


__all__ = ["FrozenResponse", "frozen_comparison"]
