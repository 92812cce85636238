import json

import numpy as np
import pytest

from edge_client.faults import LossOfEffectivenessFault
from edge_client.fleet_mix import (
    ASSUMED_ALARM,
    DEFAULT_MIX,
    HILL_GRADE_RAD,
    LOAD_SHARE,
    MIX_KINDS,
    MixError,
    allocate,
    build_fleet,
    mix_scenario,
    parse_mix,
)
from edge_client.plant import PlantSimulator
from edge_client.scenario import ScenarioError, SensorNoise
from edge_client.simulation import estimate, observer_factory, run, simulate_plant


def test_parse_mix_normalises_weights():
    assert parse_mix("healthy=0.5,torque_bias=0.2,steer_bias=0.3") == pytest.approx(
        {"healthy": 0.5, "torque_bias": 0.2, "steer_bias": 0.3}
    )
    assert parse_mix(" healthy = 1 , intermittent = 3 ") == pytest.approx({"healthy": 0.25, "intermittent": 0.75})


@pytest.mark.parametrize(
    ("text", "names"),
    [
        ("healthy=0.5,torque_biass=0.5", ["torque_biass", "known kinds", "torque_bias"]),
        ("healthy", ["'healthy'", "KIND=WEIGHT"]),
        ("healthy=abc", ["healthy", "'abc'", "not a number"]),
        ("healthy=-1,steer_bias=1", ["healthy", ">= 0"]),
        ("healthy=nan", ["healthy", "finite"]),
        ("healthy=1,healthy=2", ["'healthy'", "twice"]),
        ("healthy=0,steer_bias=0", ["all weights are zero"]),
        ("", ["empty"]),
    ],
)
def test_bad_mixes_are_rejected_naming_the_part(text, names):
    with pytest.raises(MixError) as info:
        parse_mix(text)
    for name in names:
        assert name in str(info.value)


def test_allocation_is_exact_and_interleaved():
    kinds = allocate(parse_mix("healthy=0.5,torque_bias=0.2,steer_bias=0.3"), 10)
    assert [kinds.count(k) for k in ("healthy", "torque_bias", "steer_bias")] == [5, 2, 3]
    # any prefix is mixed: the first four already hold all three kinds
    assert set(kinds[:4]) == {"healthy", "torque_bias", "steer_bias"}
    assert len(allocate(parse_mix(DEFAULT_MIX), 7)) == 7


def test_fleet_is_reproducible_and_healthy_vehicles_are_truly_healthy():
    a = build_fleet(DEFAULT_MIX, 12, 30.0, seed=5)
    b = build_fleet(DEFAULT_MIX, 12, 30.0, seed=5)
    assert [m.scenario for m in a] == [m.scenario for m in b]
    assert [m.scenario for m in a] != [m.scenario for m in build_fleet(DEFAULT_MIX, 12, 30.0, seed=6)]
    assert len({m.vehicle_id for m in a}) == 12
    for member in a:
        if member.kind == "healthy":
            assert member.scenario.faults == () and member.scenario.gusts == ()
            assert member.fault_onset_s is None
        else:
            assert len(member.scenario.faults) == 1 and member.fault_onset_s is not None
            assert member.fault_onset_s >= 2.0


def test_every_fault_kind_is_large_enough_to_alarm():
    """After onset, each true fault exceeds twice the assumed alarm threshold for longer than the persistence.

    Four seeds of every faulty kind in one plant batch of 25 s.
    """
    members = [(kind, mix_scenario(kind, f"v{seed}", 25.0, seed=seed)) for kind in MIX_KINDS[1:] for seed in range(4)]
    plant = PlantSimulator([scenario for _, scenario in members])
    f = np.array([plant.step().f for _ in range(int(plant.n_samples.max()))])  # (K, nv, 2)
    thresholds = np.array([ASSUMED_ALARM.torque_threshold_nm, ASSUMED_ALARM.steer_threshold_rad])
    persistence = round(ASSUMED_ALARM.persistence_s / 0.01)
    for i, (kind, scenario) in enumerate(members):
        channel = 0 if scenario.faults[0].channel == "torque" else 1
        above = np.abs(f[:, i, channel]) > 2 * thresholds[channel]
        longest = max(len(run) for run in "".join("1" if a else "0" for a in above).split("0"))
        assert longest > persistence, (kind, scenario.faults)
        assert not np.any(f[:, i, 1 - channel]), "one channel per vehicle"


def test_loss_of_effectiveness_vehicles_drive_fast_enough():
    scenario = mix_scenario("torque_loe", "v", 60.0, seed=1)
    assert isinstance(scenario.faults[0], LossOfEffectivenessFault)
    assert min(p.speed_mps for p in scenario.speed_profile) >= 15.0


def test_scenario_file_mix_cycles_and_names_bad_entries(tmp_path):
    good = tmp_path / "mix.json"
    scenarios = [mix_scenario("healthy", "a", 10.0, seed=1), mix_scenario("steer_bias", "b", 10.0, seed=2)]
    good.write_text(json.dumps([s.model_dump(mode="json") for s in scenarios]))
    fleet = build_fleet(str(good), 5, 20.0, noise=SensorNoise(vx_sigma_mps=0.01))
    assert [m.kind for m in fleet] == ["file"] * 5
    assert fleet[2].scenario.manoeuvres == scenarios[0].manoeuvres
    assert fleet[3].scenario.faults == scenarios[1].faults
    assert all(m.scenario.duration_s == 20.0 and m.scenario.noise.vx_sigma_mps == 0.01 for m in fleet)
    assert fleet[2].scenario.seed != fleet[0].scenario.seed
    bad = tmp_path / "bad.yaml"
    bad.write_text("- name: ok\n  duration_s: 5\n- name: broken\n  duration_s: 5\n  faults:\n    - kind: bias\n")
    with pytest.raises(ScenarioError) as info:
        build_fleet(str(bad), 2, 10.0)
    message = str(info.value)
    assert "bad.yaml[1]" in message and "faults.0" in message and "channel" in message


def test_random_gusts_leave_healthy_vehicles_below_the_alarm_thresholds(paper_gains_order1):
    """With --gusts, healthy vehicles meet 300-800 N gusts; the observer's fault estimates stay under the
    assumed thresholds (a gust is a disturbance, not an actuator fault)."""
    scenarios = [mix_scenario("healthy", f"v{seed}", 30.0, seed=seed, gusts=True) for seed in range(4)]
    assert all(s.gusts for s in scenarios)
    assert all(300 <= abs(g.force_n) <= 800 for s in scenarios for g in s.gusts)
    # the drive is the same with or without gusts
    assert scenarios[0].manoeuvres == mix_scenario("healthy", "v0", 30.0, seed=0).manoeuvres
    result = run(scenarios, observer_factory(paper_gains_order1))
    assert np.abs(result.wind).max() >= 300
    settled = result.t >= 2.0
    peak = np.abs(result.f_hat[settled]).max(axis=(0, 1))
    assert peak[0] < ASSUMED_ALARM.torque_threshold_nm / 4
    assert peak[1] < ASSUMED_ALARM.steer_threshold_rad


def test_loads_and_hills_are_drawn_apart_and_an_observer_told_them_stays_quiet(paper_gains_order1):
    """--loads --hills: the drive and the fault are those without them (their own streams); a payload within
    LOAD_SHARE of the mass and grades within HILL_GRADE_RAD. The offline estimate is told what the vehicles
    report, as the service is: healthy vehicles stay quiet; not told, the payload and the grade's pull read as
    torque faults well above WARN."""
    import dataclasses

    plain = mix_scenario("torque_bias", "v0", 30.0, seed=5)
    both = mix_scenario("torque_bias", "v0", 30.0, seed=5, loads=True, hills=True)
    assert (both.manoeuvres, both.faults, both.speed_profile) == (plain.manoeuvres, plain.faults, plain.speed_profile)
    assert plain.payload_kg == 0.0 and plain.road_grade is None
    assert 0.0 < both.payload_kg <= LOAD_SHARE[1] * both.vehicle.mass_kg
    assert both.road_grade is not None and HILL_GRADE_RAD[0] <= both.road_grade.amplitude_rad <= HILL_GRADE_RAD[1]
    healthy = [mix_scenario("healthy", f"v{seed}", 30.0, seed=seed, loads=True, hills=True) for seed in range(4)]
    record = simulate_plant(healthy)
    settled = record.t >= 2.0
    told = estimate(record, observer_factory(paper_gains_order1))
    peak = np.abs(told.f_hat[settled]).max(axis=(0, 1))
    assert peak[0] < ASSUMED_ALARM.torque_threshold_nm / 2 and peak[1] < ASSUMED_ALARM.steer_threshold_rad
    empty = [s.model_copy(update={"payload_kg": 0.0}) for s in healthy]
    blind = estimate(dataclasses.replace(record, grade=None, scenarios=empty), observer_factory(paper_gains_order1))
    assert np.abs(blind.f_hat[settled, :, 0]).max() > 3.0 * ASSUMED_ALARM.torque_threshold_nm


def test_the_assumed_alarm_is_the_services_default():
    """The mix's fault sizes are set against the service's default WARN thresholds and persistence; the vehicle
    side states them rather than import the service, and this keeps the two equal."""
    from service.profiles import AlarmThresholds

    defaults = AlarmThresholds()
    assert (ASSUMED_ALARM.torque_threshold_nm, ASSUMED_ALARM.steer_threshold_rad, ASSUMED_ALARM.persistence_s) == (
        defaults.torque_warn_nm,
        defaults.steer_warn_rad,
        defaults.raise_after_s,
    )
