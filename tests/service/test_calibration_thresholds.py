"""The thresholds calibration sets: a Gaussian tail for the false-alarm rate, the held peak, a wind gust, the floor."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.stats

from service.calibration import (
    FAULT_OVER_WARN,
    PEAK_MARGIN,
    REQUIRED_SHARE_FLOOR,
    fault_thresholds,
    gust_drives,
    held_peaks,
    observer_stepper,
)
from service.fleet.alarms import OK, WARN, FaultLevels
from service.profiles import AlarmThresholds
from synth.gains import ObserverGains
from synth.model import continuous_matrices, state_matrix
from synth.params import OperatingBounds, VehicleParams

KW = {"sample_period_s": 0.01, "persistence_s": 0.5}


def test_warn_is_the_gaussian_tail_for_the_stated_false_alarm_rate():
    estimate = np.random.default_rng(0).normal(0.0, 5.0, 120_000)  # 20 minutes of a healthy estimate
    t = fault_thresholds(estimate, 30.0, false_alarms_per_1000_h=1.0, required_bias=60.0, **KW)
    # one chance per 0.5 s window: 7,200 an hour; 1 per 1,000 h -> P(|e| >= WARN) = 1e-3 / 7200
    z = scipy.stats.norm.isf(1e-3 / 7200 / 2)
    assert t.sigma == pytest.approx(5.0, rel=0.01)
    assert t.warn == pytest.approx(z * t.sigma, rel=2e-3) and t.warn >= z * t.sigma
    assert t.fault == pytest.approx(FAULT_OVER_WARN * t.warn, rel=2e-3)
    assert t.smallest_fault_bias == pytest.approx(t.fault + 2 * t.sigma, rel=2e-3)
    assert not t.hides_required_fault
    # ten times more false alarms allowed: a lower threshold
    looser = fault_thresholds(estimate, 30.0, false_alarms_per_1000_h=10.0, required_bias=60.0, **KW)
    assert looser.warn < t.warn


def test_a_held_excursion_and_the_required_fault_floor_raise_warn():
    estimate = np.random.default_rng(1).normal(0.0, 1.0, 60_000)
    estimate[1000:1060] = 12.0  # 0.6 s held at 12: longer than the persistence time
    t = fault_thresholds(estimate, float("nan"), false_alarms_per_1000_h=1.0, required_bias=10.0, **KW)
    assert t.healthy_peak >= 11.5 and t.warn >= PEAK_MARGIN * t.healthy_peak
    quiet = np.random.default_rng(2).normal(0.0, 0.0005, 60_000)
    floor = fault_thresholds(quiet, float("nan"), false_alarms_per_1000_h=1.0, required_bias=0.02, **KW)
    assert floor.warn == pytest.approx(REQUIRED_SHARE_FLOOR * 0.02) and not floor.hides_required_fault


def test_a_threshold_that_hides_the_required_fault_is_said():
    estimate = np.random.default_rng(3).normal(0.0, 30.0, 60_000)
    t = fault_thresholds(estimate, 10.0, false_alarms_per_1000_h=1.0, required_bias=88.0, **KW)
    assert t.smallest_fault_bias > 88.0 and t.hides_required_fault


def test_a_stated_wind_gust_sets_the_warn_floor_it_needs():
    quiet = np.random.default_rng(4).normal(0.0, 0.0004, 60_000)
    t = fault_thresholds(quiet, float("nan"), false_alarms_per_1000_h=1.0, required_bias=0.02, gust_peak=0.0053, **KW)
    assert t.set_by == "gust" and t.warn >= PEAK_MARGIN * 0.0053 and t.gust_peak == 0.0053
    without = fault_thresholds(quiet, float("nan"), false_alarms_per_1000_h=1.0, required_bias=0.02, **KW)
    assert without.set_by == "floor" and without.warn < t.warn
    assert gust_drives(VehicleParams(), OperatingBounds(), 0.0) == []
    with pytest.raises(ValueError, match="gust"):
        gust_drives(VehicleParams(), OperatingBounds(), float("nan"))


def test_a_gust_shows_as_its_steady_state_steering_equivalent_and_the_floor_rides_it_through(
    robust_gains_default: ObserverGains,
) -> None:
    gains = robust_gains_default
    p = gains.params
    drives = gust_drives(p, gains.bounds, 800.0)
    assert len(drives) == 6
    for drive, sign in zip(drives, [1.0, -1.0] * 3, strict=True):
        before = drive.t < 0.5
        # straight and steady before the gust: the drive torque holds the speed
        assert np.ptp(drive.y[before], axis=0).max() < 1e-9
        assert np.sign(drive.y[np.argmax(np.abs(drive.y[:, 1])), 1]) == sign
    # the linear model's steady state: the steering fault whose yaw rate equals the gust's (speed-independent)
    cm = continuous_matrices(p)
    equivalents = []
    for v in (gains.bounds.vx_min_mps, gains.bounds.vx_max_mps):
        a = state_matrix(np.array([v, 0.0, 0.0]), p)[1:, 1:]
        r_gust = -np.linalg.solve(a, 800.0 * cm.D_v[1:, 0])[1]
        r_steer = -np.linalg.solve(a, cm.F_v[1:, 1])[1]
        equivalents.append(r_gust / r_steer)
    peaks = held_peaks(observer_stepper(gains), drives, 0.5)
    assert peaks[1] == pytest.approx(max(equivalents), rel=0.03)
    # the alarm levels: a WARN from the required-fault floor alone is raised by the gust; the gust floor is not
    thresholds = {
        name: fault_thresholds(
            np.zeros(100), float("nan"), false_alarms_per_1000_h=1.0, required_bias=0.02, gust_peak=gust, **KW
        )
        for name, gust in (("floor", 0.0), ("gust", float(peaks[1])))
    }
    assert thresholds["floor"].warn < peaks[1] < thresholds["gust"].warn
    y = np.stack([d.y for d in drives], axis=1)
    u = np.stack([d.u for d in drives], axis=1)
    for name, t in thresholds.items():
        alarms = AlarmThresholds(warmup_s=0.0, steer_warn_rad=t.warn, steer_fault_rad=t.fault)
        levels = FaultLevels(len(drives), alarms)
        rows = np.arange(len(drives))
        observer = observer_stepper(gains)(y[0], u[0])
        highest = np.full(len(drives), OK)
        for k in range(y.shape[0]):
            f_hat = np.asarray(observer.step(y[k], u[k]).faults)
            levels.update(rows, f_hat, np.full(len(drives), k * 10_000_000, dtype=np.int64))
            highest = np.maximum(highest, levels.steer.level[rows])
        if name == "floor":
            assert (highest >= WARN).all()
        else:
            assert (highest == OK).all()


@pytest.mark.parametrize("loaded", [False, True], ids=["empty", "loaded"])
def test_a_graded_drive_is_replayed_for_the_thresholds_as_the_service_steps_it(loaded):
    """The healthy minute on hills with its grade (the project's model), by the car empty or carrying a fifth of
    its mass told to both: the threshold replay with the effectiveness stage gives the fleet engine's total torque
    and steering faults for the same samples sent with their grade, to the digit (the observer on the level-ground
    torque of the car without the payload, the stage on the torque sent without it, the torque fault scaled back
    by rho); the same minute without its grade reads the weight's pull as a torque fault."""
    import dataclasses

    from agv_protocol.wire import Estimate, Measurement, vehicle_key
    from service.calibration import healthy_fault_estimates
    from service.fleet import EngineConfig, FleetEngine
    from service.profiles import ProfileSpec
    from synth.design import synthesize
    from synth.options import DesignOptions, EffectivenessOptions
    from tests.calibration_data import CAR, PAYLOAD_KG, healthy_drive_on_hills, loaded_drive_on_hills

    hills = dataclasses.replace(loaded_drive_on_hills(), payload_kg=PAYLOAD_KG) if loaded else healthy_drive_on_hills()
    assert hills.grade is not None
    gains = synthesize(CAR, options=DesignOptions())
    stage = EffectivenessOptions(enabled=True, torque_sigma_nm=6.0)
    replayed = healthy_fault_estimates(gains, [hills], 0.0, stage)
    engine = FleetEngine(EngineConfig())
    engine.add_profile("hills", ProfileSpec(params=CAR, effectiveness=stage))
    engine.activate("hills", gains)
    engine.register("car", "hills")
    if loaded:
        engine.set_payload("car", PAYLOAD_KG)
    online = []
    for k in range(len(hills)):
        vx, r = hills.y[k]
        torque, steer = hills.u[k]
        grade = float(hills.grade[k])
        m = Measurement("car", k, 1_000_000_000 + k * 10_000_000, vx, r, torque, steer, grade_rad=grade)
        for _, doc in engine.process([(vehicle_key("car", "meas"), m.encode())]).estimates:
            e = Estimate.decode(doc)
            online.append([e.torque_fault, e.steer_fault])
    np.testing.assert_allclose(np.array(online), replayed, rtol=1e-9, atol=1e-9)
    blind = healthy_fault_estimates(gains, [dataclasses.replace(hills, grade=None)], 0.0)
    told = healthy_fault_estimates(gains, [hills], 0.0)
    late = slice(300, None)
    assert np.sqrt(np.mean(blind[late, 0] ** 2)) > 5.0 * np.sqrt(np.mean(told[late, 0] ** 2))
