"""The longitudinal load transfer as the model's equivalent steering angle (docs/math.md 12.4)."""

import dataclasses

import numpy as np
import pytest

from edge_client.simulation import ekf_factory
from synth.design import synthesize
from synth.gains import ObserverGains
from synth.model import load_transfer_steer_rad, model_demand, rk4_step
from synth.observer import FuzzyObserver
from synth.options import DesignOptions
from synth.params import STANDARD_GRAVITY_MPS2, VehicleParams

HEIGHT_M = 0.55


def test_the_gain_is_the_understeer_gradients_change_per_unit_of_longitudinal_acceleration():
    p = VehicleParams(
        mass_kg=1200.0,
        front_axle_distance_m=1.0,
        rear_axle_distance_m=1.5,
        front_cornering_stiffness_npr=60000.0,
        rear_cornering_stiffness_npr=50000.0,
        cg_height_m=HEIGHT_M,
    )

    # K_us = M / L (l_r / (2 C_f) - l_f / (2 C_r)) with each axle's stiffness following its load:
    # 2 C_f (1 - a_x h / (g l_r)), 2 C_r (1 + a_x h / (g l_f)); dK_us / da_x at a_x = 0, by differences
    def understeer(a_x: float) -> float:
        front = 2 * 60000.0 * (1 - a_x * HEIGHT_M / (STANDARD_GRAVITY_MPS2 * 1.5))
        rear = 2 * 50000.0 * (1 + a_x * HEIGHT_M / (STANDARD_GRAVITY_MPS2 * 1.0))
        return 1200.0 / 2.5 * (1.5 / front - 1.0 / rear)

    slope = (understeer(1e-4) - understeer(-1e-4)) / 2e-4
    assert p.load_transfer_gain == pytest.approx(slope, rel=1e-6)
    assert VehicleParams().load_transfer_gain == 0.0


def test_a_profile_without_a_height_keeps_its_hash():
    assert "cg_height_m" not in VehicleParams().hashed()
    assert VehicleParams(cg_height_m=HEIGHT_M).hashed()["cg_height_m"] == HEIGHT_M


@pytest.mark.parametrize(("torque_nm", "sign"), [(-2000.0, 1.0), (2000.0, -1.0)])
def test_braking_in_a_turn_steers_the_model_further_into_it_and_accelerating_out(torque_nm, sign):
    p = VehicleParams(cg_height_m=HEIGHT_M)
    y = np.array([[15.0, 0.2]])  # a left turn: a_y = 3 m/s^2
    u = np.array([[torque_nm, 0.03]])
    effective = model_demand(y, u, p)
    a_x = (torque_nm / p.wheel_radius_m - p.longitudinal_drag_coeff * 15.0**2) / p.effective_mass_kg
    assert effective[0, 0] == torque_nm
    assert effective[0, 1] - 0.03 == pytest.approx(-p.load_transfer_gain * a_x * 3.0, rel=1e-12)
    assert np.sign(effective[0, 1] - 0.03) == sign
    np.testing.assert_array_equal(model_demand(y, u, VehicleParams()), u)
    assert load_transfer_steer_rad(15.0, 0.2, torque_nm, VehicleParams()) == 0.0


def _braking_in_a_turn(p: VehicleParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The model's vehicle (load transfer included) turning left at 20 m/s, braking at 3 m/s^2 from 1.5 s to 4.5 s:
    (y, u, the load transfer's angle) per sample, noise-free."""
    s = p.sample_period_s
    n = round(6.0 / s)
    x = np.array([20.0, 0.0, 0.0])
    y, u, angle = np.zeros((n, 2)), np.zeros((n, 2)), np.zeros(n)
    for k in range(n):
        t = k * s
        a_cmd = -3.0 if 1.5 <= t < 4.5 else 0.0
        torque = p.wheel_radius_m * (p.effective_mass_kg * a_cmd + p.longitudinal_drag_coeff * x[0] ** 2)
        y[k] = x[[0, 2]]
        u[k] = [torque, 0.04 * min(1.0, t / 0.5)]
        effective = model_demand(y[k], u[k], p)
        angle[k] = effective[1] - u[k, 1]
        x = rk4_step(x, effective, 0.0, np.zeros(2), p, s)
    return y, u, angle


def _steer_fault_estimates(make: object, y: np.ndarray, u: np.ndarray) -> np.ndarray:
    estimator = make(y[:1], None, u[:1])  # type: ignore[operator]
    return np.array([estimator.step(y[k : k + 1], u[k : k + 1]).faults[0, 1] for k in range(len(y))])


def test_an_observer_that_knows_the_height_sees_no_steering_fault_when_braking_in_a_turn():
    p = VehicleParams(cg_height_m=HEIGHT_M)
    gains = synthesize(p, options=DesignOptions())
    # the same gains (the LMIs do not involve h) for a model without the load transfer
    blind = dataclasses.replace(gains, params=p.model_copy(update={"cg_height_m": 0.0}))
    assert blind.params.cg_height_m == 0.0 and np.array_equal(blind.L, gains.L) and np.array_equal(blind.N, gains.N)
    y, u, angle = _braking_in_a_turn(p)
    braking = slice(round(2.5 / p.sample_period_s), round(4.5 / p.sample_period_s))
    assert np.abs(angle[braking]).mean() > 2e-3  # the effect is there: a few mrad

    def observer(g: ObserverGains) -> object:
        return lambda y0, x0, u0: FuzzyObserver(g, y0, x0, u0)

    knowing = _steer_fault_estimates(observer(gains), y, u)[braking]
    not_knowing = _steer_fault_estimates(observer(blind), y, u)[braking]
    ekf_knowing = _steer_fault_estimates(ekf_factory(gains), y, u)[braking]
    # without the term the observer reads the load transfer's angle as a steering fault, of its sign and size
    assert np.mean(not_knowing) == pytest.approx(np.mean(angle[braking]), rel=0.3)
    # with it, the observer and the EKF read (almost) nothing
    assert np.sqrt(np.mean(knowing**2)) < 0.15 * np.abs(np.mean(not_knowing))
    assert np.sqrt(np.mean(ekf_knowing**2)) < 0.15 * np.abs(np.mean(not_knowing))
