import numpy as np
import pytest

from edge_client.fleet_mix import MAX_STEER_FAULT_RAD, MIX_KINDS, mix_scenario
from edge_client.plant import PlantSimulator
from edge_client.random_drive import lateral_steady_state_gains, random_drive, steer_budget_rad
from edge_client.scenario import Manoeuvre, Scenario
from synth.params import OperatingBounds, VehicleParams
from tests.tolerances import STEADY_STATE_RTOL


@pytest.mark.parametrize("speed", [8.0, 20.0])
def test_steady_state_gains_match_a_long_plant_run(speed):
    """The linearised steady state predicts where the nonlinear plant settles under a small constant steer."""
    steer = 0.005
    scenario = Scenario(
        name="hold",
        duration_s=5.0,
        initial_speed_mps=speed,
        manoeuvres=(Manoeuvre(kind="turn", start_s=0.0, duration_s=5.0, amplitude_rad=steer, ramp_s=0.0),),
    )
    plant = PlantSimulator([scenario])
    for _ in range(int(plant.n_samples[0])):
        sample = plant.step()
    vy_gain, r_gain = lateral_steady_state_gains(VehicleParams(), float(sample.x[0, 0]))
    np.testing.assert_allclose(sample.x[0, 1:], [vy_gain * steer, r_gain * steer], rtol=STEADY_STATE_RTOL)


def test_steer_budget_shrinks_with_speed():
    p, b = VehicleParams(), OperatingBounds()
    assert steer_budget_rad(p, b, 30.0) < steer_budget_rad(p, b, 15.0) < steer_budget_rad(p, b, 8.0)


def test_random_drives_are_seeded():
    a = random_drive(np.random.default_rng(3), 60.0)
    b = random_drive(np.random.default_rng(3), 60.0)
    c = random_drive(np.random.default_rng(4), 60.0)
    assert a == b and a != c
    kinds = {m.kind for m in a.manoeuvres}
    assert kinds <= {"turn", "lane_change", "slalom"} and len(a.manoeuvres) >= 4


def test_random_fleet_vehicles_stay_inside_the_operating_bounds():
    """Every mix kind, 10 seeds each, 40 s: v_x in [5, 30], |v_y| <= 1.5, |r| <= 0.55, faults included."""
    scenarios = [
        mix_scenario(kind, f"v{seed}", 40.0, seed=1000 * i + seed)
        for i, kind in enumerate(MIX_KINDS)
        for seed in range(10)
    ]
    plant = PlantSimulator(scenarios)
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    steer_fault = 0.0
    for _ in range(int(plant.n_samples.max())):
        sample = plant.step()
        lo = np.minimum(lo, sample.x.min(axis=0))
        hi = np.maximum(hi, sample.x.max(axis=0))
        steer_fault = max(steer_fault, float(np.abs(sample.f[:, 1]).max()))
    b = OperatingBounds()
    assert b.vx_min_mps <= lo[0] and hi[0] <= b.vx_max_mps
    assert b.vy_min_mps <= lo[1] and hi[1] <= b.vy_max_mps
    assert b.r_min_radps <= lo[2] and hi[2] <= b.r_max_radps
    # the drives do use the room they have: not trivially straight
    assert max(-lo[2], hi[2]) > 0.1
    assert 0.02 <= steer_fault <= MAX_STEER_FAULT_RAD


def test_random_drive_rejects_a_speed_range_outside_the_bounds():
    with pytest.raises(ValueError, match="speed_range_mps"):
        random_drive(np.random.default_rng(0), 10.0, speed_range_mps=(3.0, 20.0))
    with pytest.raises(ValueError, match="no steering left"):
        random_drive(np.random.default_rng(0), 10.0, speed_range_mps=(8.0, 30.0), reserved_steer_rad=0.5)


def test_chunked_compilation_and_prefetch_change_nothing():
    """Signals compiled chunk by chunk (with manoeuvres outside the window skipped) equal one compilation,
    and a plant that prefetches the next chunk steps exactly like one that does not."""
    scenario = mix_scenario("steer_sinusoidal", "v", 25.0, seed=7)
    whole = scenario.compile(0.01)
    parts = [scenario.compile(0.01, start, 1000) for start in range(0, 2500, 1000)]
    for name in ("steer_demand", "speed_ref", "fault_add", "fault_gain"):
        np.testing.assert_array_equal(np.concatenate([getattr(p, name) for p in parts])[:2500], getattr(whole, name))
    scenarios = [mix_scenario(kind, f"v{i}", 25.0, seed=i) for i, kind in enumerate(MIX_KINDS)]
    eager = PlantSimulator(scenarios, prefetch=False)
    lazy = PlantSimulator(scenarios, prefetch=True)
    for _ in range(1100):  # across the first chunk boundary
        a, b = eager.step(), lazy.step()
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.u, b.u)
