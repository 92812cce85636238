"""Calibration: known parameters back from data of the project's own model, and plain refusals of data that
cannot identify them."""

import dataclasses

import numpy as np
import pytest

from edge_client.scenario import Manoeuvre
from synth.calibration import CalibrationRefused, Drive, calibrate
from synth.params import VehicleParams
from tests.calibration_data import (
    BASE,
    CAR,
    CG_HEIGHT_M,
    PAYLOAD_KG,
    healthy_drive,
    healthy_drive_on_hills,
    healthy_drive_on_hills_with_load_transfer,
    healthy_drive_with_load_transfer,
    loaded_drive_on_hills,
    simulated_drive,
)


@pytest.fixture(scope="module")
def healthy() -> Drive:
    return healthy_drive()


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


def test_a_base_without_a_cg_height_is_told_what_the_model_then_leaves_out(result):
    assert "cg_height_m" not in BASE and result.params.cg_height_m == 0.0
    assert sum("no centre-of-gravity height (cg_height_m)" in note for note in result.notes) == 1


def _refusal(drives, base=BASE) -> str:
    with pytest.raises(CalibrationRefused) as info:
        calibrate(drives, base)
    return info.value.reason


def test_a_vehicle_whose_braking_in_turns_moves_load_is_calibrated_with_its_cg_height():
    """The car with a CG height, braking in its turns: given the height, the stiffnesses come back; without it,
    the refusal names the height as what would explain the data."""
    drive = healthy_drive_with_load_transfer()
    res = calibrate([drive], {**BASE, "cg_height_m": CG_HEIGHT_M})
    assert res.params.cg_height_m == CG_HEIGHT_M
    assert res.estimates["front_cornering_stiffness_npr"].value == pytest.approx(80000.0, rel=0.05)
    assert res.estimates["rear_cornering_stiffness_npr"].value == pytest.approx(50000.0, rel=0.05)
    assert not any("no centre-of-gravity height" in note for note in res.notes)
    reason = _refusal([drive])
    assert "cannot identify front_cornering_stiffness_npr" in reason and "give the data sheet's cg_height_m" in reason


def test_a_recording_on_hills_calibrates_with_its_grade_as_on_level_ground(result):
    """The same minute on a road from -3 % to +5 %: with the grade the car reported, the longitudinal parameters
    come back as from level ground (synth.calibration.level_ground, docs/math.md 12.6); without it the weight's
    pull reads as a mass that cannot be identified, and the refusal says the grade would explain it."""
    hills = healthy_drive_on_hills()
    assert hills.grade is not None and hills.grade.max() > 0.04
    res = calibrate([hills], BASE)
    for name, truth in (
        ("effective_mass_kg", CAR.effective_mass_kg),
        ("rolling_resistance_n", CAR.rolling_resistance_n),
    ):
        assert res.estimates[name].value == pytest.approx(truth, rel=0.01), name
        assert res.estimates[name].value == pytest.approx(result.estimates[name].value, rel=0.005), name
    reason = _refusal([dataclasses.replace(hills, grade=None)])
    assert "cannot identify effective_mass_kg" in reason and "a grade column" in reason
    broken = hills.grade.copy()
    broken[7] = np.nan
    assert "row 8 has a non-finite grade" in _refusal([dataclasses.replace(hills, grade=broken)])
    assert "must give mass_kg" in _refusal([hills], {k: v for k, v in BASE.items() if k != "mass_kg"})


def test_a_loaded_recording_told_its_payload_calibrates_the_vehicle_without_it(result):
    """The minute on hills by the car carrying a fifth of its mass (the project's model), with its grade: told the
    payload, calibration identifies the car without it, the profile a reported payload is added to (the
    effective mass within 0.5 % of the truth and of the empty car's calibration, the rolling resistance within its
    interval); not told, it identifies a heavier car (more than half the payload). A payload that is
    negative, not finite or above the vehicle's mass is refused."""
    hills = loaded_drive_on_hills()
    told = calibrate([dataclasses.replace(hills, payload_kg=PAYLOAD_KG)], BASE)
    mass = told.estimates["effective_mass_kg"]
    assert mass.value == pytest.approx(CAR.effective_mass_kg, rel=0.005)
    assert mass.value == pytest.approx(result.estimates["effective_mass_kg"].value, rel=0.005)
    assert f"identified without the payloads the recordings carried (hills {PAYLOAD_KG:g} kg)" in told.notes
    rolling = told.estimates["rolling_resistance_n"]
    assert rolling.low < CAR.rolling_resistance_n < rolling.high
    for name in ("front_cornering_stiffness_npr", "rear_cornering_stiffness_npr"):
        assert told.estimates[name].value == pytest.approx(result.estimates[name].value, rel=0.02), name
    blind = calibrate([hills], BASE)  # 1,483 kg: the payload, less the part of its weight's pull it leaves out
    assert blind.estimates["effective_mass_kg"].value > CAR.effective_mass_kg + 0.5 * PAYLOAD_KG
    for bad in (-1.0, float("nan"), CAR.mass_kg + 1.0):
        assert "a payload must be finite" in _refusal([dataclasses.replace(hills, payload_kg=bad)])


def test_on_hills_the_load_transfer_is_fitted_on_the_tyres_force_not_the_acceleration():
    """The car with a CG height on the same hills: the load its turns move between the axles follows the torque
    it sends, m (a_x + g sin(theta)), not the acceleration the grade slows (docs/math.md 12.6). Told the grade,
    calibration gives the stiffnesses it gives on level ground; fitted on the measured acceleration alone, the
    grade's g sin(theta) would be read as braking in the turns (+40 % on both axles, a probe of 2026-11-28)."""
    base = {**BASE, "cg_height_m": CG_HEIGHT_M}
    level = calibrate([healthy_drive_with_load_transfer()], base)
    hills = calibrate([healthy_drive_on_hills_with_load_transfer()], base)
    for name in ("front_cornering_stiffness_npr", "rear_cornering_stiffness_npr", "effective_mass_kg"):
        assert hills.estimates[name].value == pytest.approx(level.estimates[name].value, rel=0.01), name


def test_a_stated_cg_height_the_recordings_do_not_show_is_refused_as_such(healthy):
    """The car without load transfer and a base stating a height: the fit with the term trades stiffness for it
    (docs/math.md 12.4); the refusal says the height is what does not fit, with both fits' figures."""
    reason = _refusal([healthy], {**BASE, "cg_height_m": CG_HEIGHT_M})
    assert reason.startswith("the recordings do not show the load transfer that cg_height_m = 0.55 m predicts")
    assert "leave cg_height_m out of the base" in reason
    without = float(reason.split("without it ")[1].split(" N/rad")[0])
    assert without == pytest.approx(80000.0, rel=0.05)


def test_refuses_too_little_driving(healthy):
    short = Drive(t=healthy.t[:2000], y=healthy.y[:2000], u=healthy.u[:2000], name="short")
    assert "too short: 20.0 s of driving" in _refusal([short])


def test_refuses_data_without_cornering():
    straight = simulated_drive("straight", 40.0, [(0, 10), (10, 20), (20, 10), (30, 20), (40, 20)], [])
    assert _refusal([straight]).startswith("no cornering")


def test_refuses_data_without_acceleration():
    steady = simulated_drive(
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
