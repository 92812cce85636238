"""`agv-fe replay` writes the fault channels' alarm levels, and they are the service's for the same stream.

The unit tests run the command in-process on a simulated recording with a torque bias; the end-to-end test
streams the same kind of recording through a real service (uvicorn, Zenoh on loopback, SQLite) with
`agv-fe publish-csv` and compares what came back, sample for sample, with the replay.
"""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from itertools import groupby
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agv_fe.cli import main
from agv_protocol.wire import Estimate, Measurement, vehicle_key
from edge_client.faults import BiasFault
from edge_client.recording import write_recording
from edge_client.scenario import REALISTIC_NOISE, Manoeuvre, Scenario
from edge_client.simulation import simulate_plant
from service.fleet import EngineConfig, FleetEngine
from service.profiles import AlarmThresholds, ProfileSpec
from synth.design import synthesize
from synth.options import DesignOptions
from synth.params import VehicleParams
from tests.service.helpers import T0_NS, WAIT_S, make_settings, running
from tests.tolerances import CSV_ROUND_TRIP_ATOL, CSV_ROUND_TRIP_RTOL

PERIOD_NS = 10_000_000
#: Torque bias of the unit recording [N m] and its onset [s].
BIAS_NM, ONSET_S = 150.0, 8.0
#: Thresholds of the 'custom' profile: higher and quicker than the defaults (40 / 80 N m held 0.5 s).
CUSTOM_ALARMS: dict[str, Any] = {"torque_warn_nm": 100.0, "torque_fault_nm": 140.0, "raise_after_s": 0.2}


def record(path: Path, scenario: Scenario) -> Path:
    """Simulate the scenario (100 Hz, noisy measurements) and write it as a recording."""
    plant = simulate_plant([scenario])
    write_recording(path, plant.t, plant.y[:, 0], plant.u[:, 0])
    return path


def read_rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        return list(csv.DictReader(handle))


def runs(levels: list[str]) -> list[str]:
    """The sequence of distinct levels: OK, OK, WARN, FAULT, FAULT -> OK, WARN, FAULT."""
    return [level for level, _ in groupby(levels)]


def transitions(rows: list[dict[str, str]], column: str) -> list[tuple[int, str]]:
    """(t_ns, new level) of every change of ``column``, t_ns = round(t * 1e9) as the replay counts time."""
    out, previous = [], "OK"
    for row in rows:
        if row[column] != previous:
            out.append((round(float(row["t"]) * 1e9), row[column]))
            previous = row[column]
    return out


def first_held(rows: list[dict[str, str]], column: str, threshold: float, alarms: AlarmThresholds) -> float | None:
    """Oracle, written from the documented rule alone: the first t [s] at which |column| >= threshold has held
    for raise_after_s, counting only samples from warmup_s after the start (None: never)."""
    t_ns = [round(float(r["t"]) * 1e9) for r in rows]
    warmup_ns, hold_ns = round(alarms.warmup_s * 1e9), round(alarms.raise_after_s * 1e9)
    since = None
    for t, row in zip(t_ns, rows, strict=True):
        if t - t_ns[0] < warmup_ns:
            continue
        if abs(float(row[column])) < threshold:
            since = None
            continue
        since = t if since is None else since
        if t - since >= hold_ns:
            return t / 1e9
    return None


def first_at_least(rows: list[dict[str, str]], column: str, level: str) -> float | None:
    order = {"OK": 0, "WARN": 1, "FAULT": 2}
    return next((float(r["t"]) for r in rows if order[r[column]] >= order[level]), None)


@pytest.fixture(scope="module")
def gains_file(tmp_path_factory, robust_gains_default):
    path = tmp_path_factory.mktemp("gains") / "gains.json"
    path.write_text(json.dumps(robust_gains_default.to_dict()))
    return path


@pytest.fixture(scope="module")
def bias_recording(tmp_path_factory):
    """14 s at 12 m/s, realistic sensor noise, a 150 N m torque bias from t = 8 s, no steering fault."""
    scenario = Scenario(
        name="torque-bias",
        duration_s=14.0,
        initial_speed_mps=12.0,
        manoeuvres=(Manoeuvre(kind="lane_change", start_s=2.0, duration_s=4.0, amplitude_rad=0.02),),
        faults=(BiasFault(channel="torque", onset_s=ONSET_S, magnitude=BIAS_NM),),
        noise=REALISTIC_NOISE,
        seed=3,
    )
    return record(tmp_path_factory.mktemp("rec") / "bias.csv", scenario)


def replay(capsys: pytest.CaptureFixture[str], recording: Path, out: Path, *extra: str) -> tuple[int, str, str]:
    code = main(["replay", str(recording), "--out", str(out), *extra])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_torque_bias_raises_warn_then_fault_after_the_onset_with_the_profiles_thresholds(
    tmp_path, capsys, gains_file, bias_recording
):
    code, out, err = replay(capsys, bias_recording, tmp_path / "default.csv", "--gains", str(gains_file))
    assert code == 0, err
    rows = read_rows(tmp_path / "default.csv")
    assert list(rows[0]) == [
        "t", "vx_hat", "vy_hat", "r_hat", "torque_fault_hat", "steer_fault_hat", "in_domain",
        "torque_level", "steer_level",
    ]  # fmt: skip
    torque = [r["torque_level"] for r in rows]
    assert runs(torque) == ["OK", "WARN", "FAULT"]
    first_warn = first_at_least(rows, "torque_level", "WARN")
    first_fault = first_at_least(rows, "torque_level", "FAULT")
    assert first_warn is not None and first_fault is not None and ONSET_S < first_warn < first_fault
    assert {r["steer_level"] for r in rows} == {"OK"}
    # the levels follow the documented rule on the written estimates (default thresholds: no --params)
    defaults = AlarmThresholds()
    assert first_warn == first_held(rows, "torque_fault_hat", defaults.torque_warn_nm, defaults)
    assert first_fault == first_held(rows, "torque_fault_hat", defaults.torque_fault_nm, defaults)
    # the summary: time at each level and the first time reached, per channel
    torque_line = next(line for line in out.splitlines() if line.strip().startswith("torque"))
    warn_s = torque.count("WARN") * 0.01
    assert f"WARN {warn_s:.2f} s (first at t = {first_warn:.2f} s)" in torque_line
    assert f"FAULT {torque.count('FAULT') * 0.01:.2f} s (first at t = {first_fault:.2f} s)" in torque_line
    steer_line = next(line for line in out.splitlines() if line.strip().startswith("steer"))
    assert "WARN 0.00 s (never), FAULT 0.00 s (never)" in steer_line

    # a profile file (the body of PUT /profiles/{name}) with other thresholds gives other levels
    profile = tmp_path / "custom.json"
    profile.write_text(json.dumps({"name": "custom", "description": "quick and high", "alarms": CUSTOM_ALARMS}))
    code, out, err = replay(
        capsys, bias_recording, tmp_path / "custom.csv", "--gains", str(gains_file), "--params", str(profile)
    )
    assert code == 0, err
    custom_rows = read_rows(tmp_path / "custom.csv")
    custom = AlarmThresholds(**CUSTOM_ALARMS)
    custom_warn = first_at_least(custom_rows, "torque_level", "WARN")
    assert custom_warn is not None and custom_warn != first_warn
    assert custom_warn == first_held(custom_rows, "torque_fault_hat", custom.torque_warn_nm, custom)
    assert first_at_least(custom_rows, "torque_level", "FAULT") == first_held(
        custom_rows, "torque_fault_hat", custom.torque_fault_nm, custom
    )
    assert runs([r["torque_level"] for r in custom_rows]) == ["OK", "WARN", "FAULT"]
    assert str(profile) in out  # the summary says whose thresholds these are
    # the estimates are the same: only the levels differ
    assert [r["torque_fault_hat"] for r in custom_rows] == [r["torque_fault_hat"] for r in rows]


def first_cusum_crossing(rows: list[dict[str, str]], column: str, threshold: float, sigma: float) -> float | None:
    """The CUSUM rule written out (service.fleet.cusum): 10-sample block means after the 3 s warm-up,
    g+- = max(0, g+- +- m / sigma - k), k = threshold / (2 sigma), the first block end with max(g+, g-) > h."""
    from service.fleet.cusum import blocks_per_false_alarm
    from synth.cusum import cusum_threshold

    k = threshold / (2.0 * sigma)
    h = cusum_threshold(round(k, 9), blocks_per_false_alarm(1.0, 0.1))
    t0 = round(float(rows[0]["t"]) * 1e9)
    warm = [r for r in rows if round(float(r["t"]) * 1e9) - t0 >= 3_000_000_000]
    g_plus = g_minus = 0.0
    for start in range(0, len(warm) - 9, 10):
        block = warm[start : start + 10]
        m = sum(float(r[column]) for r in block) / 10.0
        g_plus, g_minus = max(0.0, g_plus + m / sigma - k), max(0.0, g_minus - m / sigma - k)
        if max(g_plus, g_minus) > h:
            return float(block[-1]["t"])
    return None


def test_a_cusum_profile_replays_with_the_cusum_rule(tmp_path, capsys, gains_file, bias_recording):
    alarms = {"rule": "cusum", "torque_block_sigma_nm": 5.0, "steer_block_sigma_rad": 0.001}
    profile = tmp_path / "cusum.json"
    profile.write_text(json.dumps({"name": "cusum", "alarms": alarms}))
    code, out, err = replay(
        capsys, bias_recording, tmp_path / "cusum.csv", "--gains", str(gains_file), "--params", str(profile)
    )
    assert code == 0, err
    rows = read_rows(tmp_path / "cusum.csv")
    assert runs([r["torque_level"] for r in rows]) == ["OK", "WARN", "FAULT"]
    assert {r["steer_level"] for r in rows} == {"OK"}
    assert "a CUSUM on 0.1 s block means" in out
    first_warn = first_at_least(rows, "torque_level", "WARN")
    first_fault = first_at_least(rows, "torque_level", "FAULT")
    defaults = AlarmThresholds()
    assert first_warn == first_cusum_crossing(rows, "torque_fault_hat", defaults.torque_warn_nm, 5.0)
    assert first_fault == first_cusum_crossing(rows, "torque_fault_hat", defaults.torque_fault_nm, 5.0)
    # the same estimates through the threshold rule reach WARN later: it waits out its 0.5 s persistence
    held = first_held(rows, "torque_fault_hat", defaults.torque_warn_nm, defaults)
    assert first_warn is not None and held is not None and ONSET_S < first_warn < held


def test_the_ekf_replays_with_levels_too(tmp_path, capsys, gains_file, bias_recording):
    code, _, err = replay(
        capsys, bias_recording, tmp_path / "ekf.csv", "--gains", str(gains_file), "--estimator", "ekf"
    )
    assert code == 0, err
    rows = read_rows(tmp_path / "ekf.csv")
    first_warn = first_at_least(rows, "torque_level", "WARN")
    assert first_warn is not None and first_warn > ONSET_S
    assert runs([r["torque_level"] for r in rows])[-1] == "FAULT"


def test_builtin_profile_by_name_and_alarm_thresholds_refused_with_the_field(
    tmp_path, capsys, gains_file, bias_recording
):
    code, out, err = replay(
        capsys, bias_recording, tmp_path / "paper.csv", "--gains", str(gains_file), "--params", "paper"
    )
    assert code == 0, err
    assert "built-in profile 'paper'" in out
    # the paper's profile has the default thresholds
    code, _, err = replay(capsys, bias_recording, tmp_path / "none.csv", "--gains", str(gains_file))
    assert code == 0, err
    assert read_rows(tmp_path / "paper.csv") == read_rows(tmp_path / "none.csv")

    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"params": {}, "alarms": {"torque_warn_nm": 100.0, "torque_fault_nm": 100.0}}))
    code, _, err = replay(
        capsys, bias_recording, tmp_path / "bad.csv", "--gains", str(gains_file), "--params", str(bad)
    )
    assert code == 2
    assert "alarms: " in err and "torque_warn_nm must be below torque_fault_nm" in err
    assert not (tmp_path / "bad.csv").exists()
    # a field of the section is named by its path
    bad.write_text(json.dumps({"alarms": {"steer_warn_rad": -1.0}}))
    code, _, err = replay(
        capsys, bias_recording, tmp_path / "bad.csv", "--gains", str(gains_file), "--params", str(bad)
    )
    assert code == 2 and "alarms.steer_warn_rad" in err
    bad.write_text(json.dumps({"params": {}, "alarm": {}}))  # a misspelt section
    code, _, err = replay(
        capsys, bias_recording, tmp_path / "bad.csv", "--gains", str(gains_file), "--params", str(bad)
    )
    assert code == 2 and "unknown section(s) alarm" in err


# -- offline equals online -------------------------------------------------------------------------------

#: The thresholds of the end-to-end profile: short warm-up and persistence, so that 10 s show every transition.
E2E_ALARMS: dict[str, Any] = {
    "torque_warn_nm": 60.0,
    "torque_fault_nm": 100.0,
    "steer_warn_rad": 0.01,
    "steer_fault_rad": 0.02,
    "raise_after_s": 0.3,
    "clear_after_s": 0.5,
    "warmup_s": 1.0,
}


@pytest.mark.network
def test_replay_levels_equal_the_services_for_the_same_stream(tmp_path, capsys):
    """One profile file for the service and the replay; the service's active gains for the replay. Every alarm
    transition of the service (raised WARN / FAULT, cleared) on both fault channels happens at the replay's
    transition sample, and every estimate's level is the replay's, sample for sample."""
    scenario = Scenario(
        name="e2e",
        duration_s=10.0,
        initial_speed_mps=12.0,
        manoeuvres=(Manoeuvre(kind="slalom", start_s=1.0, duration_s=8.0, amplitude_rad=0.02, period_s=4.0),),
        faults=(
            BiasFault(channel="torque", onset_s=3.0, end_s=6.0, magnitude=150.0),
            BiasFault(channel="steer", onset_s=5.0, magnitude=0.03),
        ),
        noise=REALISTIC_NOISE,
        seed=5,
    )
    recording = record(tmp_path / "e2e.csv", scenario)
    n_samples = 1000
    body = {"description": "offline equals online", "alarms": E2E_ALARMS}
    profile = tmp_path / "profile.json"
    profile.write_text(json.dumps(body))
    settings = make_settings(tmp_path / "svc", {"default": body})
    with running(settings) as server:
        gains = server.get("/profiles/default/gains", params={"matrices": "true"}, headers=server.auth)
        assert gains.status_code == 200, gains.text
        (tmp_path / "gains.json").write_text(gains.text)
        published = subprocess.run(
            [
                sys.executable, "-m", "agv_fe", "publish-csv", str(recording), "--vehicle", "replay-1",
                "--connect", settings.zenoh.endpoint, "--log", str(tmp_path / "back.jsonl"),
            ],
            capture_output=True, text=True, timeout=WAIT_S,
        )  # fmt: skip
    assert published.returncode == 0, published.stderr
    assert f"sent {n_samples} of {n_samples} samples" in published.stdout

    code, _, err = replay(
        capsys, recording, tmp_path / "replay.csv", "--gains", str(tmp_path / "gains.json"), "--params", str(profile)
    )
    assert code == 0, err
    rows = read_rows(tmp_path / "replay.csv")

    back = [json.loads(line) for line in (tmp_path / "back.jsonl").read_text().splitlines()]
    estimates = sorted((b["message"] for b in back if b["type"] == "estimate"), key=lambda e: e["seq"])
    alarms = [b["message"] for b in back if b["type"] == "alarm"]
    assert [e["seq"] for e in estimates] == list(range(n_samples))  # every sample answered
    start_ns = estimates[0]["t_ns"]
    assert all(e["t_ns"] == start_ns + e["seq"] * PERIOD_NS for e in estimates)
    assert {e["gain_version"] for e in estimates} == {json.loads(gains.text)["version"]}
    # the same observer: the estimates agree to the replay's 9 written digits
    np.testing.assert_allclose(
        [e["torque_fault"] for e in estimates],
        [float(r["torque_fault_hat"]) for r in rows],
        rtol=CSV_ROUND_TRIP_RTOL,
        atol=CSV_ROUND_TRIP_ATOL,
    )

    # every alarm transition of each fault channel, at the sample the replay changes level
    assert not [a for a in alarms if a["kind"] == "out_of_domain"]  # so an estimate's level is the fault channels'
    for kind, column in (("torque_fault", "torque_level"), ("steer_fault", "steer_level")):
        service = [
            (a["t_ns"] - start_ns, a["level"] if a["state"] == "raised" else "OK") for a in alarms if a["kind"] == kind
        ]
        offline = transitions(rows, column)
        assert service == offline, kind
    torque_runs = runs([r["torque_level"] for r in rows])
    assert torque_runs == ["OK", "WARN", "FAULT", "WARN", "OK"]  # raised, escalated, lowered, cleared
    assert runs([r["steer_level"] for r in rows])[-1] == "FAULT"

    # and per sample: the level each estimate carries is the higher of the replay's two
    order = ["OK", "WARN", "FAULT"]
    offline_levels = [order[max(order.index(r["torque_level"]), order.index(r["steer_level"]))] for r in rows]
    assert [e["level"] for e in estimates] == offline_levels


def replay_with_files(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, recording: Path, gains: Any, body: dict[str, Any]
) -> list[dict[str, str]]:
    """Write ``gains`` and the profile ``body`` as files in tmp_path and replay ``recording`` with them (as
    `--gains` and `--params`); the rows it wrote."""
    (tmp_path / "gains.json").write_text(json.dumps(gains.to_dict()))
    (tmp_path / "profile.json").write_text(json.dumps(body))
    code, _, err = replay(
        capsys,
        recording,
        tmp_path / "replay.csv",
        "--gains",
        str(tmp_path / "gains.json"),
        "--params",
        str(tmp_path / "profile.json"),
    )
    assert code == 0, err
    return read_rows(tmp_path / "replay.csv")


def test_a_vehicle_with_a_steering_lag_replays_as_the_fleet_engine_steps_it(tmp_path, capsys):
    """With a steering actuator lag the observer state carries the actuator's angle, which starts on the first
    demand (a turn held from t = 0): the replay passes it, as the service's bank does. In-process, the fleet
    engine fed the same samples gives the replay's estimates, alarm transitions and levels."""
    params = {"steer_time_constant_s": 0.05}
    body = {"params": params, "design": {"switching": None}, "alarms": E2E_ALARMS}
    gains = synthesize(VehicleParams(**params), options=DesignOptions(switching=None))
    scenario = Scenario(
        name="lag",
        duration_s=8.0,
        initial_speed_mps=12.0,
        manoeuvres=(Manoeuvre(kind="turn", start_s=0.0, duration_s=8.0, amplitude_rad=0.02, ramp_s=0.0),),
        faults=(BiasFault(channel="steer", onset_s=3.0, magnitude=0.03),),
        noise=REALISTIC_NOISE,
        vehicle=VehicleParams(**params),
        seed=7,
    )
    recording = record(tmp_path / "lag.csv", scenario)
    rows = replay_with_files(capsys, tmp_path, recording, gains, body)
    assert float(rows[0]["steer_fault_hat"]) == 0.0 and abs(float(rows[0]["vx_hat"])) > 0  # a cold start

    estimates = assert_the_engine_gives_the_replay(body, gains, recording, rows)
    assert runs([r["steer_level"] for r in rows]) == ["OK", "WARN", "FAULT"]
    order = ["OK", "WARN", "FAULT"]
    assert [e.level for e in estimates] == [
        order[max(order.index(r["torque_level"]), order.index(r["steer_level"]))] for r in rows
    ]


def assert_the_engine_gives_the_replay(
    body: dict[str, Any], gains: Any, recording: Path, rows: list[dict[str, str]], payload_kg: float = 0.0
) -> list[Estimate]:
    """Feed the recording's samples (with the road grade where it has a grade column) to an in-process fleet engine
    with the profile ``body`` and ``gains`` (the vehicle carrying ``payload_kg``): its estimates are the replay's
    ``rows`` and its fault alarms change level at the replay's transition samples.
    Returns the engine's estimates."""
    engine = FleetEngine(EngineConfig())
    engine.add_profile("default", ProfileSpec.model_validate(body))
    engine.activate("default", gains)
    if payload_kg:
        engine.register("veh-1", "default")
        engine.set_payload("veh-1", payload_kg)
    estimates: list[Estimate] = []
    alarms = []
    for k, row in enumerate(read_rows(recording)):
        vx, r, torque, steer = (float(row[c]) for c in ("vx", "r", "torque", "steer"))
        grade = float(row["grade"]) if "grade" in row else None
        m = Measurement("veh-1", k, T0_NS + k * PERIOD_NS, vx, r, torque, steer, grade_rad=grade)
        result = engine.process([(vehicle_key("veh-1", "meas"), m.encode())])
        estimates += [Estimate.decode(doc) for _, doc in result.estimates]
        alarms += [change.event for change in result.alarms]
    assert [e.seq for e in estimates] == list(range(len(rows)))
    online = np.array([[e.vx, e.vy, e.r, e.torque_fault, e.steer_fault] for e in estimates])
    offline = np.array([[float(r[c]) for c in ("vx_hat", "vy_hat", "r_hat", "torque_fault_hat", "steer_fault_hat")]
                        for r in rows])  # fmt: skip
    np.testing.assert_allclose(online, offline, rtol=CSV_ROUND_TRIP_RTOL, atol=CSV_ROUND_TRIP_ATOL)
    if "torque_bias_hat" in rows[0]:  # the effectiveness stage's columns too
        stage = ("torque_bias", "steer_bias", "torque_alpha", "steer_alpha")
        online = np.array([[getattr(e, c) for c in stage] for e in estimates], dtype=float)
        offline = np.array([[float(r[f"{c}_hat"]) for c in stage] for r in rows])
        np.testing.assert_allclose(online, offline, rtol=CSV_ROUND_TRIP_RTOL, atol=CSV_ROUND_TRIP_ATOL)
    for kind, column in (("torque_fault", "torque_level"), ("steer_fault", "steer_level")):
        service = [(a.t_ns - T0_NS, a.level if a.state == "raised" else "OK") for a in alarms if a.kind == kind]
        assert service == transitions(rows, column), kind
    return estimates


def turn_with_a_torque_bias(tmp_path: Path, duration_s: float, amplitude_rad: float) -> Path:
    """A recording of 10 s at 12 m/s, a turn from 1.5 s lasting ``duration_s`` with ``amplitude_rad`` of steering,
    a 150 N m torque bias from 3 s (inside the turn), realistic noise."""
    scenario = Scenario(
        name="turn",
        duration_s=10.0,
        initial_speed_mps=12.0,
        manoeuvres=(
            Manoeuvre(kind="turn", start_s=1.5, duration_s=duration_s, amplitude_rad=amplitude_rad, ramp_s=0.5),
        ),
        faults=(BiasFault(channel="torque", onset_s=3.0, magnitude=150.0),),
        noise=REALISTIC_NOISE,
        seed=11,
    )
    return record(tmp_path / "turn.csv", scenario)


def test_outside_the_certified_domain_the_replay_holds_the_levels_as_the_engine_does(tmp_path, capsys):
    """A profile whose box holds yaw rates to 0.15 rad/s only, a turn beyond it, and a torque bias from inside
    the turn: neither the replay nor the engine judges the fault channels in the turn and for the warm-up after
    it; both raise the bias at the same sample, the warm-up after the last sample outside."""
    body = {"bounds": {"r_min_radps": -0.15, "r_max_radps": 0.15}, "design": {"switching": None}, "alarms": E2E_ALARMS}
    spec = ProfileSpec.model_validate(body)
    gains = synthesize(spec.params, spec.bounds, DesignOptions(switching=None))
    recording = turn_with_a_torque_bias(tmp_path, duration_s=4.0, amplitude_rad=0.06)
    rows = replay_with_files(capsys, tmp_path, recording, gains, body)
    outside = [float(r["t"]) for r in rows if r["in_domain"] in ("False", "0", "false")]
    assert outside and 1.5 < outside[0] < 3.0 < outside[-1] < 6.0  # the turn leaves the box around the onset
    first_warn = first_at_least(rows, "torque_level", "WARN")
    alarms = AlarmThresholds(**E2E_ALARMS)
    # the bias is above WARN from its onset, yet judged only from the warm-up after the last sample outside
    assert first_warn is not None and first_warn >= outside[-1] + alarms.warmup_s + alarms.raise_after_s - 0.011
    assert first_held(rows, "torque_fault_hat", alarms.torque_warn_nm, alarms) < outside[-1]  # the old rule's
    assert_the_engine_gives_the_replay(body, gains, recording, rows)


def test_a_recording_of_a_loaded_vehicle_replays_with_its_payload(tmp_path, capsys, gains_file):
    """The default vehicle carrying 100 kg, speeding up and slowing down, no fault: --payload-kg reads no torque
    fault where the replay without it reads the accelerations as one; a payload heavier than the vehicle is
    refused."""
    from edge_client.scenario import SpeedPoint

    p = VehicleParams()
    scenario = Scenario(
        name="loaded",
        duration_s=14.0,
        initial_speed_mps=10.0,
        vehicle=p.model_copy(update={"effective_mass_kg": p.effective_mass_kg + 100.0}),
        speed_profile=[SpeedPoint(t_s=t, speed_mps=v) for t, v in ((0, 10), (4, 16), (8, 9), (12, 14), (14, 14))],
        noise=REALISTIC_NOISE,
        seed=5,
    )
    recording = record(tmp_path / "loaded.csv", scenario)
    torque = {}
    for name, extra in (("blind", ()), ("told", ("--payload-kg", "100"))):
        out = tmp_path / f"{name}.csv"
        code, _, err = replay(capsys, recording, out, "--gains", str(gains_file), *extra)
        assert code == 0, err
        torque[name] = np.array([float(r["torque_fault_hat"]) for r in read_rows(out)])[300:]
    assert np.sqrt(np.mean(torque["blind"] ** 2)) > 3.0 * np.sqrt(np.mean(torque["told"] ** 2))
    code, _, err = replay(capsys, recording, tmp_path / "x.csv", "--gains", str(gains_file), "--payload-kg", "5000")
    assert code != 0 and "--payload-kg must be finite, >= 0 and at most the profile's mass_kg" in err


def test_a_recording_with_a_grade_column_replays_on_level_ground_as_the_service_steps_it(
    tmp_path, capsys, gains_file, robust_gains_default
):
    """The default vehicle on a road that climbs and descends, no fault, the grade in the recording's grade column:
    the replay reads no torque fault where the same recording without the column reads the weight's pull as one,
    and the engine fed the grade in its measurements (flag bit 1) gives the replay's estimates to the digit; so it
    does with the effectiveness stage, unloaded and carrying a payload (its bias and effectiveness columns too)."""
    from edge_client.faults import SinusoidalFault, fault_tables
    from synth.params import STANDARD_GRAVITY_MPS2

    p = VehicleParams()
    weight_torque = p.wheel_radius_m * p.mass_kg * STANDARD_GRAVITY_MPS2
    pull = SinusoidalFault(
        channel="torque", amplitude=0.01 * weight_torque, omega_radps=0.6, offset=-0.005 * weight_torque
    )
    scenario = Scenario(
        name="hills", duration_s=12.0, initial_speed_mps=12.0, faults=(pull,), noise=REALISTIC_NOISE, seed=6
    )
    plant = simulate_plant([scenario])
    grade = np.arcsin(-fault_tables((pull,), plant.t)[0][:, 0] / weight_torque)
    graded, level = tmp_path / "graded.csv", tmp_path / "level.csv"
    write_recording(graded, plant.t, plant.y[:, 0], plant.u[:, 0], {"grade": grade})
    write_recording(level, plant.t, plant.y[:, 0], plant.u[:, 0])
    torque = {}
    for name, recording in (("told", graded), ("blind", level)):
        out = tmp_path / f"{name}.csv"
        code, _, err = replay(capsys, recording, out, "--gains", str(gains_file))
        assert code == 0, err
        torque[name] = np.array([float(r["torque_fault_hat"]) for r in read_rows(out)])[300:]
    assert np.sqrt(np.mean(torque["blind"] ** 2)) > 3.0 * np.sqrt(np.mean(torque["told"] ** 2))
    assert_the_engine_gives_the_replay({}, robust_gains_default, graded, read_rows(tmp_path / "told.csv"))
    # with the effectiveness stage and a payload too: the observer on the level-ground torque, the stage on the
    # demanded one, both for the loaded vehicle, as the service's bank steps them
    body = {"effectiveness": {"enabled": True, "torque_sigma_nm": 6.0}}
    profile = tmp_path / "stage.json"
    profile.write_text(json.dumps(body))
    for payload in (0.0, 60.0):
        out = tmp_path / f"stage-{payload:g}.csv"
        args = ("--gains", str(gains_file), "--params", str(profile), "--payload-kg", str(payload))
        code, _, err = replay(capsys, graded, out, *args)
        assert code == 0, err
        rows = read_rows(out)
        assert "torque_alpha_hat" in rows[0]
        assert_the_engine_gives_the_replay(body, robust_gains_default, graded, rows, payload)


def grip_flags(recording: Path, limit_g: float) -> np.ndarray:
    """The samples of a recording beyond ``limit_g`` (combined and cornering) for service.fleet.grip.GripGate."""
    from service.fleet.grip import GripGate, GripLimits

    rows = read_rows(recording)
    gate, row = GripGate(1, GripLimits(limit_g, 0.2, limit_g)), np.zeros(1, dtype=np.intp)
    return np.array(
        [
            gate.update(
                row, np.array([float(r["vx"])]), np.array([float(r["r"])]), np.array([round(float(r["t"]) * 1e9)])
            )[0]
            for r in rows
        ]
    )


def test_beyond_the_grip_limit_the_replay_holds_the_levels_as_the_engine_does(tmp_path, capsys, robust_gains_default):
    """A turn at about 0.26 g with a profile whose grip limits are 0.2 g, and a torque bias from inside the turn:
    the replay judges the fault channels only from grip_hold_s after the last sample beyond the limit, says how
    long it held them and that the torque level was raised soon after the hold ended, and the engine fed the same
    samples does the same; without the gate the bias raises WARN inside the turn."""
    alarms = {**E2E_ALARMS, "grip_limit_g": 0.2, "grip_cornering_g": 0.2, "grip_hold_s": 0.5}
    recording = turn_with_a_torque_bias(tmp_path, duration_s=3.0, amplitude_rad=0.05)
    gated = replay_with_files(capsys, tmp_path, recording, robust_gains_default, {"alarms": alarms})
    code, out, err = replay(capsys, recording, tmp_path / "again.csv", "--params", str(tmp_path / "profile.json"))
    assert code == 0, err
    assert "beyond the grip limits (0.2 g combined while braking" in out and "0.2 g in any case)" in out
    assert "held there and for 0.5 s after" in out
    (tmp_path / "off").mkdir()
    ungated = replay_with_files(
        capsys, tmp_path / "off", recording, robust_gains_default, {"alarms": {**alarms, "grip_limit_g": None}}
    )
    warn_gated, warn_ungated = (
        first_at_least(gated, "torque_level", "WARN"),
        first_at_least(ungated, "torque_level", "WARN"),
    )
    assert warn_ungated is not None and 3.0 < warn_ungated < 4.0  # inside the turn
    # the last sample beyond the limit (the turn ends at 4.5 s), held 0.5 s after it, then raise_after_s
    t, flagged = [float(r["t"]) for r in gated], grip_flags(recording, 0.2)
    last = t[int(np.flatnonzero(flagged)[-1])]
    assert 3.5 < last < 4.8 and warn_gated is not None
    assert last + 0.5 + 0.3 - 0.011 <= warn_gated <= last + 0.5 + 0.3 + 0.011
    # the replay names the raise that came within the warm-up of the hold's end, and what to look at
    assert "levels raised within the warm-up (1 s) of the grip gate's hold ending:" in out
    assert f"torque reached WARN at t = {warn_gated:.2f} s, {warn_gated - last - 0.5:.2f} s after the hold" in out
    assert "steer reached WARN" not in out and "alarms.grip_hold_s (docs/math.md 12.4)" in out
    assert_the_engine_gives_the_replay({"alarms": alarms}, robust_gains_default, recording, gated)
