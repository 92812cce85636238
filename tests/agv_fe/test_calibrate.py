"""`agv-fe calibrate`: recordings and a data sheet in, a profile out that synth, replay and the API accept."""

from __future__ import annotations

import csv
import json
import re

import pytest

from agv_fe.cli import main
from service.calibration import DECAY_RATE_CANDIDATES
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
    # each stage says when it ends: the identification, then one design per decay-rate candidate
    stages = [line for line in printed.splitlines() if re.match(r"^\s+\d+\.\d s  ", line)]
    assert "parameters identified from" in stages[0]
    assert [("observer designed" in line) for line in stages[1:]] == [True] * len(DECAY_RATE_CANDIDATES)
    assert f"({len(DECAY_RATE_CANDIDATES)} of {len(DECAY_RATE_CANDIDATES)})" in stages[-1]
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
    # its bias steps: half the gust's held steering response; the gust barely moves the torque estimate, no steps
    assert effectiveness["steer_jump_rad"] == pytest.approx(steer["gust_peak"] / 2.0, rel=0.01)
    assert summary["thresholds"]["torque"]["gust_peak"] < 3.0 * summary["thresholds"]["torque"]["sigma"]
    assert effectiveness["torque_jump_nm"] == 0.0
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
    # --payload-kg: one value for all recordings or one each, in their order
    again = root / "again.csv"
    again.write_text(rec.read_text())
    two = ["calibrate", str(rec), str(again), "--base", str(base), "--out", str(root / "x.json"), "--payload-kg"]
    assert main([*two, "0", "100", "200"]) == 2
    assert "--payload-kg: give one value, or one per recording (2), got 3" in capsys.readouterr().err
    assert main([*two, "-1"]) == 2
    assert "--payload-kg: expected kg >= 0, got -1.0" in capsys.readouterr().err
    assert main([*two, "0", "3000"]) == 3
    assert "again.csv: a payload must be finite, 0 kg or more and at most the vehicle's" in capsys.readouterr().err
    assert main([*two, "3000"]) == 3
    assert "healthy.csv: a payload must be" in capsys.readouterr().err
    assert not (root / "x.json").exists()


def test_calibrate_with_the_effectiveness_stage_sets_thresholds_from_its_totals(files, capsys):
    """--effectiveness: the profile enables the stage, and the fault thresholds come from the stage's total faults on
    the same drive (which vary more than the observer's own estimates), so replaying that drive with the stage
    raises no level, and the profile is one the service accepts."""
    from service.profiles import ProfileSpec

    root, rec, base = files
    plain, staged = root / "plain.json", root / "staged.json"
    plain_report, staged_report = root / "plain-report.json", root / "staged-report.json"
    assert main(["calibrate", str(rec), "--base", str(base), "--out", str(plain), "--report", str(plain_report)]) == 0
    args = ["calibrate", str(rec), "--base", str(base), "--out", str(staged), "--report", str(staged_report)]
    assert main([*args, "--effectiveness"]) == 0
    capsys.readouterr()
    doc, plain_doc = json.loads(staged.read_text()), json.loads(plain.read_text())
    assert doc["effectiveness"]["enabled"] is True
    assert doc["effectiveness"]["torque_sigma_nm"] == plain_doc["effectiveness"]["torque_sigma_nm"]
    staged_sigma = json.loads(staged_report.read_text())["thresholds"]["torque"]["sigma"]
    plain_sigma = json.loads(plain_report.read_text())["thresholds"]["torque"]["sigma"]
    assert staged_sigma > plain_sigma  # the totals of the stage, not the observer's estimates
    ProfileSpec.model_validate(doc)
    out = root / "staged-estimates.csv"
    assert main(["replay", str(rec), "--params", str(staged), "--out", str(out)]) == 0
    with out.open() as handle:
        rows = list(csv.DictReader(handle))
    assert "torque_alpha_hat" in rows[0]
    assert {r["torque_level"] for r in rows} == {"OK"} and {r["steer_level"] for r in rows} == {"OK"}
