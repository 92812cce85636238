"""`agv-fe calibrate`: recordings and a data sheet in, a profile out that synth, replay and the API accept."""

from __future__ import annotations

import csv
import json

import pytest

from agv_fe.cli import main
from tests.calibration_data import BASE, csv_text, healthy_drive


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    root = tmp_path_factory.mktemp("calibrate")
    rec = root / "healthy.csv"
    rec.write_text(csv_text(healthy_drive()))
    base = root / "base.json"
    base.write_text(json.dumps({"params": BASE, "alarms": {"raise_after_s": 0.5}}))
    return root, rec, base


def test_calibrate_writes_a_profile_that_synth_and_replay_accept(files, capsys):
    root, rec, base = files
    profile, report = root / "car.json", root / "report.json"
    assert main(["calibrate", str(rec), "--base", str(base), "--out", str(profile), "--report", str(report)]) == 0
    printed = capsys.readouterr().out
    for line in ("effective_mass_kg", "95 % confidence interval", "sensor noise", "fit residuals", "torque WARN"):
        assert line in printed
    doc = json.loads(profile.read_text())
    assert set(doc) >= {"params", "bounds", "design", "alarms"}
    assert doc["params"]["effective_mass_kg"] == pytest.approx(1290.0, rel=0.01)
    summary = json.loads(report.read_text())
    assert summary["thresholds"]["torque"]["warn"] == doc["alarms"]["torque_warn_nm"]
    # the default 800 N gust holds the steering WARN above what it makes the observer report
    assert summary["gust"] == {"force_n": 800.0, "duration_s": 2.0} and "in the gust" in printed
    steer = summary["thresholds"]["steer"]
    assert steer["gust_peak"] > 0.004 and steer["warn"] >= 1.25 * steer["gust_peak"]
    # the effectiveness stage gets the healthy estimates' RMS as its noise, and stays off until asked
    effectiveness = doc["effectiveness"]
    assert effectiveness["enabled"] is False
    assert effectiveness["torque_sigma_nm"] == pytest.approx(summary["thresholds"]["torque"]["sigma"], rel=0.01)
    # the same file is a --params profile: it designs the same gains and replays with its own thresholds
    gains = root / "gains.json"
    assert main(["synth", "--params", str(profile), "--out", str(gains)]) == 0
    assert json.loads(gains.read_text())["version"] == summary["gain_version"]
    out = root / "estimates.csv"
    assert main(["replay", str(rec), "--params", str(profile), "--gains", str(gains), "--out", str(out)]) == 0
    with out.open() as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 6000
    # its own healthy drive raises no fault level with the thresholds calibrated on it
    assert {r["torque_level"] for r in rows} == {"OK"} and {r["steer_level"] for r in rows} == {"OK"}


def test_calibrate_refuses_with_the_reason_and_exit_codes(files, capsys):
    root, rec, base = files
    short = root / "short.csv"
    short.write_text("\n".join(rec.read_text().splitlines()[:2001]) + "\n")
    assert main(["calibrate", str(short), "--base", str(base), "--out", str(root / "x.json")]) == 3
    assert "calibration refused: too short: 20.0 s of driving" in capsys.readouterr().err
    thin = root / "thin.json"
    thin.write_text(json.dumps({"params": {"mass_kg": 1200.0}}))
    assert main(["calibrate", str(rec), "--base", str(thin), "--out", str(root / "x.json")]) == 2
    assert "params must give front_axle_distance_m, rear_axle_distance_m, wheel_radius_m" in capsys.readouterr().err
    assert main(["calibrate", str(rec), "--base", str(base), "--out", str(root / "x.json"), "--gust", "-5"]) == 2
    assert "--gust must be a force of 0 N or more, got -5" in capsys.readouterr().err
    assert not (root / "x.json").exists()
