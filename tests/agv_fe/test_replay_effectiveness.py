"""`agv-fe replay --effectiveness`: the total faults, and the bias and effectiveness columns beside them."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from agv_fe.cli import main
from edge_client.faults import LossOfEffectivenessFault
from edge_client.recording import OUTPUT_COLUMNS, write_recording
from edge_client.scenario import REALISTIC_NOISE, Scenario, SpeedPoint
from edge_client.simulation import simulate_plant
from tests.tolerances import CSV_PRODUCT_ATOL_NM

EXTRA = ("torque_bias_hat", "steer_bias_hat", "torque_alpha_hat", "steer_alpha_hat")


@pytest.fixture(scope="module")
def files(tmp_path_factory, robust_gains_default):
    """A recording of the paper's vehicle speeding up and slowing down with a torque loss ramp (alpha 1 to 0.6
    from t = 8 s), the default design's gains, and a profile with the stage's noise."""
    root = tmp_path_factory.mktemp("effectiveness")
    points = [SpeedPoint(t_s=0.0, speed_mps=10.0)]
    t, speed = 1.0, 10.0
    while t < 36.0:
        points.append(SpeedPoint(t_s=t, speed_mps=speed))
        speed, t = 30.0 - speed, t + 5.0
    scenario = Scenario(
        name="loss",
        duration_s=36.0,
        speed_profile=tuple(points),
        faults=(LossOfEffectivenessFault(channel="torque", onset_s=8.0, rate_per_s=0.04, alpha_min=0.6),),
        noise=REALISTIC_NOISE,
        seed=5,
    )
    plant = simulate_plant([scenario])
    rec = root / "loss.csv"
    write_recording(rec, plant.t, plant.y[:, 0], plant.u[:, 0])
    gains = root / "gains.json"
    gains.write_text(json.dumps(robust_gains_default.to_dict()))
    profile = root / "profile.json"
    profile.write_text(json.dumps({"effectiveness": {"torque_sigma_nm": 6.0}}))
    return rec, gains, profile


def rows_of(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        return list(csv.DictReader(handle))


def test_replay_writes_the_total_faults_and_the_bias_and_effectiveness_columns(tmp_path, capsys, files):
    rec, gains, profile = files
    out = tmp_path / "out.csv"
    args = ["replay", str(rec), "--out", str(out), "--gains", str(gains), "--params", str(profile)]
    assert main([*args, "--effectiveness"]) == 0, capsys.readouterr().err
    rows = rows_of(out)
    assert tuple(rows[0]) == (*OUTPUT_COLUMNS, *EXTRA)
    alpha = np.array([float(r["torque_alpha_hat"]) for r in rows])
    assert alpha[-1] == pytest.approx(0.6, rel=0.03) and np.abs(alpha[:700] - 1.0).max() < 0.05
    assert {r["steer_alpha_hat"] for r in rows} == {"1"}
    # the total is the bias plus (alpha - 1) times the demand
    total = np.array([float(r["torque_fault_hat"]) for r in rows])
    bias = np.array([float(r["torque_bias_hat"]) for r in rows])
    demand = np.array([float(line.split(",")[3]) for line in rec.read_text().splitlines()[1:]])
    np.testing.assert_allclose(total - bias, (alpha - 1.0) * demand, rtol=0, atol=CSV_PRODUCT_ATOL_NM)
    # the profile can switch the stage on itself; without either, the replay is the additive design's
    on = tmp_path / "on.json"
    on.write_text(json.dumps({"effectiveness": {"enabled": True, "torque_sigma_nm": 6.0}}))
    on_csv = tmp_path / "on.csv"
    assert main(["replay", str(rec), "--out", str(on_csv), "--gains", str(gains), "--params", str(on)]) == 0
    assert rows_of(on_csv) == rows
    plain = tmp_path / "plain.csv"
    assert main(["replay", str(rec), "--out", str(plain), "--gains", str(gains), "--params", str(profile)]) == 0
    additive = rows_of(plain)
    assert tuple(additive[0]) == OUTPUT_COLUMNS
    # the stage does not touch the observer: the state estimates are the same
    assert [r["vy_hat"] for r in additive] == [r["vy_hat"] for r in rows]


def test_an_effectiveness_alarm_raises_the_channels_level_when_alpha_stays_low(tmp_path, capsys, files):
    rec, gains, _ = files
    # fault thresholds out of reach: only the effectiveness rule can raise the torque channel
    profile = tmp_path / "quiet.json"
    alarms = {"torque_warn_nm": 1e5, "torque_fault_nm": 2e5, "effectiveness_warn": 0.9, "effectiveness_after_s": 1.0}
    first_warn = {}
    for k in (0.0, 3.0):  # 0: the rule on alpha_hat itself; 3 (the default): on alpha_hat + 3 sigma
        settings = {"alarms": alarms | {"effectiveness_confidence_k": k}}
        profile.write_text(json.dumps(settings | {"effectiveness": {"enabled": True, "torque_sigma_nm": 6.0}}))
        out = tmp_path / "levels.csv"
        assert main(["replay", str(rec), "--out", str(out), "--gains", str(gains), "--params", str(profile)]) == 0
        capsys.readouterr()
        rows = rows_of(out)
        levels = [r["torque_level"] for r in rows]
        assert {"WARN"} <= set(levels) <= {"OK", "WARN", "FAULT"}
        first_warn[k] = levels.index("WARN")
        assert set(levels[: first_warn[k]]) == {"OK"}
    t = np.array([float(r["t"]) for r in rows])
    alpha = np.array([float(r["torque_alpha_hat"]) for r in rows])
    # the rule written out with k = 0: alpha_hat <= 0.9 held for 1 s after the 3 s warm-up
    low = (alpha <= 0.9) & (t >= 3.0)
    assert first_warn[0.0] == next(k for k in range(100, len(t)) if low[k - 100 : k + 1].all())
    # the upper bound is above alpha_hat: identified later, within a second here (the demand swings)
    assert first_warn[0.0] < first_warn[3.0] <= first_warn[0.0] + 100


def test_the_stage_runs_beside_the_observer_only(tmp_path, capsys, files):
    rec = files[0]
    code = main(["replay", str(rec), "--out", str(tmp_path / "x.csv"), "--effectiveness", "--estimator", "ekf"])
    assert code == 2 and "--effectiveness runs beside the observer, not the EKF" in capsys.readouterr().err
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"effectiveness": {"alpha_bounds": [1.0, 1.2]}}))
    code = main(["replay", str(rec), "--out", str(tmp_path / "x.csv"), "--params", str(bad)])
    assert code == 2 and "effectiveness.alpha_bounds" in capsys.readouterr().err
