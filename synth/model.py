"""The 2-DOF nonlinear vehicle model (eqs. 1-6) and its Euler discretisation (eq. 12).

State x = [v_x, v_y, r] ([m/s], [m/s], [rad/s]); demanded input
u_d = [T_d, delta_d] ([N m], [rad]); disturbance w = F_w (lateral wind force
[N]); actuator faults f = [T_f, delta_f] ([N m], [rad]); output y = [v_x, r].

T_d is the total drive torque at the driven wheels (braking negative), a force
T_d / R_w at the road; delta_d the front road-wheel angle (+ = left). The
longitudinal equation of eq. (1), read physically, with the two terms a real
vehicle adds (both off in the paper's profile):

    dv_x/dt = (T / R_w - C_x v_x^2 - F_r - F_yf sin(delta)) / m_eff + v_y r

F_r is the rolling resistance and -F_yf sin(delta) the front lateral force
projected on the vehicle's x axis (cornering drag, ``cornering_drag``).

The steering actuator: with a time constant tau_delta (``steer_time_constant_s``)
the road-wheel angle follows its target delta_d + b_delta delta_f through a
first-order lag. With the target held over each sample, exactly:

    delta_{k+1} = a delta_k + (1 - a) target_k,      a = exp(-s / tau_delta),
    mean over [t_k, t_k+1) = delta_k + c (target_k - delta_k),   c = 1 - (tau_delta / s)(1 - a).

The discrete model holds its inputs over a sample, so it takes the mean. The
lag is linear, so the model's steering input is the lagged demand and its
steering fault the lagged fault (for a constant bias, the bias): the functions
below take the steering angle the actuator delivers, and :func:`lagged_steer`
computes it from the demand.

All functions broadcast over leading axes, so one call serves one vehicle or a
fleet: ``x`` of shape (..., 3), ``u`` of shape (..., 2), ``w`` of shape (...),
``f`` of shape (..., 2).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from synth.params import STANDARD_GRAVITY_MPS2, VehicleParams

FloatArray = NDArray[np.floating[Any]]

#: Measurement matrix of eq. (4): y = C x = [v_x, r].
C = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])

STATE_NAMES = ("v_x", "v_y", "r")
FAULT_NAMES = ("T_f", "delta_f")


@dataclass(frozen=True)
class ContinuousMatrices:
    """The constant matrices of eqs. (3) and (6).

    B_v : (3, 2)  input matrix
    D_v : (3, 1)  wind matrix
    F_v : (3, 2)  fault matrix, F_v = B_v diag(b_T, b_delta)
    """

    B_v: FloatArray
    D_v: FloatArray
    F_v: FloatArray


def continuous_matrices(p: VehicleParams) -> ContinuousMatrices:
    """B_v, D_v and F_v of eqs. (3) and (6).

    Parameters
    ----------
    p : VehicleParams
        The vehicle.

    Returns
    -------
    ContinuousMatrices
        B_v (3, 2) on the demands [T_d, delta_d], D_v (3, 1) on the wind force F_w, F_v (3, 2) on the faults.
    """
    k = p.symbols()
    # the drive torque at the wheels is a force T / R_w on the effective mass
    b11 = 1.0 / (k["R_w"] * k["m_eff"])
    b22 = 2.0 * k["C_f"] / k["M_v"]
    b32 = 2.0 * k["l_f"] * k["C_f"] / k["I_z"]
    B_v = np.array([[b11, 0.0], [0.0, b22], [0.0, b32]])
    D_v = np.array([[0.0], [0.0], [1.0 / k["I_z"]]])
    F_v = B_v @ np.diag([k["b_T"], k["b_delta"]])
    return ContinuousMatrices(B_v=B_v, D_v=D_v, F_v=F_v)


def tire_forces(x: ArrayLike, steer_rad: ArrayLike, p: VehicleParams) -> tuple[FloatArray, FloatArray]:
    """Front and rear lateral tyre forces F_yf, F_yr of eq. (2) [N].

    Parameters
    ----------
    x : (..., 3) array_like
        State [v_x [m/s], v_y [m/s], r [rad/s]].
    steer_rad : (...) array_like
        Applied front wheel angle delta [rad].
    p : VehicleParams
        The vehicle.

    Returns
    -------
    F_yf, F_yr : (...) ndarray
        The front and rear lateral forces [N].
    """
    x = np.asarray(x, dtype=float)
    k = p.symbols()
    v_x, v_y, r = x[..., 0], x[..., 1], x[..., 2]
    # eq. (2): F_yf = 2 C_f (delta - (v_y + l_f r)/v_x), F_yr = 2 C_r (l_r r - v_y)/v_x
    F_yf = 2.0 * k["C_f"] * (np.asarray(steer_rad, dtype=float) - (v_y + k["l_f"] * r) / v_x)
    F_yr = 2.0 * k["C_r"] * (k["l_r"] * r - v_y) / v_x
    return F_yf, F_yr


def longitudinal_resistance_n(x: ArrayLike, steer_rad: ArrayLike, p: VehicleParams) -> FloatArray:
    """The forces against the motion that eq. (1) leaves out: F_r + F_yf sin(delta) [N].

    F_r is the rolling resistance, F_yf sin(delta) the front lateral force of eq. (2) projected on the vehicle's
    x axis (only with ``cornering_drag``). Zero in the paper's profile.

    Parameters
    ----------
    x : (..., 3) array_like
        State [v_x [m/s], v_y [m/s], r [rad/s]].
    steer_rad : (...) array_like
        Applied front road-wheel angle delta [rad].
    p : VehicleParams
        The vehicle.

    Returns
    -------
    (...) ndarray
        The resistance [N].
    """
    x = np.asarray(x, dtype=float)
    steer_rad = np.asarray(steer_rad, dtype=float)
    resistance = np.full(np.broadcast_shapes(x.shape[:-1], steer_rad.shape), p.rolling_resistance_n)
    if p.cornering_drag:
        F_yf, _ = tire_forces(x, steer_rad, p)
        resistance = resistance + F_yf * np.sin(steer_rad)
    return resistance


def load_transfer_steer_rad(v_x: ArrayLike, r: ArrayLike, torque_nm: ArrayLike, p: VehicleParams) -> FloatArray:
    """The steering angle equivalent to the longitudinal load transfer, -G a_x a_y [rad] (docs/math.md 12.4).

    Braking moves load from the rear axle to the front one, by M_v a_x h / (l_f + l_r); with each axle's
    cornering stiffness following its load, the front grips more and the rear less, and the vehicle turns as if
    steered by -G a_x a_y more (G: :attr:`VehicleParams.load_transfer_gain`, its understeer gradient's change
    per m/s^2 of a_x). a_x = (T_d / R_w - C_x v_x^2 - F_r) / m_eff is the acceleration the demanded torque
    gives, a_y = v_x r the lateral one: known signals only, so the model's input stays known. Zero without a
    centre-of-gravity height.

    Parameters
    ----------
    v_x, r : (...) array_like
        Measured (or, in a simulation, true) speed [m/s] and yaw rate [rad/s].
    torque_nm : (...) array_like
        Demanded drive torque T_d [N m].
    p : VehicleParams
        The vehicle.

    Returns
    -------
    (...) ndarray
        The angle to add to the steering demand [rad].
    """
    v_x = np.asarray(v_x, dtype=float)
    gain = p.load_transfer_gain
    if gain == 0.0:
        return np.zeros(np.broadcast_shapes(v_x.shape, np.shape(r), np.shape(torque_nm)))
    a_x = (np.asarray(torque_nm, dtype=float) / p.wheel_radius_m - p.longitudinal_drag_coeff * v_x**2
           - p.rolling_resistance_n) / p.effective_mass_kg  # fmt: skip
    return np.asarray(-gain * a_x * (v_x * np.asarray(r, dtype=float)), dtype=float)


def load_transfer_steer_change(
    v_x: ArrayLike, r: ArrayLike, torque_change_nm: ArrayLike, p: VehicleParams
) -> FloatArray:
    """How much :func:`load_transfer_steer_rad` changes when the torque changes by ``torque_change_nm`` at the same
    v_x and r: -G Delta T / (R_w m_eff) v_x r [rad] (it is affine in the torque); 0 without a centre-of-gravity
    height."""
    gain = p.load_transfer_gain
    if gain == 0.0:
        return np.zeros(np.broadcast_shapes(np.shape(v_x), np.shape(r), np.shape(torque_change_nm)))
    scale = -gain / (p.wheel_radius_m * p.effective_mass_kg)
    return np.asarray(scale * np.asarray(torque_change_nm, dtype=float) * np.asarray(v_x) * np.asarray(r), dtype=float)


def model_demand(y: ArrayLike, u_d: ArrayLike, p: VehicleParams) -> FloatArray:
    """The demand the model takes, [T_d, delta_d + the load transfer's angle] (:func:`load_transfer_steer_rad`),
    from the measurement y = [v_x, r] and the demand u_d = [T_d, delta_d], (..., 2) each; ``u_d`` itself (as an
    array) without a centre-of-gravity height."""
    u_d = np.asarray(u_d, dtype=float)
    if p.cg_height_m == 0.0:
        return u_d
    y = np.asarray(y, dtype=float)
    out = u_d.copy()
    out[..., 1] += load_transfer_steer_rad(y[..., 0], y[..., 1], u_d[..., 0], p)
    return out


def payload_torque(
    v_x: ArrayLike, torque_nm: ArrayLike, payload_kg: ArrayLike, p: VehicleParams, grade_rad: ArrayLike = 0.0
) -> tuple[FloatArray, FloatArray]:
    """The drive torque the profile's vehicle would need on level ground to move as the vehicle with a payload, on
    a road of grade ``grade_rad``, does, and the ratio rho = m_eff / (m_eff + payload) a torque fault is seen
    through (docs/math.md 12.5 and 12.6).

    A payload of Delta kg at the centre of gravity adds Delta to the effective mass and, with the rolling
    resistance proportional to the weight, F_r Delta / M_v to it; a grade theta (+ uphill) pulls the whole mass
    back with (M_v + Delta) g sin(theta). The vehicle's dv_x/dt - v_y r is then
    rho (T / R_w - C_x v_x^2 - F_r kappa - (M_v + Delta) g sin(theta)) / m_eff with kappa = (M_v + Delta) / M_v.
    The model's eq. (1) gives the same acceleration with the torque

        T_model = rho T + R_w ((1 - rho) C_x v_x^2 + (1 - rho kappa) F_r - rho (M_v + Delta) g sin(theta)),

    and a torque fault T_f of the vehicle appears in the model as rho T_f: an observer fed T_model estimates
    rho T_f, which divided by rho is the fault again. Known signals only, so the model's input stays known and
    the design's certificate holds. Left out: the cornering drag's share (its factor 1 - rho kappa is under
    1 % for any payload when m_eff is within 5 % of M_v), the payload's effect on the lateral dynamics, and the
    grade's cos(theta) on the rolling resistance (0.1 % at a 5 % grade).

    Parameters
    ----------
    v_x : (...) array_like
        Measured speed [m/s].
    torque_nm : (...) array_like
        Demanded drive torque T_d [N m].
    payload_kg : (...) array_like
        The payload [kg], >= 0.
    p : VehicleParams
        The vehicle without payload (the profile).
    grade_rad : (...) array_like
        The road's grade, the angle of the road to the horizontal along the vehicle's x axis [rad], + uphill.

    Returns
    -------
    torque : (...) ndarray
        T_model [N m].
    rho : (...) ndarray
        m_eff / (m_eff + payload).
    """
    payload = np.asarray(payload_kg, dtype=float)
    v_x = np.asarray(v_x, dtype=float)
    m_eff = p.effective_mass_kg
    rho = m_eff / (m_eff + payload)
    kappa = (p.mass_kg + payload) / p.mass_kg
    drag = (1.0 - rho) * p.longitudinal_drag_coeff * v_x**2 + (1.0 - rho * kappa) * p.rolling_resistance_n
    torque = rho * np.asarray(torque_nm, dtype=float) + p.wheel_radius_m * drag
    grade = np.asarray(grade_rad, dtype=float)
    if grade.any():
        torque = torque - grade_torque(grade, payload, p)
    return np.asarray(torque, dtype=float), rho


def grade_torque(grade_rad: ArrayLike, payload_kg: ArrayLike, p: VehicleParams) -> FloatArray:
    """The part of :func:`payload_torque` the road's grade takes [N m]: rho R_w (M_v + payload) g sin(theta), with
    theta [rad] + uphill and rho = m_eff / (m_eff + payload) (docs/math.md 12.6)."""
    payload = np.asarray(payload_kg, dtype=float)
    m_eff = p.effective_mass_kg
    return np.asarray(m_eff / (m_eff + payload) * _grade_pull(grade_rad, payload, p), dtype=float)


def level_torque(torque_nm: ArrayLike, grade_rad: ArrayLike, payload_kg: ArrayLike, p: VehicleParams) -> FloatArray:
    """The torque that moves the vehicle (with its payload) on level ground as ``torque_nm`` does on a road of grade
    ``grade_rad`` [rad, + uphill]: T - R_w (M_v + payload) g sin(theta); :func:`payload_torque` of it without the
    grade is :func:`payload_torque` of T with it (docs/math.md 12.6)."""
    return np.asarray(np.asarray(torque_nm, dtype=float) - _grade_pull(grade_rad, payload_kg, p), dtype=float)


def model_inputs(
    y: FloatArray, u: FloatArray, payload_kg: FloatArray | float | None, grade_rad: FloatArray | None, p: VehicleParams
) -> tuple[FloatArray, FloatArray, FloatArray | None]:
    """What the service steps for samples of a vehicle with a payload on a road with a grade (docs/math.md 12.5,
    12.6): the observer's input, the effectiveness stage's input, and rho.

    The observer takes the model's torque, :func:`payload_torque` with the grade; the effectiveness stage the same
    without the grade's part (a loss of effectiveness scales the torque the actuator delivers, not the weight's
    pull); a torque fault (and a torque bias) estimated on these is rho times the vehicle's. On a grade the
    observer's steering demand also carries :func:`load_transfer_steer_change` of the grade's part, so that the
    model's load-transfer angle (:func:`model_demand`) is the one of the torque without it: load moves between the
    axles with the force the tyres put on the road, m (a_x + g sin(theta)), which the grade leaves as it is for
    a given torque, not with the acceleration it slows (docs/math.md 12.6).

    Parameters
    ----------
    y, u : (k, 2) ndarray
        Measured [v_x, r] and demanded [T_d, delta_d].
    payload_kg : (k,) ndarray or float, optional
        The payload [kg]; None for none.
    grade_rad : (k,) ndarray, optional
        The road grade [rad, + uphill]; None for level ground.
    p : VehicleParams
        The profile's vehicle.

    Returns
    -------
    model_u, stage_u : (k, 2) ndarray
        The observer's and the stage's [torque, delta_d]; ``u`` itself where nothing changes it.
    rho : ndarray or None
        m_eff / (m_eff + payload), shaped as v_x and ``payload_kg`` broadcast; None without a payload.
    """
    stage_u, rho = u, None
    if payload_kg is not None:
        torque, rho = payload_torque(y[:, 0], u[:, 0], payload_kg, p)
        stage_u = u.copy()
        stage_u[:, 0] = torque
    if grade_rad is None:
        return stage_u, stage_u, rho
    model_u = stage_u.copy()
    pull = grade_torque(grade_rad, 0.0 if payload_kg is None else payload_kg, p)
    model_u[:, 0] -= pull
    if p.cg_height_m != 0.0:
        model_u[:, 1] += load_transfer_steer_change(y[:, 0], y[:, 1], pull, p)
    return model_u, stage_u, rho


def _grade_pull(grade_rad: ArrayLike, payload_kg: ArrayLike, p: VehicleParams) -> FloatArray:
    """R_w (M_v + payload) g sin(theta): the wheel torque that holds the weight on the grade [N m]."""
    weight = (p.mass_kg + np.asarray(payload_kg, dtype=float)) * STANDARD_GRAVITY_MPS2
    return np.asarray(p.wheel_radius_m * weight * np.sin(np.asarray(grade_rad, dtype=float)), dtype=float)


def continuous_dynamics(x: ArrayLike, u_d: ArrayLike, w: ArrayLike, f: ArrayLike, p: VehicleParams) -> FloatArray:
    """dx/dt of eqs. (1), (2) and (5): the plant as physics, not as a matrix form.

    Parameters
    ----------
    x : (..., 3) array_like
        State [v_x [m/s], v_y [m/s], r [rad/s]].
    u_d : (..., 2) array_like
        Demanded [T_d [N m], delta_d [rad]].
    w : (...) array_like
        Lateral wind force F_w [N].
    f : (..., 2) array_like
        Faults [T_f [N m], delta_f [rad]].
    p : VehicleParams
        The vehicle.

    Returns
    -------
    (..., 3) ndarray
        dx/dt [m/s^2, m/s^2, rad/s^2].
    """
    x = np.asarray(x, dtype=float)
    u_d = np.asarray(u_d, dtype=float)
    f = np.asarray(f, dtype=float)
    k = p.symbols()
    # eq. (5): applied inputs T = T_d + b_T T_f, delta = delta_d + b_delta delta_f
    torque = u_d[..., 0] + k["b_T"] * f[..., 0]
    steer = u_d[..., 1] + k["b_delta"] * f[..., 1]
    v_x, v_y, r = x[..., 0], x[..., 1], x[..., 2]
    F_yf, F_yr = tire_forces(x, steer, p)
    # eq. (1), physical: dv_x/dt = (T / R_w - C_x v_x^2 - F_r - F_yf sin(delta)) / m_eff + v_y r
    drive_force = torque / k["R_w"] - k["C_x"] * v_x**2 - longitudinal_resistance_n(x, steer, p)
    dv_x = drive_force / k["m_eff"] + v_y * r
    dv_y = (F_yf + F_yr - k["C_y"] * v_y**2) / k["M_v"] - v_x * r
    dr = (k["l_f"] * F_yf - k["l_r"] * F_yr) / k["I_z"] + np.asarray(w, dtype=float) / k["I_z"]
    return np.stack([dv_x, dv_y, dr], axis=-1)


def state_matrix(x: ArrayLike, p: VehicleParams) -> FloatArray:
    """A_v(x) of eq. (3), such that dx/dt = A_v(x) x + B_v u + D_v w + F_v f - e_1 R(x, delta) / m_eff.

    R is :func:`longitudinal_resistance_n`.

    Parameters
    ----------
    x : (..., 3) array_like
        State [v_x [m/s], v_y [m/s], r [rad/s]].
    p : VehicleParams
        The vehicle.

    Returns
    -------
    (..., 3, 3) ndarray
        A_v(x).
    """
    x = np.asarray(x, dtype=float)
    k = p.symbols()
    v_x, v_y = x[..., 0], x[..., 1]
    a11 = -k["C_x"] * v_x / k["m_eff"]
    a22 = -2.0 * (k["C_f"] + k["C_r"]) / (k["M_v"] * v_x) - k["C_y"] * v_y / k["M_v"]
    a23 = 2.0 * (k["C_r"] * k["l_r"] - k["C_f"] * k["l_f"]) / (k["M_v"] * v_x) - v_x
    a32 = 2.0 * (k["l_r"] * k["C_r"] - k["C_f"] * k["l_f"]) / (k["I_z"] * v_x)
    a33 = -2.0 * (k["C_f"] * k["l_f"] ** 2 + k["C_r"] * k["l_r"] ** 2) / (k["I_z"] * v_x)
    zero = np.zeros_like(v_x)
    return np.stack(
        [
            np.stack([a11, zero, v_y], axis=-1),
            np.stack([zero, a22, a23], axis=-1),
            np.stack([zero, a32, a33], axis=-1),
        ],
        axis=-2,
    )


def lagged_steer(steer_demand_rad: ArrayLike, p: VehicleParams, initial_rad: ArrayLike | None = None) -> FloatArray:
    """The road-wheel angle over each sample for a demand sequence held over the samples.

    The mean over [t_k, t_k+1) of a first-order actuator lag, delta_k + c (delta_d,k - delta_k), with
    delta_{k+1} = a delta_k + (1 - a) delta_d,k (``VehicleParams.steer_lag_factor``, ``steer_lag_mean_factor``).
    The ideal actuator (tau = 0) returns the demand itself.

    Parameters
    ----------
    steer_demand_rad : (K, ...) array_like
        The demanded angle delta_d at each sample [rad].
    p : VehicleParams
        The vehicle (its steering time constant).
    initial_rad : (...) array_like, optional
        delta_0 [rad]; by default the first demand (an actuator at rest).

    Returns
    -------
    (K, ...) ndarray
        The mean road-wheel angle over each sample [rad].
    """
    demand = np.asarray(steer_demand_rad, dtype=float)
    a, c = p.steer_lag_factor, p.steer_lag_mean_factor
    if a == 0.0:
        return demand.copy()
    out = np.empty_like(demand)
    state = demand[0].copy() if initial_rad is None else np.asarray(initial_rad, dtype=float).copy()
    for k in range(demand.shape[0]):
        out[k] = state + c * (demand[k] - state)
        state = a * state + (1.0 - a) * demand[k]
    return out


def euler_step(x: ArrayLike, u_d: ArrayLike, w: ArrayLike, f: ArrayLike, p: VehicleParams) -> FloatArray:
    """One step of eq. (12): x_{k+1} = x_k + s dx/dt(x_k).

    Parameters
    ----------
    x, u_d, w, f, p
        As for :func:`continuous_dynamics`.

    Returns
    -------
    (..., 3) ndarray
        x_{k+1} [m/s, m/s, rad/s].
    """
    x = np.asarray(x, dtype=float)
    return x + p.sample_period_s * continuous_dynamics(x, u_d, w, f, p)


def rk4_step(
    x: ArrayLike,
    u_d: ArrayLike,
    w: ArrayLike,
    f: ArrayLike,
    p: VehicleParams,
    dt_s: float,
) -> FloatArray:
    """One classical Runge-Kutta step of :func:`continuous_dynamics` with the inputs held.

    Parameters
    ----------
    x, u_d, w, f, p
        As for :func:`continuous_dynamics`.
    dt_s : float
        The step [s].

    Returns
    -------
    (..., 3) ndarray
        The state after ``dt_s`` [m/s, m/s, rad/s].
    """
    x = np.asarray(x, dtype=float)
    k1 = continuous_dynamics(x, u_d, w, f, p)
    k2 = continuous_dynamics(x + 0.5 * dt_s * k1, u_d, w, f, p)
    k3 = continuous_dynamics(x + 0.5 * dt_s * k2, u_d, w, f, p)
    k4 = continuous_dynamics(x + dt_s * k3, u_d, w, f, p)
    return x + (dt_s / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
