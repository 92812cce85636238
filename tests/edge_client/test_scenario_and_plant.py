import json

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from edge_client.faults import BiasFault
from edge_client.library import BUILTIN_SCENARIOS, builtin_scenario
from edge_client.plant import PlantSimulator
from edge_client.scenario import Scenario, ScenarioError, SensorNoise, load_scenario
from synth.model import continuous_dynamics
from synth.params import OperatingBounds
from tests.tolerances import (
    FORMULA_EQUALITY_ATOL,
    NOISE_SIGMA_RTOL,
    PLANT_STEP_ATOL,
    REFERENCE_INTEGRATION_ATOL,
    REFERENCE_INTEGRATION_RTOL,
)


def test_one_plant_sample_matches_the_continuous_model():
    """The plant's 10 RK4 sub-steps over one sample equal a tight integration of eqs. (1)-(2)."""
    scenario = Scenario(
        name="check",
        duration_s=1.0,
        initial_speed_mps=12.0,
        initial_lateral_speed_mps=0.2,
        initial_yaw_rate_radps=0.1,
        faults=(BiasFault(channel="steer", magnitude=0.02),),
    )
    plant = PlantSimulator([scenario])
    sample = plant.step()
    p = scenario.vehicle

    def rhs(_t: float, x: np.ndarray) -> np.ndarray:
        return continuous_dynamics(x, sample.u[0], sample.wind[0], sample.f[0], p)

    ref = solve_ivp(
        rhs, (0.0, 0.01), sample.x[0], rtol=REFERENCE_INTEGRATION_RTOL, atol=REFERENCE_INTEGRATION_ATOL, method="DOP853"
    ).y[:, -1]
    np.testing.assert_allclose(plant.state[0, :3], ref, atol=PLANT_STEP_ATOL)
    assert sample.f[0, 1] == 0.02


def test_batch_of_vehicles_steps_independently():
    a = builtin_scenario("paper-1")
    b = builtin_scenario("paper-2")
    both = PlantSimulator([a, b])
    alone = PlantSimulator([b])
    for _ in range(300):
        s_both = both.step()
        s_alone = alone.step()
    np.testing.assert_allclose(s_both.x[1], s_alone.x[0], atol=FORMULA_EQUALITY_ATOL)


@pytest.mark.parametrize("name", sorted(BUILTIN_SCENARIOS))
def test_builtin_scenarios_stay_inside_the_design_bounds(name):
    plant = PlantSimulator([builtin_scenario(name)])
    b = OperatingBounds()
    states = np.array([plant.step().x[0] for _ in range(int(plant.n_samples[0]))])
    assert b.vx_min_mps <= states[:, 0].min() and states[:, 0].max() <= b.vx_max_mps
    assert b.vy_min_mps <= states[:, 1].min() and states[:, 1].max() <= b.vy_max_mps
    assert b.r_min_radps <= states[:, 2].min() and states[:, 2].max() <= b.r_max_radps


def test_sensor_noise_has_the_requested_sigma():
    s = builtin_scenario("paper-1", noise=SensorNoise(vx_sigma_mps=0.05, r_sigma_radps=0.005))
    plant = PlantSimulator([s])
    err = np.array([(lambda smp: smp.y[0] - smp.x[0, [0, 2]])(plant.step()) for _ in range(2000)])
    np.testing.assert_allclose(err.std(axis=0), [0.05, 0.005], rtol=NOISE_SIGMA_RTOL)


def test_sensor_bias_offsets_every_measurement_by_exactly_the_bias(tmp_path):
    """Noise fields of a scenario file, sigma 0: y_k = C x_k + bias, bit for bit, for each vehicle of a batch."""
    scenario_file = tmp_path / "biased.yaml"
    scenario_file.write_text(
        "name: biased\n"
        "duration_s: 4\n"
        "initial_speed_mps: 12\n"
        "speed_profile: [{t_s: 0, speed_mps: 12}, {t_s: 4, speed_mps: 16}]\n"
        "manoeuvres: [{kind: slalom, start_s: 0.5, duration_s: 3, amplitude_rad: 0.03, period_s: 2}]\n"
        "noise: {vx_sigma_mps: 0, r_sigma_radps: 0, vx_bias_mps: 0.3, r_bias_radps: -0.02}\n"
    )
    biased = load_scenario(scenario_file)
    assert biased.noise == SensorNoise(vx_bias_mps=0.3, r_bias_radps=-0.02)
    other = biased.model_copy(update={"noise": SensorNoise(vx_bias_mps=-0.5, r_bias_radps=0.01)})
    plant = PlantSimulator([biased, other, biased.model_copy(update={"noise": SensorNoise()})])
    bias = np.array([[0.3, -0.02], [-0.5, 0.01], [0.0, 0.0]])
    samples = [plant.step() for _ in range(int(plant.n_samples[0]))]
    for smp in samples:  # sigma 0 adds a signed zero: the offset is exact, no tolerance
        np.testing.assert_array_equal(smp.y, smp.x[:, [0, 2]] + bias)
    # the bias is on the sensor only: the true initial state is the scenario's
    np.testing.assert_array_equal(samples[0].x[0], [12.0, 0.0, 0.0])
    # the drive turned, so the yaw-rate bias was checked on a moving r, not only on r = 0
    assert np.abs(np.array([smp.x[0, 2] for smp in samples])).max() > 0.05


def test_scenario_file_round_trip_and_errors(tmp_path):
    good = tmp_path / "s.json"
    good.write_text(builtin_scenario("paper-2").model_dump_json())
    assert load_scenario(good) == builtin_scenario("paper-2")
    yaml_file = tmp_path / "s.yaml"
    yaml_file.write_text("name: y\nduration_s: 5\nfaults:\n  - kind: bias\n    channel: torque\n    magnitude: 10\n")
    assert load_scenario(yaml_file).faults[0].magnitude == 10
    bad = tmp_path / "bad.json"
    bad.write_text(
        json.dumps(
            {
                "name": "b",
                "duration_s": -3,
                "manoeuvres": [{"kind": "turn", "start_s": 0, "duration_s": 1, "ramp_s": 2}],
            }
        )
    )
    with pytest.raises(ScenarioError) as info:
        load_scenario(bad)
    message = str(info.value)
    assert "duration_s" in message and "manoeuvres.0" in message and "bad.json" in message


def _drive(seconds: float, **extra) -> Scenario:
    """Speed changes, a slalom and a torque bias, without sensor noise (each vehicle of a batch draws its own)."""
    from edge_client.scenario import Manoeuvre, SpeedPoint

    return Scenario(
        name="hilly",
        duration_s=seconds,
        initial_speed_mps=12.0,
        speed_profile=tuple(SpeedPoint(t_s=t, speed_mps=v) for t, v in ((0, 12), (4, 18), (8, 10))),
        manoeuvres=(Manoeuvre(kind="slalom", start_s=1, duration_s=6, amplitude_rad=0.03),),
        faults=(BiasFault(channel="torque", magnitude=120.0, onset_s=5.0),),
        seed=4,
        **extra,
    )


def _run(scenarios) -> tuple[np.ndarray, np.ndarray, list]:
    plant = PlantSimulator(scenarios)
    samples = [plant.step() for _ in range(int(plant.n_samples.max()))]
    return np.array([s.x for s in samples]), np.array([s.u for s in samples]), samples


def test_a_payload_on_hills_is_the_loaded_vehicle_pulled_back_by_its_weight():
    """A scenario's payload_kg and road_grade: the vehicle moves as the project's model of the loaded vehicle (more
    mass to accelerate, the rolling resistance in proportion to the weight) with the grade's pull, a torque fault
    included; the driver's feed-forward takes both, so the demanded torque is the loaded level-ground one plus
    R_w (M_v + payload) g sin(theta); the sample carries the grade, NaN for a vehicle on level ground."""
    from edge_client.scenario import RoadGrade
    from synth.params import STANDARD_GRAVITY_MPS2
    from tests.calibration_data import loaded

    payload = 300.0
    hills = RoadGrade(amplitude_rad=0.05, period_s=9.0, phase_rad=0.4)
    base = _drive(8.0)
    heavier = base.model_copy(update={"vehicle": loaded(base.vehicle, payload)})
    x, u, samples = _run([_drive(8.0, payload_kg=payload, road_grade=hills), base])  # one vehicle model a batch
    x_heavy, u_heavy, level = _run([heavier])
    # the scenario's payload is the loaded vehicle: the same motion, fault and all (to 0.1 mm/s: the load's drag
    # terms are held over each 10 ms sample, as in the model the service gives the observer)
    np.testing.assert_allclose(x[:, 0], x_heavy[:, 0], rtol=0, atol=1e-4)
    # the loaded vehicle's level torque plus the weight's pull on the grade: the same motion as on level ground
    grade = hills.grade(np.arange(len(samples)) * 0.01)
    p = base.vehicle
    pull = p.wheel_radius_m * (p.mass_kg + payload) * STANDARD_GRAVITY_MPS2 * np.sin(grade)
    np.testing.assert_allclose(u[:, 0, 0] - u_heavy[:, 0, 0], pull, rtol=0, atol=0.5)  # pull up to 870 N m
    assert np.abs(pull).max() > 800
    # ... which the empty vehicle does not follow: the payload moves the speed
    assert np.abs(x[:, 0, 0] - x[:, 1, 0]).max() > 0.05
    reported = np.array([s.grade for s in samples])
    np.testing.assert_array_equal(reported[:, 0], grade)
    assert np.isnan(reported[:, 1]).all()
    assert level[0].grade is None  # no vehicle on a grade: no grade column at all


def test_a_payload_heavier_than_the_vehicle_and_a_road_too_steep_are_refused():
    from edge_client.scenario import RoadGrade

    with pytest.raises(ValueError, match="payload_kg must be at most the vehicle's mass_kg"):
        _drive(1.0, payload_kg=5000.0)
    with pytest.raises(ValueError, match=r"must be at most 0\.3 rad"):
        RoadGrade(amplitude_rad=0.2, offset_rad=0.15)
    with pytest.raises(ValueError, match="amplitude_rad"):
        RoadGrade(amplitude_rad=-0.01)
