"""End to end: `agv-fe fleet` (its own process) against the estimation service through a router process.

The service comes from the ``estimation_service`` fixture (conftest.py), the one
place to swap in the real service.
"""

import json
import subprocess
import sys
import time

import numpy as np
import pytest

from edge_client.fleet_mix import DEFAULT_MIX
from tests.tolerances import MAX_ALARM_DELAY_S, SILENT_LOSS_PER_VEHICLE

pytestmark = pytest.mark.network


def fleet_command(router, tmp_path, *extra):
    return [
        sys.executable,
        "-m",
        "agv_fe",
        "fleet",
        "--connect",
        router.endpoint,
        "--summary-json",
        str(tmp_path / "summary.json"),
        "--log",
        str(tmp_path / "received.jsonl"),
        *extra,
    ]


def test_fleet_run_gets_estimates_for_every_vehicle_and_alarms_for_the_faulty_ones_only(
    router, estimation_service, tmp_path
):
    duration = 14.0
    out = subprocess.run(
        fleet_command(router, tmp_path, "--vehicles", "12", "--duration", str(duration), "--seed", "0"),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    summary = json.loads((tmp_path / "summary.json").read_text())
    vehicles = summary["vehicles"]
    assert len(vehicles) == 12
    n_samples = round(duration / 0.01)
    assert summary["sent"] == 12 * n_samples and summary["lost"] == 0
    faulty = [v for v in vehicles if v["onset_s"] is not None]
    healthy = [v for v in vehicles if v["onset_s"] is None]
    assert len(faulty) == 6 and len(healthy) == 6
    assert {v["kind"] for v in faulty} == {
        "torque_bias",
        "torque_loe",
        "steer_bias",
        "steer_sinusoidal",
        "intermittent",
    }
    for v in vehicles:
        # estimates for every vehicle, all the way to the end of the run
        assert v["estimates"] >= duration and v["last_estimate_seq"] >= n_samples - 100, v["vehicle_id"]
    for v in faulty:
        expected = "torque_fault" if v["injected"].startswith("T_f") else "steer_fault"
        assert v["fault_alarms"] == [expected], v
        assert 0 < v["first_alarm_after_onset_s"] < MAX_ALARM_DELAY_S, v
        assert v["false_alarms"] == 0
    for v in healthy:
        assert v["fault_alarms"] == [] and v["false_alarms"] == 0, v
        # realistic sensor noise (the fleet's default): the quiet estimates stay well under the 40 N m / 0.01 rad
        # WARN thresholds (measured peaks up to ~17 N m and 0.001 rad with the robust design)
        assert v["estimated_peak_quiet"][0] < 25.0 and v["estimated_peak_quiet"][1] < 0.005, v
    assert summary["false_alarms"] == 0
    # what the operator sees: progress lines, then the per-vehicle table
    assert "Hz sent" in out.stdout and "fleet summary" in out.stdout
    assert "faulty vehicles alarmed 6/6; false alarms 0" in " ".join(out.stdout.split())
    assert all(len(line) <= 80 for line in out.stdout.splitlines())
    # the log holds what came back: every alarm and the estimates
    kinds = [json.loads(line)["type"] for line in (tmp_path / "received.jsonl").read_text().splitlines()]
    assert kinds.count("alarm") == summary["alarms"] and kinds.count("estimate") == summary["estimates"]


def test_router_restart_during_a_fleet_run(router, estimation_service, tmp_path):
    """Kill the router 3 s into a 12 s run, restart it 1 s later: the fleet reconnects, the service keeps
    estimating, and the samples the 0.5 s buffer could not hold are counted as lost."""
    duration = 12.0
    n_samples = round(duration / 0.01)
    process = subprocess.Popen(
        fleet_command(
            router,
            tmp_path,
            "--vehicles",
            "6",
            "--duration",
            str(duration),
            "--buffer",
            "0.5",
            "--scenario-mix",
            "healthy=1,torque_bias=1",
        ),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    lines = []
    try:
        assert process.stdout is not None
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            line = process.stdout.readline()
            if not line:  # the fleet ended early
                pytest.fail(f"the fleet stopped before 3 s: {''.join(lines)}{process.communicate()[1]}")
            lines.append(line)
            first = line.split(maxsplit=1)[0] if line.strip() else ""
            if first.endswith("s") and first[:-1].replace(".", "", 1).isdigit() and float(first[:-1]) >= 3.0:
                break
        else:
            pytest.fail(f"the fleet did not reach 3 s: {''.join(lines)}")
        router.kill()
        time.sleep(1.0)
        router.start()
        stdout, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    output = "".join(lines) + stdout
    assert process.returncode == 0, stderr
    summary = json.loads((tmp_path / "summary.json").read_text())
    print("\n" + output)
    assert "link DOWN" in output  # the operator saw the outage
    assert summary["link_changes"] >= 2 * 6  # every vehicle lost its subscriber and found it again
    for v in summary["vehicles"]:
        # every sample is accounted for: sent, or dropped from the full buffer (lost)
        assert v["sent"] + v["lost"] == n_samples, v
        # an outage of ~1-2 s against a 0.5 s buffer loses samples, and they are counted
        assert 20 <= v["lost"] <= 500, v
        # the service kept estimating after the restart, to the end of the run
        assert v["last_estimate_seq"] >= n_samples - 100, v
        if getattr(estimation_service, "answers_every_sample", False):
            assert v["sent"] - SILENT_LOSS_PER_VEHICLE <= v["estimates"] <= v["sent"], v
    assert summary["lost"] == sum(v["lost"] for v in summary["vehicles"]) > 0
    # the gap does not make the service cry wolf
    assert summary["false_alarms"] == 0
    assert all(v["fault_alarms"] == [] for v in summary["vehicles"] if v["onset_s"] is None)
    assert f"lost {summary['lost']}" in " ".join(output.split())


def test_a_fleet_with_loads_on_hills_reports_both_and_raises_no_false_alarm(router, estimation_service, tmp_path):
    """--loads --hills: every vehicle carries a payload (reported on its payload key before its first sample) and
    drives hills (the grade sent with each sample); the service models both, so the faulty vehicles alarm on their
    channel and the healthy ones raise nothing, and it shows each vehicle's payload and last grade."""
    from edge_client.fleet_mix import build_fleet

    duration, n = 12.0, 8
    args = ["--vehicles", str(n), "--duration", str(duration), "--seed", "3", "--loads", "--hills"]
    out = subprocess.run(fleet_command(router, tmp_path, *args), capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["sent"] == n * round(duration / 0.01) and summary["lost"] == 0
    assert summary["payloads_reported"] == n and f"payloads reported {n}/{n};" in " ".join(out.stdout.split())
    members = {m.vehicle_id: m.scenario for m in build_fleet(DEFAULT_MIX, n, duration, seed=3, loads=True, hills=True)}
    for v in summary["vehicles"]:
        scenario = members[v["vehicle_id"]]
        assert scenario.payload_kg > 0 and scenario.road_grade is not None
        assert v["conditions"].startswith(f"{scenario.payload_kg:g} kg, hills ±"), v
        if v["onset_s"] is None:
            assert v["fault_alarms"] == [] and v["false_alarms"] == 0, v
        else:
            expected = "torque_fault" if v["injected"].startswith("T_f") else "steer_fault"
            assert v["fault_alarms"] == [expected] and v["false_alarms"] == 0, v
        shown = estimation_service.get(f"/vehicles/{v['vehicle_id']}").json()
        assert shown["payload_kg"] == scenario.payload_kg
        assert shown["grade_seq"] == shown["last_seq"]  # the grade at the last sample's time, t = seq * 10 ms
        at = np.array([shown["last_seq"] * 0.01])
        assert shown["grade_rad"] == pytest.approx(float(scenario.road_grade.grade(at)[0]), abs=1e-9)
    assert summary["false_alarms"] == 0
    # the table says what each vehicle carries and where it drives, still at 80 columns
    assert "kg, hills ±" in out.stdout and all(len(line) <= 80 for line in out.stdout.splitlines())
