"""A payload and a road grade as the model's equivalent drive torque (synth.model.payload_torque, docs/math.md 12.5
and 12.6)."""

import numpy as np
import pytest

from synth.design import synthesize
from synth.model import (
    continuous_dynamics,
    grade_torque,
    level_torque,
    model_demand,
    model_inputs,
    payload_torque,
    rk4_step,
)
from synth.observer import FuzzyObserver
from synth.options import DesignOptions
from synth.params import STANDARD_GRAVITY_MPS2, VehicleParams
from tests.calibration_data import loaded

PROFILE = VehicleParams(rolling_resistance_n=180.0, longitudinal_drag_coeff=0.45, effective_mass_kg=1340.0)
PAYLOAD_KG = 240.0


@pytest.mark.parametrize("fault_nm", [0.0, -150.0])
def test_the_model_fed_the_payload_torque_accelerates_as_the_loaded_vehicle(fault_nm):
    heavy = loaded(PROFILE, PAYLOAD_KG)
    x = np.array([[8.0, 0.1, 0.05], [25.0, -0.2, -0.1], [15.0, 0.0, 0.0]])
    u = np.array([[900.0, 0.02], [-1500.0, -0.01], [0.0, 0.0]])
    f = np.array([fault_nm, 0.0])
    truth = continuous_dynamics(x, u, 0.0, f, heavy)[:, 0]
    torque, rho = payload_torque(x[:, 0], u[:, 0], PAYLOAD_KG, PROFILE)
    model = continuous_dynamics(x, np.column_stack([torque, u[:, 1]]), 0.0, rho * f, PROFILE)[:, 0]
    np.testing.assert_allclose(model, truth, rtol=1e-12, atol=1e-12)
    assert rho == pytest.approx(1340.0 / 1580.0)
    unchanged, one = payload_torque(x[:, 0], u[:, 0], 0.0, PROFILE)
    np.testing.assert_array_equal(unchanged, u[:, 0])
    assert one == 1.0


@pytest.mark.parametrize("payload_kg", [0.0, PAYLOAD_KG])
def test_the_model_fed_the_grade_torque_accelerates_as_the_vehicle_on_the_grade(payload_kg):
    """On a grade theta the weight (M_v + payload) g sin(theta) pulls the vehicle back: the loaded vehicle with
    that force as a torque fault -R_w (M_v + payload) g sin(theta) is the truth; the profile's model fed
    payload_torque(..., grade) and rho times the vehicle's own fault accelerates as it does."""
    heavy = loaded(PROFILE, payload_kg)
    x = np.array([[8.0, 0.1, 0.05], [25.0, -0.2, -0.1], [15.0, 0.0, 0.0]])
    u = np.array([[900.0, 0.02], [-1500.0, -0.01], [400.0, 0.0]])
    grade = np.array([0.08, -0.05, 0.0])
    fault = -120.0
    pull = PROFILE.wheel_radius_m * (PROFILE.mass_kg + payload_kg) * STANDARD_GRAVITY_MPS2 * np.sin(grade)
    truth = continuous_dynamics(x, u, 0.0, np.column_stack([fault - pull, np.zeros(3)]), heavy)[:, 0]
    torque, rho = payload_torque(x[:, 0], u[:, 0], payload_kg, PROFILE, grade)
    model = continuous_dynamics(x, np.column_stack([torque, u[:, 1]]), 0.0, np.array([rho * fault, 0.0]), PROFILE)
    np.testing.assert_allclose(model[:, 0], truth, rtol=1e-12, atol=1e-12)
    # the grade's part, and the level-ground torque the payload's own term is then applied to
    without, _ = payload_torque(x[:, 0], u[:, 0], payload_kg, PROFILE)
    np.testing.assert_allclose(without - torque, grade_torque(grade, payload_kg, PROFILE), rtol=1e-12)
    level = level_torque(u[:, 0], grade, payload_kg, PROFILE)
    np.testing.assert_allclose(payload_torque(x[:, 0], level, payload_kg, PROFILE)[0], torque, rtol=1e-12)
    assert grade_torque(0.0, payload_kg, PROFILE) == 0.0


def _accelerating(p: VehicleParams, fault_nm: float) -> tuple[np.ndarray, np.ndarray]:
    """The loaded vehicle accelerating and braking at 1.5 m/s^2 (period 8 s), a torque fault from 3 s; noise-free
    (y, u) per sample."""
    s = p.sample_period_s
    n = round(16.0 / s)
    x = np.array([12.0, 0.0, 0.0])
    y, u = np.zeros((n, 2)), np.zeros((n, 2))
    for k in range(n):
        t = k * s
        a_cmd = 1.5 * np.sign(np.sin(2 * np.pi * t / 8.0))
        torque = p.wheel_radius_m * (p.effective_mass_kg * a_cmd + p.longitudinal_drag_coeff * x[0] ** 2)
        torque += p.wheel_radius_m * p.rolling_resistance_n
        y[k], u[k] = x[[0, 2]], [torque, 0.0]
        x = rk4_step(x, u[k], 0.0, np.array([fault_nm if t >= 3.0 else 0.0, 0.0]), p, s)
    return y, u


def test_an_observer_told_the_payload_reads_the_torque_fault_and_only_it():
    gains = synthesize(PROFILE, options=DesignOptions())
    heavy = loaded(PROFILE, PAYLOAD_KG)
    late = slice(round(8.0 / PROFILE.sample_period_s), None)

    def torque_fault(y: np.ndarray, u: np.ndarray, payload_kg: float) -> np.ndarray:
        torque, rho = payload_torque(y[:, 0], u[:, 0], payload_kg, PROFILE)
        model_u = np.column_stack([torque, u[:, 1]])
        obs = FuzzyObserver(gains, y[:1], None, model_u[:1])
        est = np.array([obs.step(y[k : k + 1], model_u[k : k + 1]).faults[0, 0] for k in range(len(y))])
        return est / rho

    y, u = _accelerating(heavy, 0.0)
    told = torque_fault(y, u, PAYLOAD_KG)[late]
    blind = torque_fault(y, u, 0.0)[late]
    # without the payload, accelerating reads as a torque fault of about Delta R_w a_x (here ~ 110 N m peaks)
    assert np.abs(blind).max() > 60.0
    assert np.abs(told).max() < 0.05 * np.abs(blind).max()
    y, u = _accelerating(heavy, -200.0)
    assert np.median(torque_fault(y, u, PAYLOAD_KG)[late]) == pytest.approx(-200.0, rel=0.03)


def _turning_on_a_hill(p: VehicleParams, grade_amplitude_rad: float) -> tuple[np.ndarray, ...]:
    """A vehicle turning left and right at 12 m/s on a road that climbs and descends, its speed held (the torque
    sent carries the weight's pull); the plant's load transfer follows the torque sent (the tyres' force on the
    road), the pull acts at the centre of gravity. Noise-free (y, u, grade) per sample."""
    s = p.sample_period_s
    t = np.arange(round(24.0 / s)) * s
    grade = grade_amplitude_rad * np.sin(2 * np.pi * t / 12.0)
    pull = grade_torque(grade, 0.0, p)
    x = np.array([12.0, 0.0, 0.0])
    y, u = np.zeros((t.size, 2)), np.zeros((t.size, 2))
    for k in range(t.size):
        hold = p.wheel_radius_m * (p.longitudinal_drag_coeff * x[0] ** 2 + p.rolling_resistance_n)
        y[k], u[k] = x[[0, 2]], [hold + pull[k], 0.04 * np.sin(2 * np.pi * t[k] / 5.0)]
        x = rk4_step(x, model_demand(x[[0, 2]], u[k], p), 0.0, np.array([-pull[k], 0.0]), p, s)
    return y, u, grade


def test_on_a_grade_the_load_transfer_follows_the_torque_sent_not_the_acceleration():
    """Load moves between the axles with the force the tyres put on the road, m (a_x + g sin(theta)); the weight's
    pull acts at the centre of gravity and moves none (docs/math.md 12.6). A vehicle with a CG height turning on a
    6 % hill: told the grade (synth.model.model_inputs), the observer estimates as on level ground; given the
    level-ground torque with the demanded angle alone, its load transfer follows the acceleration, and the grade's
    g sin(theta) a_y reads as a steering fault."""
    p = PROFILE.model_copy(update={"cg_height_m": 0.6})
    gains = synthesize(p, options=DesignOptions())
    y, u, grade = _turning_on_a_hill(p, 0.06)
    model_u, stage_u, rho = model_inputs(y, u, None, grade, p)
    assert rho is None and stage_u is u
    np.testing.assert_allclose(model_u[:, 0], u[:, 0] - grade_torque(grade, 0.0, p), rtol=1e-12)
    # the model's load-transfer angle is the one of the torque sent
    np.testing.assert_allclose(model_demand(y, model_u, p)[:, 1], model_demand(y, u, p)[:, 1], rtol=0, atol=1e-15)

    def steer_fault(y: np.ndarray, demand: np.ndarray) -> np.ndarray:
        obs = FuzzyObserver(gains, y[:1], None, demand[:1])
        return np.array([obs.step(y[k : k + 1], demand[k : k + 1]).faults[0, 1] for k in range(len(y))])

    level_y, level_u, _ = _turning_on_a_hill(p, 0.0)
    level = steer_fault(level_y, level_u)
    told = steer_fault(y, model_u) - level
    acceleration_driven = steer_fault(y, np.column_stack([model_u[:, 0], u[:, 1]])) - level
    # G g sin(theta) a_y: 0.6 mrad at the crests here
    assert np.abs(acceleration_driven).max() > 4e-4
    assert np.abs(told).max() < 0.02 * np.abs(acceleration_driven).max()
