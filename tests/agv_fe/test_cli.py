"""The `agv-fe` commands as a user runs them (console script, separate process)."""

import json
import subprocess
import sys

import numpy as np
import pytest

from tests.tolerances import REPLAY_STEER_FAULT_ATOL_RAD, REPLAY_TORQUE_FAULT_ATOL_NM


def agv_fe(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "agv_fe", *args], capture_output=True, text=True, timeout=600)


def test_decoupled_design_exits_non_zero_with_the_reason(tmp_path):
    out = agv_fe("synth", "--design", "paper-decoupled", "--out", str(tmp_path / "g.json"))
    assert out.returncode == 3
    assert "impossible" in out.stderr and "unobservable" in out.stderr and "r = 0.00 rad/s" in out.stderr
    assert not (tmp_path / "g.json").exists()


@pytest.fixture(scope="module")
def gains_file(tmp_path_factory, paper_gains):
    path = tmp_path_factory.mktemp("gains") / "gains.json"
    path.write_text(json.dumps(paper_gains.to_dict()))
    return path


def test_synth_prints_a_summary_and_writes_loadable_gains(tmp_path):
    out = agv_fe("synth", "--fault-order", "1", "--no-decay-rate", "--out", str(tmp_path / "g.json"))
    assert out.returncode == 0, out.stderr
    for word in ("design", "decay rate", "verification  passed", "time", "version"):
        assert word in out.stdout
    data = json.loads((tmp_path / "g.json").read_text())
    assert data["certificate"]["verified"] and data["options"]["fault_order"] == 1


def test_synth_robust_cost_flag_selects_the_h2_cost_form(tmp_path):
    out = agv_fe("synth", "--robust-cost", "h2", "--out", str(tmp_path / "g.json"))
    assert out.returncode == 0, out.stderr
    data = json.loads((tmp_path / "g.json").read_text())
    assert data["options"]["robust_cost"] == "h2" and data["certificate"]["verified"]
    assert any("'h2'" in note for note in data["certificate"]["notes"])


def test_switching_flag_designs_two_gain_sets_that_simulate_runs(tmp_path):
    out = agv_fe("synth", "--switching", "--out", str(tmp_path / "g.json"))
    assert out.returncode == 0, out.stderr
    assert "switched: fast and quiet gain sets" in out.stdout and "fast_set_h2_cost_bound" in out.stdout
    data = json.loads((tmp_path / "g.json").read_text())
    assert data["options"]["switching"]["threshold"] > 0 and "L_quiet" in data["matrices"]
    sim = agv_fe("simulate", "--scenario", "paper-2", "--noise", "realistic", "--gains", str(tmp_path / "g.json"),
                 "--out", str(tmp_path / "sim"))  # fmt: skip
    assert sim.returncode == 0, sim.stderr
    assert data["version"] in sim.stdout


def test_a_loaded_scenario_on_hills_simulates_told_and_replays_to_the_same_estimates(tmp_path, gains_file):
    """A scenario with payload_kg and road_grade: simulate estimates told both (as the service would) and writes
    the grade column; replay with --payload-kg reproduces the estimates, and the torque fault is the injected
    one at the vehicle's scale."""
    from edge_client.library import builtin_scenario

    scenario = builtin_scenario("paper-1").model_dump(mode="json")
    scenario |= {"payload_kg": 200.0, "road_grade": {"amplitude_rad": 0.05, "period_s": 12.0}}
    path = tmp_path / "loaded.json"
    path.write_text(json.dumps(scenario))
    sim = agv_fe("simulate", "--scenario", str(path), "--gains", str(gains_file), "--out", str(tmp_path / "sim"))
    assert sim.returncode == 0, sim.stderr
    summary = json.loads((tmp_path / "sim" / "summary.json").read_text())
    assert summary["payload_kg"] == 200.0 and summary["road_grade"]["amplitude_rad"] == 0.05
    assert summary["rmse_after_3s"]["T_f"] < 0.1 * summary["fault_amplitude"]["T_f"]
    a = np.genfromtxt(tmp_path / "sim" / "simulation.csv", delimiter=",", names=True)
    assert np.abs(a["grade"]).max() > 0.049
    rep = agv_fe(
        "replay", str(tmp_path / "sim" / "simulation.csv"), "--gains", str(gains_file), "--initial-state", "5,-1,0",
        "--payload-kg", "200", "--out", str(tmp_path / "rep.csv"),
    )  # fmt: skip
    assert rep.returncode == 0, rep.stderr
    b = np.genfromtxt(tmp_path / "rep.csv", delimiter=",", names=True)
    np.testing.assert_allclose(b["torque_fault_hat"], a["torque_fault_hat"], atol=REPLAY_TORQUE_FAULT_ATOL_NM)
    np.testing.assert_allclose(b["steer_fault_hat"], a["steer_fault_hat"], atol=REPLAY_STEER_FAULT_ATOL_RAD)


def test_bad_params_file_names_the_field(tmp_path):
    params = tmp_path / "p.json"
    params.write_text(json.dumps({"params": {"mass_kg": -5}, "bounds": {"vx_min_mps": 40}}))
    out = agv_fe("synth", "--params", str(params), "--out", str(tmp_path / "g.json"))
    assert out.returncode == 2
    assert "params.mass_kg" in out.stderr


def test_simulate_then_replay_reproduces_the_estimates(tmp_path, gains_file):
    sim = agv_fe("simulate", "--scenario", "paper-1", "--gains", str(gains_file), "--out", str(tmp_path / "sim"))
    assert sim.returncode == 0, sim.stderr
    for name in ("simulation.csv", "states.png", "faults.png"):
        assert (tmp_path / "sim" / name).stat().st_size > 10_000
    summary = json.loads((tmp_path / "sim" / "summary.json").read_text())
    assert summary["rmse_after_3s"]["T_f"] < 0.1 * summary["fault_amplitude"]["T_f"]
    assert "T_f" in sim.stdout and "delta_f" in sim.stdout
    rep = agv_fe(
        "replay",
        str(tmp_path / "sim" / "simulation.csv"),
        "--gains",
        str(gains_file),
        "--initial-state",
        "5,-1,0",
        "--out",
        str(tmp_path / "rep.csv"),
    )
    assert rep.returncode == 0, rep.stderr
    a = np.genfromtxt(tmp_path / "sim" / "simulation.csv", delimiter=",", names=True)
    b = np.genfromtxt(tmp_path / "rep.csv", delimiter=",", names=True)
    assert b.dtype.names == (
        "t", "vx_hat", "vy_hat", "r_hat", "torque_fault_hat", "steer_fault_hat", "in_domain",
        "torque_level", "steer_level",
    )  # fmt: skip
    np.testing.assert_allclose(b["torque_fault_hat"], a["torque_fault_hat"], atol=REPLAY_TORQUE_FAULT_ATOL_NM)
    np.testing.assert_allclose(b["steer_fault_hat"], a["steer_fault_hat"], atol=REPLAY_STEER_FAULT_ATOL_RAD)


def test_replay_names_the_bad_row(tmp_path, gains_file):
    bad = tmp_path / "bad.csv"
    bad.write_text("t,vx,r,torque,steer\n0,10,0,50,0\n0.01,inf,0,50,0\n")
    out = agv_fe("replay", str(bad), "--gains", str(gains_file), "--out", str(tmp_path / "o.csv"))
    assert out.returncode == 2
    assert "line 3" in out.stderr and "'vx' is not finite" in out.stderr


def test_version_is_the_installed_distributions():
    from importlib.metadata import version

    out = agv_fe("--version")
    assert out.returncode == 0 and out.stdout.strip() == f"agv-fe {version('agv-fault-estimator')}"


def test_replay_checks_its_input_before_designing_gains(tmp_path, monkeypatch, capsys):
    """A missing or broken recording is reported at once, not after a design of several seconds."""
    from agv_fe import common
    from agv_fe.cli import build_parser, main

    def no_design(*args, **kwargs):
        raise AssertionError("a design was started before the input was checked")

    # every command module is imported before the patch: one that imports the name (agv_fe.commands.synth) would
    # otherwise keep the stand-in for the rest of the session, and a later test's `agv-fe synth` would fail
    build_parser()
    monkeypatch.setattr(common, "synthesize_or_fail", no_design)
    assert main(["replay", str(tmp_path / "missing.csv"), "--out", str(tmp_path / "o.csv")]) == 2
    assert "missing.csv" in capsys.readouterr().err
    bad = tmp_path / "bad.csv"
    bad.write_text("t,vx,r,torque,steer\n0,10,0,50,0\n0.01,nan,0,50,0\n")
    assert main(["replay", str(bad), "--out", str(tmp_path / "o.csv")]) == 2
    assert "line 3" in capsys.readouterr().err


def test_a_failed_design_says_what_to_try():
    from agv_fe.common import VehicleProfileFile, design_hints
    from synth.options import DesignOptions
    from synth.params import OperatingBounds, VehicleParams

    profile = VehicleProfileFile(VehicleParams(), OperatingBounds(vx_min_mps=0.5, vx_max_mps=80.0), {})
    hints = design_hints(profile, DesignOptions())
    assert hints.startswith("What to try:")
    assert "v_x 0.5 to 80 m/s (a ratio of 160)" in hints and "bounds.vx_min_mps" in hints
    assert "design.robust_decay_rate closer to 1 (now 0.994)" in hints
