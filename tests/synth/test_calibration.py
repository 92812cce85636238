"""Calibration: known parameters back from data of the project's own model, and plain refusals of data that
cannot identify them."""

import dataclasses

import numpy as np
import pytest

from edge_client.scenario import Manoeuvre, Scenario, SensorNoise, SpeedPoint
from edge_client.simulation import simulate_plant
from synth.calibration import CalibrationRefused, Drive, calibrate
from synth.params import VehicleParams

#: A physical car with everything calibration identifies switched on.
CAR = VehicleParams(
    mass_kg=1230.0,
    effective_mass_kg=1290.0,
    wheel_radius_m=0.33,
    yaw_inertia_kgm2=1540.0,
    front_axle_distance_m=0.9,
    rear_axle_distance_m=1.5,
    front_cornering_stiffness_npr=80000.0,
    rear_cornering_stiffness_npr=50000.0,
    longitudinal_drag_coeff=0.4,
    rolling_resistance_n=150.0,
    cornering_drag=True,
    steer_time_constant_s=0.04,
)
BASE = {
    name: getattr(CAR, name)
    for name in ("mass_kg", "front_axle_distance_m", "rear_axle_distance_m", "wheel_radius_m", "yaw_inertia_kgm2")
}
NOISE = SensorNoise(vx_sigma_mps=0.05, r_sigma_radps=0.005)


def _drive(name: str, duration_s: float, speeds, manoeuvres, seed: int = 3) -> Drive:
    scenario = Scenario(
        name=name,
        duration_s=duration_s,
        initial_speed_mps=speeds[0][1],
        vehicle=CAR,
        speed_profile=[SpeedPoint(t_s=t, speed_mps=v) for t, v in speeds],
        manoeuvres=manoeuvres,
        noise=NOISE,
        seed=seed,
    )
    rec = simulate_plant([scenario])
    return Drive(t=rec.t, y=rec.y[:, 0, :], u=rec.u[:, 0, :], name=name)


@pytest.fixture(scope="module")
def healthy() -> Drive:
    """A minute of ordinary driving: speed changes between 9 and 22 m/s, turns, lane changes, slaloms."""
    speeds = [(0, 10), (7, 18), (12, 18), (18, 9), (24, 9), (30, 20), (38, 20), (44, 12), (50, 12), (56, 17), (60, 17)]
    manoeuvres = [
        Manoeuvre(kind="slalom", start_s=1, duration_s=5, amplitude_rad=0.03),
        Manoeuvre(kind="turn", start_s=13, duration_s=4, amplitude_rad=0.04, ramp_s=0.5),
        Manoeuvre(kind="lane_change", start_s=25, duration_s=4, amplitude_rad=-0.04),
        Manoeuvre(kind="turn", start_s=39, duration_s=4, amplitude_rad=-0.03, ramp_s=0.4),
        Manoeuvre(kind="slalom", start_s=50, duration_s=6, amplitude_rad=0.035),
    ]
    return _drive("healthy", 60.0, speeds, manoeuvres)


@pytest.fixture(scope="module")
def result(healthy):
    return calibrate([healthy], BASE)


def test_calibration_recovers_the_parameters_of_the_projects_own_model(result):
    e = result.estimates
    assert set(e) == {
        "effective_mass_kg",
        "longitudinal_drag_coeff",
        "rolling_resistance_n",
        "front_cornering_stiffness_npr",
        "rear_cornering_stiffness_npr",
        "steer_time_constant_s",
    }
    assert e["effective_mass_kg"].value == pytest.approx(1290.0, rel=0.01)
    assert e["front_cornering_stiffness_npr"].value == pytest.approx(80000.0, rel=0.05)
    assert e["rear_cornering_stiffness_npr"].value == pytest.approx(50000.0, rel=0.05)
    assert e["steer_time_constant_s"].value == pytest.approx(0.04, rel=0.2)
    assert e["longitudinal_drag_coeff"].value == pytest.approx(0.4, abs=0.1)
    assert e["rolling_resistance_n"].value == pytest.approx(150.0, abs=40.0)
    for name, est in e.items():  # every interval holds its estimate, and here the truth
        assert est.low <= est.value <= est.high, name
        assert est.low <= getattr(CAR, name) <= est.high, name
    assert result.noise["vx_sigma_mps"] == pytest.approx(0.05, rel=0.1)
    assert result.noise["r_sigma_radps"] == pytest.approx(0.005, rel=0.1)
    # the fits explain the data down to the sensor noise
    assert 0.9 < result.residuals["yaw_rate_rms_over_noise"] < 1.15
    assert 0.8 < result.residuals["speed_change_rms_over_noise"] < 1.3


def test_the_calibrated_profile_is_complete_and_its_box_holds_the_drive(result, healthy):
    p, b = result.params, result.bounds
    assert p.cornering_drag and p.mass_kg == CAR.mass_kg and p.wheel_radius_m == CAR.wheel_radius_m
    assert b.vx_min_mps <= healthy.y[:, 0].min() and healthy.y[:, 0].max() <= b.vx_max_mps
    assert np.abs(healthy.y[:, 1]).max() <= b.r_max_radps and b.r_min_radps == -b.r_max_radps
    assert np.abs(healthy.u[:, 1]).max() < b.steer_max_rad
    assert VehicleParams.model_validate(p.model_dump()) == p


def test_a_given_parameter_is_kept_not_identified(healthy):
    res = calibrate([healthy], {**BASE, "rolling_resistance_n": 150.0, "longitudinal_drag_coeff": 0.4})
    assert "rolling_resistance_n" not in res.estimates and res.params.rolling_resistance_n == 150.0
    assert res.estimates["effective_mass_kg"].value == pytest.approx(1290.0, rel=0.01)


def _refusal(drives, base=BASE) -> str:
    with pytest.raises(CalibrationRefused) as info:
        calibrate(drives, base)
    return info.value.reason


def test_refuses_too_little_driving(healthy):
    short = Drive(t=healthy.t[:2000], y=healthy.y[:2000], u=healthy.u[:2000], name="short")
    assert "too short: 20.0 s of driving" in _refusal([short])


def test_refuses_data_without_cornering():
    straight = _drive("straight", 40.0, [(0, 10), (10, 20), (20, 10), (30, 20), (40, 20)], [])
    assert _refusal([straight]).startswith("no cornering")


def test_refuses_data_without_acceleration():
    steady = _drive(
        "steady",
        40.0,
        [(0, 15), (40, 15)],
        [Manoeuvre(kind="slalom", start_s=1, duration_s=38, amplitude_rad=0.03)],
    )
    assert _refusal([steady]).startswith("no acceleration")


def test_refuses_non_finite_rows_and_a_missing_base(healthy):
    y = healthy.y.copy()
    y[123, 1] = np.nan
    assert "row 124 has a non-finite y value" in _refusal([dataclasses.replace(healthy, y=y)])
    assert "must give wheel_radius_m" in _refusal([healthy], {k: v for k, v in BASE.items() if k != "wheel_radius_m"})


def test_refuses_a_recording_that_looks_faulty(healthy):
    """A torque actuator losing 200 N m from t = 30 s: the demand no longer explains the accelerations there."""
    u = healthy.u.copy()
    u[3000:, 0] += 200.0  # the recorded demand is 200 N m more than what drove the vehicle
    reason = _refusal([dataclasses.replace(healthy, u=u, name="torque-fault")])
    assert reason.startswith("torque-fault looks faulty") and "torque fault" in reason


def test_refuses_a_biased_steering_signal(healthy):
    u = healthy.u.copy()
    u[:, 1] += 0.015
    assert _refusal([dataclasses.replace(healthy, u=u)]).startswith("the steering looks biased")
