"""An augmented-state extended Kalman filter: the baseline the fuzzy observer is measured against.

State x_a = [v_x, v_y, r, f_k, ...] with the same fault model as the observer
(order 1: random-walk faults; order 2: integrated random walks; order 3: the
paper's triple integrator), dimension n = 3 + 2 q. Process model: the Euler
step of the nonlinear eqs. (1)-(2) (eq. 12) with the current fault f_k, the
fault chain of eq. (17), white process noise from the same
:class:`~synth.options.NoiseModel` the robust design uses (wind force through
D, fault drift on the last chain block) plus a small model-error floor.
Measurement y = [v_x, r] with the sensor sigmas.

Per sample, for every vehicle of the batch at once: the measurement update
with y_k (Joseph form, numerically symmetric and positive), the estimate
x_{k|k}, then the prediction with the analytic Jacobian. A weak baseline
proves nothing: the Jacobian is checked against finite differences in the
tests, and the filter converges on noise-free runs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from synth.augmented import AugmentedEstimate, AugmentedModel, difference_coordinates, fault_chain_matrix
from synth.fuzzy import NTSModel
from synth.model import FloatArray, continuous_dynamics, continuous_matrices, model_demand
from synth.options import NoiseModel
from synth.params import OperatingBounds, VehicleParams

#: Standard deviation of the per-sample model error on [v_x, v_y, r] (Euler vs reality, unmodelled forces).
MODEL_ERROR_SIGMA = np.array([1e-4, 1e-3, 1e-4])
#: Initial standard deviations of the unmeasured parts: v_y [m/s], T_f [N m], delta_f [rad].
INITIAL_SIGMA_VY = 1.0
INITIAL_SIGMA_FAULT = np.array([200.0, 0.1])


@dataclass(frozen=True)
class EKFResult(AugmentedEstimate):
    """The filtered estimate x_{k|k} of a batch: state (nv, 3), faults (nv, 2), in_domain (nv,)."""

    x_hat: FloatArray
    in_domain: np.ndarray

    @property
    def certified(self) -> np.ndarray:
        """(nv,) the premise lay in the box of the gains it was tuned beside (the EKF has no certificate; its
        alarms are held outside the same box as the observer's, for a like-for-like comparison)."""
        return self.in_domain


def jacobian(x: FloatArray, p: VehicleParams, steer_rad: FloatArray | None = None) -> FloatArray:
    """d(dx/dt)/d[v_x, v_y, r] of eqs. (1)-(2) at x.

    Without the cornering drag the inputs enter affinely (the steering angle additively in F_yf), so the
    Jacobian does not depend on them and the fault columns are F_v. With it, the applied steering angle enters
    through -F_yf sin(delta) / m_eff (see :func:`cornering_drag_partials`).

    Parameters
    ----------
    x : (nv, 3) ndarray
        State [v_x [m/s], v_y [m/s], r [rad/s]].
    p : VehicleParams
        The vehicle.
    steer_rad : (nv,) ndarray, optional
        The applied steering angle [rad]; needed with the cornering drag.

    Returns
    -------
    (nv, 3, 3) ndarray
        The Jacobian [1/s and the mixed units of eq. (1)-(2)].
    """
    k = p.symbols()
    v_x, v_y, r = x[:, 0], x[:, 1], x[:, 2]
    inv = 1.0 / v_x
    # tyre force derivatives, eq. (2)
    dFf_dvx = 2 * k["C_f"] * (v_y + k["l_f"] * r) * inv**2
    dFf_dvy = -2 * k["C_f"] * inv
    dFf_dr = -2 * k["C_f"] * k["l_f"] * inv
    dFr_dvx = -2 * k["C_r"] * (k["l_r"] * r - v_y) * inv**2
    dFr_dvy = -2 * k["C_r"] * inv
    dFr_dr = 2 * k["C_r"] * k["l_r"] * inv
    J = np.empty((x.shape[0], 3, 3))
    J[:, 0, 0] = -2 * k["C_x"] * v_x / k["m_eff"]
    J[:, 0, 1] = r
    J[:, 0, 2] = v_y
    if p.cornering_drag and steer_rad is not None:
        d_state, _ = cornering_drag_partials(x, steer_rad, p)
        J[:, 0, :] -= d_state / k["m_eff"]
    J[:, 1, 0] = (dFf_dvx + dFr_dvx) / k["M_v"] - r
    J[:, 1, 1] = (dFf_dvy + dFr_dvy - 2 * k["C_y"] * v_y) / k["M_v"]
    J[:, 1, 2] = (dFf_dr + dFr_dr) / k["M_v"] - v_x
    J[:, 2, 0] = (k["l_f"] * dFf_dvx - k["l_r"] * dFr_dvx) / k["I_z"]
    J[:, 2, 1] = (k["l_f"] * dFf_dvy - k["l_r"] * dFr_dvy) / k["I_z"]
    J[:, 2, 2] = (k["l_f"] * dFf_dr - k["l_r"] * dFr_dr) / k["I_z"]
    return J


def cornering_drag_partials(x: FloatArray, steer_rad: FloatArray, p: VehicleParams) -> tuple[FloatArray, FloatArray]:
    """Partials of the cornering drag phi_c = F_yf sin(delta) [N].

    F_yf = 2 C_f (delta - (v_y + l_f r) / v_x) of eq. (2).

    Parameters
    ----------
    x : (nv, 3) ndarray
        State [v_x [m/s], v_y [m/s], r [rad/s]].
    steer_rad : (nv,) ndarray
        The applied steering angle delta [rad].
    p : VehicleParams
        The vehicle.

    Returns
    -------
    d_state : (nv, 3) ndarray
        d phi_c / d[v_x, v_y, r] [N s/m, N s/m, N s].
    d_steer : (nv,) ndarray
        d phi_c / d delta [N/rad].
    """
    k = p.symbols()
    v_x, v_y, r = x[:, 0], x[:, 1], x[:, 2]
    sin_d, cos_d = np.sin(steer_rad), np.cos(steer_rad)
    two_C_f = 2.0 * k["C_f"]
    F_yf = two_C_f * (steer_rad - (v_y + k["l_f"] * r) / v_x)
    d_state = np.column_stack(
        [two_C_f * (v_y + k["l_f"] * r) / v_x**2 * sin_d, -two_C_f / v_x * sin_d, -two_C_f * k["l_f"] / v_x * sin_d]
    )
    return d_state, two_C_f * sin_d + F_yf * cos_d


class AugmentedEKF:
    """The EKF for a batch of vehicles sharing parameters and tuning."""

    def __init__(
        self,
        params: VehicleParams,
        bounds: OperatingBounds,
        noise: NoiseModel,
        fault_order: int,
        y0: ArrayLike,
        x_hat0: ArrayLike | None = None,
    ) -> None:
        self.params = params
        self.nts = NTSModel.build(params, bounds)
        aug = AugmentedModel.build(self.nts, fault_order)
        n = aug.n
        self.n = n
        self.fault_order = fault_order
        y0 = np.atleast_2d(np.asarray(y0, dtype=float))
        nv = y0.shape[0]
        s = params.sample_period_s
        self.F_v = continuous_matrices(params).F_v
        self.chain = fault_chain_matrix(fault_order)
        # process noise: model error, wind through D, drift on the last fault block
        Q = np.zeros((n, n))
        Q[:3, :3] = np.diag(MODEL_ERROR_SIGMA**2)
        Q[2, 2] += (s * noise.wind_sigma_n / params.yaw_inertia_kgm2) ** 2
        drift = np.array([noise.torque_fault_rate_nm_per_s * s, noise.steer_fault_rate_rad_per_s * s])
        Q[n - 2 :, n - 2 :] += np.diag(drift**2)
        self.Q = Q
        self.R = np.diag([noise.vx_sigma_mps**2, noise.r_sigma_radps**2])
        self.x = np.zeros((nv, n))
        if x_hat0 is None:
            self.x[:, 0], self.x[:, 2] = y0[:, 0], y0[:, 1]
        else:
            given = np.atleast_2d(np.asarray(x_hat0, dtype=float))
            self.x[:, : given.shape[1]] = given
        # initial covariance: diagonal in difference coordinates of the fault chain, mapped to shift coordinates
        parts: list[FloatArray] = [np.array([noise.vx_sigma_mps, INITIAL_SIGMA_VY, noise.r_sigma_radps])]
        parts += [INITIAL_SIGMA_FAULT] + [drift] * (fault_order - 1)
        sig = np.concatenate(parts)
        T_inv = np.linalg.inv(difference_coordinates(fault_order))
        P0 = T_inv @ np.diag(sig**2) @ T_inv.T
        self.P = np.broadcast_to(P0, (nv, n, n)).copy()
        self._eye = np.eye(n)
        # the constant blocks of the Jacobian of the augmented model; the vehicle block changes per step
        s = params.sample_period_s
        self._F = np.zeros((nv, n, n))
        self._F[:, :3, 3:5] = s * self.F_v
        self._F[:, 3:, 3:] = self.chain
        #: the steering actuator model's angle (nv,), with a lag only
        self._steer: FloatArray | None = None

    def step(self, y: ArrayLike, u: ArrayLike) -> EKFResult:
        """Update with y_k, report x_{k|k}, predict to k + 1 with u_k.

        Parameters
        ----------
        y, u : (nv, 2) array_like
            The measurement and the demand of sample k, as for :meth:`synth.observer.FuzzyObserver.step`.

        Returns
        -------
        EKFResult
            x_{k|k} and the in-domain flags.
        """
        y = np.atleast_2d(np.asarray(y, dtype=float))
        u = model_demand(y, np.atleast_2d(np.asarray(u, dtype=float)), self.params)  # the load transfer's angle added
        demand = u
        if self.params.steer_lag_factor != 0.0:
            # the actuator's lagged road-wheel angle is the model's steering input (synth.model.lagged_steer);
            # it starts at rest on the first demand
            if self._steer is None:
                self._steer = u[:, 1].copy()
            c = self.params.steer_lag_mean_factor
            u = np.column_stack([u[:, 0], self._steer + c * (u[:, 1] - self._steer)])
        x, P = self.x, self.P
        # measurement update; C selects [v_x, r] = x[[0, 2]], so C P C^T and P C^T are slices
        PCt = P[:, :, ::2][:, :, :2]  # (nv, n, 2): columns 0 and 2
        S = PCt[:, ::2][:, :2] + self.R  # (nv, 2, 2): C P C^T + R
        det = S[:, 0, 0] * S[:, 1, 1] - S[:, 0, 1] * S[:, 1, 0]
        S_inv = np.empty_like(S)
        S_inv[:, 0, 0] = S[:, 1, 1] / det
        S_inv[:, 1, 1] = S[:, 0, 0] / det
        S_inv[:, 0, 1] = -S[:, 0, 1] / det
        S_inv[:, 1, 0] = -S[:, 1, 0] / det
        K = PCt @ S_inv  # (nv, n, 2)
        innovation = y - x[:, ::2][:, :2]
        x = x + (K @ innovation[:, :, None])[:, :, 0]
        # Joseph form (I - K C) P (I - K C)^T + K R K^T, expanded exactly with C P = (P C^T)^T:
        # P - K (C P) - (P C^T) K^T + K (C P C^T + R) K^T
        # (batched matmul is only fast on contiguous operands, hence the explicit copies of transposes)
        Kt = np.ascontiguousarray(K.transpose(0, 2, 1))
        K_CP = K @ np.ascontiguousarray(PCt.transpose(0, 2, 1))
        P = P - K_CP - K_CP.transpose(0, 2, 1) + (K @ S) @ Kt
        lo, hi = self.nts.premise_low, self.nts.premise_high
        V_x = 1.0 / y[:, 0]
        in_domain = (V_x >= lo[0]) & (V_x <= hi[0]) & (y[:, 1] >= lo[1]) & (y[:, 1] <= hi[1])
        result = EKFResult(x_hat=x, in_domain=in_domain)
        # prediction with the Euler model of eq. (12) and the fault chain of eq. (17)
        p = self.params
        s = p.sample_period_s
        veh = x[:, :3].copy()
        veh[:, 0] = np.maximum(veh[:, 0], 0.5)
        x_next = np.empty_like(x)
        x_next[:, :3] = veh + s * continuous_dynamics(veh, u, 0.0, x[:, 3:5], p)
        x_next[:, 3:] = x[:, 3:] @ self.chain.T
        F = self._F
        steer = u[:, 1] + p.steer_fault_gain * x[:, 4] if p.cornering_drag else None
        F[:, :3, :3] = self._eye[:3, :3] + s * jacobian(veh, p, steer)
        if steer is not None:
            # the steering fault also acts through the cornering drag: d(dv_x/dt)/d delta_f
            _, d_delta = cornering_drag_partials(veh, steer, p)
            F[:, 0, 4] = -s * p.steer_fault_gain * d_delta / p.effective_mass_kg
        P = (F @ P) @ np.ascontiguousarray(F.transpose(0, 2, 1)) + self.Q
        self.x = x_next
        if self._steer is not None:
            a = p.steer_lag_factor
            self._steer = a * self._steer + (1.0 - a) * demand[:, 1]
        self.P = 0.5 * (P + P.transpose(0, 2, 1))
        return result
