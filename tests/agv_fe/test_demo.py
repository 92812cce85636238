"""`agv-fe demo --duration 20` as a new user runs it: every injected fault alarmed, no healthy vehicle."""

import json
import subprocess
import sys


def test_demo_alarms_every_injected_fault_and_no_healthy_vehicle(tmp_path):
    summary_path = tmp_path / "summary.json"
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "agv_fe",
            "demo",
            "--duration",
            "20",
            "--data-dir",
            str(tmp_path / "data"),
            "--http-port",
            "0",
            "--zenoh-port",
            "0",
            "--summary-json",
            str(summary_path),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stdout + out.stderr
    summary = json.loads(summary_path.read_text())
    vehicles = summary["vehicles"]
    assert len(vehicles) == 20
    faulty = [v for v in vehicles if v["onset_s"] is not None]
    healthy = [v for v in vehicles if v["onset_s"] is None]
    assert len(faulty) >= 10 and len(healthy) >= 6
    for v in faulty:
        expected = "torque_fault" if v["injected"].startswith("T_f") else "steer_fault"
        assert v["fault_alarms"] == [expected], v
        assert v["first_alarm_after_onset_s"] is not None, v
    for v in healthy:
        assert v["fault_alarms"] == [], v
    assert summary["false_alarms"] == 0
    assert summary["lost"] == 0 and summary["estimates"] == summary["sent"]
    # what the user reads: where to look, then the per-vehicle report
    assert "web dashboard" in out.stdout and "/docs" in out.stdout
    assert f"faulty vehicles alarmed {len(faulty)}/{len(faulty)}; false alarms 0" in " ".join(out.stdout.split())
