"""The independent multi-body plant (edge_client/multibody.py): actuators, driver, drives, truth, CSV.

Only parameter sets 1 and 3 are simulated here; set 2 is kept for checks the
plant was not tuned on.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest

from edge_client import multibody as mb
from edge_client.faults import BiasFault, LossOfEffectivenessFault
from edge_client.recording import read_recording
from tests.tolerances import AMPLIFIED_ROUNDING_RTOL, FORMULA_EQUALITY_RTOL, LAST_BITS_ATOL

SETS = (1, 3)
#: Measured a_x against T / (R_w m_eff), relative.
ACCEL_REL_TOL = 0.03
#: a_y against v_x r in a steady turn, relative.
STEADY_TURN_REL_TOL = 0.03
#: Largest |v_y| in the steady turns tested [m/s].
STEADY_TURN_MAX_VY_MPS = 0.5
#: The road wheels against their target delayed by the servo lag [rad].
STEER_TRACKING_TOL_RAD = 3e-4
#: How far the simulated vehicle may overshoot the random drive's bounds (relative), transients included.
BOUNDS_OVERSHOOT = 0.05
NO_NOISE = mb.SensorNoise(speed_sigma_mps=0.0, yaw_rate_sigma_radps=0.0)


def _straight_torque(torque_nm: float, duration_s: float, speed_mps: float = 12.0) -> mb.OpenLoopDemand:
    u = np.zeros((round(duration_s / mb.SAMPLE_PERIOD_S), 2))
    u[:, 0] = torque_nm
    return mb.OpenLoopDemand(name="straight torque", initial_speed_mps=speed_mps, u=u)


@pytest.mark.parametrize("parameter_set", SETS)
@pytest.mark.parametrize("torque_nm", [800.0, -1200.0])
def test_constant_torque_accelerates_the_effective_mass(parameter_set, torque_nm):
    run = mb.simulate(_straight_torque(torque_nm, 3.0), parameter_set, seed=3)
    ref = mb.reference_values(parameter_set)
    settled = run.t >= 0.5  # after the tyre-slip and pitch transient
    measured_accel = np.polyfit(run.t[settled], run.y[settled, 0], 1)[0]
    expected = torque_nm / (ref["wheel_radius_m"] * ref["effective_mass_kg"])
    assert measured_accel == pytest.approx(expected, rel=ACCEL_REL_TOL)
    np.testing.assert_array_equal(run.torque_nm, run.u[:, 0])  # inside the power limit: nothing clipped
    np.testing.assert_array_equal(run.f, 0.0)


def test_steering_servo_follows_demand_plus_bias_fault():
    t = np.arange(400) * mb.SAMPLE_PERIOD_S
    u = np.zeros((t.size, 2))
    u[:, 1] = np.where(t >= 1.5, 0.02 * np.sin(np.pi * (t - 1.5)), 0.0)  # 0.063 rad/s at most: below the rate limit
    bias = BiasFault(channel="steer", onset_s=0.5, magnitude=0.01)
    run = mb.simulate(mb.OpenLoopDemand("sine steer", 15.0, u), 1, faults=[bias], noise=NO_NOISE)

    target = u[:, 1] + np.where(t >= 0.5, 0.01, 0.0)
    np.testing.assert_allclose(run.f[:, 1], target - u[:, 1], atol=LAST_BITS_ATOL)
    np.testing.assert_array_equal(run.f[:, 0], 0.0)
    # the bias alone (u_d = 0): a first-order step of time constant 1/k_steer
    lag_s = 1.0 / mb.STEER_SERVO_GAIN_PER_S
    step = run.steer_rad[(t >= 0.5) & (t < 1.5)]
    assert step[0] == 0.0
    assert 0.9 * 0.01 < step[round(3.0 * lag_s / mb.SAMPLE_PERIOD_S) + 1] < 0.01
    assert step[-1] == pytest.approx(0.01, abs=1e-6)
    # demand plus bias: the target delayed by the lag and half a sample of hold
    lag = round((lag_s + 0.5 * mb.SAMPLE_PERIOD_S) / mb.SAMPLE_PERIOD_S)
    moving = t >= 1.8
    error = run.steer_rad[moving] - np.roll(target, lag)[moving]
    assert np.abs(error).max() < STEER_TRACKING_TOL_RAD


@pytest.mark.parametrize("parameter_set", SETS)
@pytest.mark.parametrize(("speed_mps", "lateral_accel_mps2"), [(10.0, 4.0), (22.0, -6.0)])
def test_steady_turn(parameter_set, speed_mps, lateral_accel_mps2):
    drive = mb.steady_turn_drive(speed_mps, lateral_accel_mps2, 10.0)
    run = mb.simulate(drive, parameter_set, seed=1)
    steady = run.t >= 7.0
    v_x, v_y, r = (run.x_true[steady, i].mean() for i in range(3))
    a_y = run.a_y[steady].mean()
    assert a_y == pytest.approx(v_x * r, rel=STEADY_TURN_REL_TOL)
    assert a_y == pytest.approx(lateral_accel_mps2, rel=0.05)  # the driver holds the requested turn
    # the 2-DOF steady state with the tyres' cornering stiffness: v_y = r (b - m v_x^2 a / (2 C_r (a + b)))
    ref = mb.reference_values(parameter_set)
    a, b = ref["front_axle_distance_m"], ref["rear_axle_distance_m"]
    predicted = r * (b - ref["mass_kg"] * v_x**2 * a / (2.0 * ref["rear_cornering_stiffness_npr"] * (a + b)))
    assert abs(v_y) < STEADY_TURN_MAX_VY_MPS
    assert np.sign(v_y) == np.sign(predicted) != 0  # + at 10 m/s (kinematic), - at 22 m/s (rear slip)


def test_same_seed_same_run_other_seed_other_run():
    drive = mb.random_drive(5, 4.0)
    again = mb.random_drive(5, 4.0)
    for name in ("speed_mps", "accel_mps2", "curvature_1pm"):
        np.testing.assert_array_equal(getattr(drive, name), getattr(again, name))
    other = mb.random_drive(6, 4.0)
    assert not np.array_equal(drive.speed_mps, other.speed_mps)

    first, second, third = (mb.simulate(drive, 1, seed=seed) for seed in (11, 11, 12))
    for name in ("t", "y", "u", "x_true", "torque_nm", "steer_rad", "f", "a_x", "a_y"):
        np.testing.assert_array_equal(getattr(first, name), getattr(second, name))
    assert not np.array_equal(first.y, third.y)
    assert not np.array_equal(first.u, third.u)  # the driver sees the noise


def test_loss_of_effectiveness_scales_the_applied_torque():
    t = np.arange(800) * mb.SAMPLE_PERIOD_S
    speed = 8.0 + 1.0 * t  # accelerating all along, so T_d is far from zero
    drive = mb.Drive("ramp", speed_mps=speed, accel_mps2=np.full(t.size, 1.0), curvature_1pm=np.zeros(t.size))
    fault = LossOfEffectivenessFault(channel="torque", onset_s=1.0, rate_per_s=1000.0, alpha_min=0.6)
    run = mb.simulate(drive, 1, faults=[fault], seed=2)
    after = t >= 1.01
    assert run.u[after, 0].min() > 300.0
    np.testing.assert_allclose(run.torque_nm[after], 0.6 * run.u[after, 0], rtol=FORMULA_EQUALITY_RTOL)
    np.testing.assert_allclose(run.f[after, 0], -0.4 * run.u[after, 0], rtol=AMPLIFIED_ROUNDING_RTOL)
    np.testing.assert_array_equal(run.f[t < 1.0], 0.0)
    np.testing.assert_array_equal(run.f[:, 1], 0.0)
    # the speed loop makes up for the lost torque: the demand grows by about 1/0.6 and the speed error fades
    assert run.u[t >= 6.0, 0].mean() > 1.4 * run.u[(t > 0.5) & (t < 1.0), 0].mean()
    speed_error = np.abs(run.x_true[:, 0] - speed)
    assert speed_error[t >= 7.0].max() < 0.5 * speed_error.max()


def test_csv_round_trip(tmp_path):
    run = mb.simulate(mb.random_drive(3, 3.0), 3, seed=4)
    path = tmp_path / "multibody.csv"
    run.to_csv(path)
    recording = read_recording(path)
    np.testing.assert_array_equal(recording.t, run.t)
    np.testing.assert_array_equal(recording.y, run.y)
    np.testing.assert_array_equal(recording.u, run.u)
    header = path.read_text().splitlines()[0].split(",")
    assert header[:5] == ["t", "vx", "r", "torque", "steer"]
    data = np.loadtxt(path, delimiter=",", skiprows=1)
    np.testing.assert_array_equal(data[:, header.index("vy_true")], run.x_true[:, 1])
    np.testing.assert_array_equal(data[:, header.index("ay")], run.a_y)


@pytest.mark.parametrize("parameter_set", SETS)
def test_reference_values(parameter_set):
    from vehiclemodels.utils.tire_model import formula_lateral  # type: ignore[import-untyped]

    p = mb.vehicle_parameters(parameter_set)
    ref = mb.reference_values(parameter_set)
    assert ref["effective_mass_kg"] == pytest.approx(p.m + 4.0 * p.I_y_w / p.R_w**2, rel=1e-12)
    assert ref["effective_mass_kg"] > ref["mass_kg"]
    # static tyre loads: those of init_mb's initial state, F_z = K_zt z_u
    x0 = mb.initial_state(parameter_set, 0.0)
    loads = (x0[16] * p.K_zt, x0[21] * p.K_zt)
    assert mb.static_tyre_loads_n(parameter_set) == pytest.approx(loads, rel=1e-12)
    total = 2.0 * sum(loads)
    assert total == pytest.approx(p.m * mb.GRAVITY_MPS2, rel=1e-5)  # m = m_s + m_uf + m_ur up to rounding
    # the slope of the lateral magic formula at alpha = 0, zero camber, by central differences
    eps = 1e-6
    for load, name in zip(loads, ("front_cornering_stiffness_npr", "rear_cornering_stiffness_npr"), strict=True):
        slope = (formula_lateral(eps, 0.0, load, p.tire)[0] - formula_lateral(-eps, 0.0, load, p.tire)[0]) / (2 * eps)
        assert ref[name] == pytest.approx(abs(slope), rel=1e-6)
    profile = mb.base_profile(parameter_set)
    assert list(profile) == ["params"]
    assert set(profile["params"]) == {
        "mass_kg",
        "yaw_inertia_kgm2",
        "front_axle_distance_m",
        "rear_axle_distance_m",
        "wheel_radius_m",
        "cg_height_m",
    }
    assert profile["params"]["yaw_inertia_kgm2"] == p.I_z
    assert profile["params"]["cg_height_m"] == p.h_cg
    assert profile["params"]["wheel_radius_m"] == p.R_w


def test_a_variant_changes_the_vehicle_its_reference_values_and_its_data_sheet():
    p = mb.vehicle_parameters(1)
    assert mb.vehicle_parameters(1, mb.Variant("identity")) == p
    back = mb.Variant("CG back", cg_back_m=0.2)
    q = mb.vehicle_parameters(1, back)
    assert (q.a, q.b) == pytest.approx((p.a + 0.2, p.b - 0.2)) and q.m == p.m
    # the CG further back loads the rear tyres: their stiffness (p_ky1 F_z) follows the load
    front, rear = mb.static_tyre_loads_n(1)
    front_back, rear_back = mb.static_tyre_loads_n(1, back)
    assert front_back < front and rear_back > rear
    assert front_back + rear_back == pytest.approx(front + rear, rel=1e-12)
    ref, ref_back = mb.reference_values(1), mb.reference_values(1, back)
    assert ref_back["rear_cornering_stiffness_npr"] / ref["rear_cornering_stiffness_npr"] == pytest.approx(
        rear_back / rear, rel=1e-12
    )
    assert mb.base_profile(1, back)["params"]["front_axle_distance_m"] == pytest.approx(p.a + 0.2)
    soft = mb.Variant(
        "soft", tyre_stiffness_factor=0.8, cg_height_factor=1.25, brake_front_share=0.5, drive_front_share=0.4
    )
    r = mb.vehicle_parameters(3, soft)
    assert mb.reference_values(3, soft)["front_cornering_stiffness_npr"] == pytest.approx(
        0.8 * mb.reference_values(3)["front_cornering_stiffness_npr"], rel=1e-12
    )
    base = mb.vehicle_parameters(3)
    assert (r.h_cg, r.h_s, r.T_sb, r.T_se) == pytest.approx((1.25 * base.h_cg, 1.25 * base.h_s, 0.5, 0.4))
    assert mb.vehicle_parameters(3).tire.p_ky1 == base.tire.p_ky1  # the set's own parameters are left alone
    wet = mb.vehicle_parameters(3, mb.Variant("wet", road_friction=0.6))
    assert (wet.tire.p_dx1, wet.tire.p_dy1) == pytest.approx((0.6 * base.tire.p_dx1, 0.6 * base.tire.p_dy1))
    assert wet.tire.p_ky1 == base.tire.p_ky1 and mb.reference_values(3, mb.Variant("wet", road_friction=0.6)) == (
        mb.reference_values(3)
    )  # the slope at zero slip, which calibration identifies, is the dry road's


def test_a_variant_is_what_the_plant_simulates():
    """Softer tyres need more steering beyond the kinematic angle L r / v_x for the same turn (the understeer
    part grows as 1 / stiffness): the plant runs the variant, not the set."""
    drive = mb.steady_turn_drive(15.0, 4.0, 6.0)
    stock = mb.run_job(mb.MultibodyJob(drive=drive, parameter_set=1, seed=1))
    soft = mb.run_job(mb.MultibodyJob(drive=drive, parameter_set=1, seed=1, variant=mb.Variant("soft", 0.0, 1.0, 0.7)))
    p = mb.vehicle_parameters(1)
    steady = stock.t >= 4.0

    def understeer(run: mb.MultibodyRun) -> float:
        kinematic = (p.a + p.b) * run.x_true[steady, 2] / run.x_true[steady, 0]
        return float(np.mean(run.steer_rad[steady] - kinematic))

    assert soft.a_y[steady].mean() == pytest.approx(stock.a_y[steady].mean(), rel=0.05)  # the driver holds the turn
    assert understeer(stock) > 0 and understeer(soft) > 1.3 * understeer(stock)


@pytest.mark.parametrize(
    ("variant", "words"),
    [
        (mb.Variant("far back", cg_back_m=2.0), "off the wheelbase"),
        (mb.Variant("far forward", cg_back_m=-1.0), "off the wheelbase"),
        (mb.Variant("flat", cg_height_factor=0.0), "must be positive"),
        (mb.Variant("no grip", tyre_stiffness_factor=-1.0), "must be positive"),
        (mb.Variant("ice rink", road_friction=0.0), "must be positive"),
        (mb.Variant("nan road", road_friction=float("nan")), "finite"),
        (mb.Variant("nan", cg_back_m=float("nan")), "finite"),
        (mb.Variant("brakes", brake_front_share=1.5), "brake_front_share"),
        (mb.Variant("drive", drive_front_share=-0.1), "drive_front_share"),
    ],
)
def test_a_variant_that_leaves_no_vehicle_is_refused(variant, words):
    with pytest.raises(mb.MultibodyError, match=words):
        mb.vehicle_parameters(1, variant)


@pytest.mark.parametrize("bad", [0, 5, True, "1"])
def test_unknown_parameter_set_is_refused(bad):
    with pytest.raises(mb.MultibodyError, match="parameter_set must be one of"):
        mb.vehicle_parameters(bad)


def test_set_without_multibody_data_is_refused():
    with pytest.raises(mb.MultibodyError, match="parameter set 4 lacks multi-body parameters"):
        mb.reference_values(4)


def test_missing_package_names_it(monkeypatch):
    mb._library.cache_clear()
    monkeypatch.setitem(sys.modules, "vehiclemodels.init_mb", None)
    try:
        with pytest.raises(ImportError, match="install commonroad-vehicle-models"):
            mb._library()
    finally:
        mb._library.cache_clear()


def test_random_drive_stays_within_its_bounds():
    low, high, r_max, ay_max, ax_max = 8.0, 22.0, 0.5, 7.0, 3.0
    for seed in range(5):
        drive = mb.random_drive(seed, 120.0)
        assert drive.n_samples == 12_000
        assert low - 1e-9 <= drive.speed_mps.min() and drive.speed_mps.max() <= high + 1e-9
        assert np.abs(drive.yaw_rate_radps).max() <= r_max + 1e-9
        assert np.abs(drive.lateral_accel_mps2).max() <= ay_max + 1e-9
        assert np.abs(drive.accel_mps2).max() <= ax_max * 1.01
        assert np.abs(drive.lateral_accel_mps2).max() > 0.5 * ay_max  # it does turn hard
        assert np.ptp(drive.speed_mps) > 2.0  # and changes speed
    drive = mb.random_drive(1, 20.0)
    run = mb.simulate(drive, 1, seed=0)
    v_x, _, r = run.x_true.T
    margin = 1.0 + BOUNDS_OVERSHOOT
    assert low / margin <= v_x.min() and v_x.max() <= high * margin
    assert np.abs(r).max() <= r_max * margin
    assert np.abs(run.a_y).max() <= ay_max * margin
    assert np.abs(run.a_y).max() > 0.3 * ay_max
    np.testing.assert_array_equal(run.f, 0.0)  # healthy driving never reaches the power limit


def test_stopping_ends_the_run_with_a_clear_error():
    with pytest.raises(mb.MultibodyError, match=r"v_x fell to .* m/s at t = "):
        mb.simulate(_straight_torque(-1500.0, 4.0, speed_mps=6.0), 1)


def test_random_drive_rejects_a_speed_band_below_the_minimum():
    with pytest.raises(mb.MultibodyError, match="speed_range_mps"):
        mb.random_drive(0, 10.0, speed_range_mps=(3.0, 10.0))


def test_calibration_drive_is_natural_and_fixed():
    drive = mb.calibration_drive()
    assert drive.n_samples == 12_000
    np.testing.assert_array_equal(drive.speed_mps, mb.named_drive("calibration").speed_mps)
    assert drive.speed_mps.min() >= 10.0 - 1e-9 and drive.speed_mps.max() <= 20.0 + 1e-9
    assert np.abs(drive.yaw_rate_radps).max() <= 0.5
    assert np.abs(drive.accel_mps2).max() <= 3.0 * 1.01
    with pytest.raises(mb.MultibodyError, match="unknown drive"):
        mb.named_drive("moose test")


def test_parallel_runs_equal_serial_runs():
    jobs = [
        mb.MultibodyJob(drive=mb.random_drive(seed, 2.0), parameter_set=ps, seed=seed) for seed, ps in [(0, 1), (1, 3)]
    ]
    parallel = mb.simulate_many(jobs, workers=2)
    serial = mb.simulate_many(jobs, workers=1)
    for a, b in zip(parallel, serial, strict=True):
        np.testing.assert_array_equal(a.x_true, b.x_true)
        np.testing.assert_array_equal(a.y, b.y)
    assert [run.parameter_set for run in parallel] == [1, 3]


def test_a_vehicle_sliding_beyond_a_slippery_road_s_grip_stops_the_plant_with_a_clear_error():
    """Braking and accelerating in turns at 0.8 of the dry road's accelerations on a road of 0.6 of its friction:
    set 3 spins out within 15 s, a wheel's ground speed reaches zero (the MB divides its slip by it), and the
    plant says so instead of raising ZeroDivisionError."""
    drive = mb.combined_drive(4, 60.0, lateral_accel_mps2=(3.2, 4.4), max_accel_mps2=4.4)
    job = mb.MultibodyJob(drive=drive, parameter_set=3, seed=4, variant=mb.Variant("wet", road_friction=0.6))
    with pytest.raises(mb.MultibodyError, match=r"ground speed reached 0 at t = \d+\.\d\d s"):
        mb.run_job(job)


def test_on_a_slippery_road_braking_takes_the_same_share_of_the_lateral_grip_at_the_same_share_of_the_longitudinal():
    """road_friction 0.6 keeps the slope at zero slip, so the tyre reaches a share of its (lower) grip at 0.6 of
    the slips; the combined-slip weighting, which reads the slips themselves, is rescaled with them: at 0.6 of the
    dry road's slips the wet tyre gives 0.6 of the dry one's pure lateral force and loses the same share of it
    to braking, and the same share of its longitudinal force to cornering."""
    from vehiclemodels.utils import tire_model as tm  # the plant's own tyre functions

    dry, wet = mb.vehicle_parameters(3).tire, mb.vehicle_parameters(3, mb.Variant("wet", road_friction=0.6)).tire
    load_n = 4000.0
    for kappa, alpha in ((0.01, 0.02), (0.04, 0.05), (-0.03, 0.08)):
        shares = []
        for tyre, scale in ((dry, 1.0), (wet, 0.6)):
            k, a = scale * kappa, scale * alpha
            f_y, mu_y = tm.formula_lateral(a, 0.0, load_n, tyre)
            f_x = tm.formula_longitudinal(k, 0.0, load_n, tyre)
            lateral_kept = tm.formula_lateral_comb(k, a, 0.0, mu_y, load_n, f_y, tyre) / f_y
            longitudinal_kept = tm.formula_longitudinal_comb(k, a, f_x, tyre) / f_x
            shares.append((f_y / scale, lateral_kept, longitudinal_kept))
        (f_y_dry, lat_dry, lon_dry), (f_y_wet, lat_wet, lon_wet) = shares
        assert f_y_wet == pytest.approx(f_y_dry, rel=1e-9)
        assert lat_wet == pytest.approx(lat_dry, rel=1e-9) and lon_wet == pytest.approx(lon_dry, rel=1e-9)
        assert lat_dry < 1.0  # braking or driving does take lateral grip here
