"""The built-in profile 'paper': the paper's Table 1 read physically (a 1 m wheel, I_e as the effective mass),
and the paper's scenarios reproduced with it exactly as before the physical fields existed."""

from __future__ import annotations

import csv
import json

import pytest

from agv_fe.cli import main
from agv_fe.common import BUILTIN_PROFILES
from synth.params import OperatingBounds, VehicleParams


def test_the_paper_profile_is_table_1_with_a_one_metre_wheel():
    paper = BUILTIN_PROFILES["paper"]
    assert paper.params == VehicleParams() and paper.bounds == OperatingBounds()
    assert paper.params.wheel_radius_m == 1.0 and paper.params.effective_mass_kg == 443.0
    assert paper.params.rolling_resistance_n == 0.0 and not paper.params.cornering_drag
    assert paper.params.steer_time_constant_s == 0.0


@pytest.mark.parametrize("scenario", ["paper-1", "paper-2"])
def test_the_paper_profile_reproduces_the_papers_scenarios(tmp_path, scenario, capsys):
    """The paper's design on its scenarios: the same gains and the same estimates whether the profile is named or
    left to the defaults, and the faults are tracked (noise-free, after 3 s) as the paper shows."""
    gains = tmp_path / "gains.json"
    assert main(["synth", "--params", "paper", "--design", "paper", "--out", str(gains)]) == 0
    runs = {}
    for label, extra in (("named", ["--params", "paper"]), ("default", [])):
        out = tmp_path / label
        assert main(["simulate", "--scenario", scenario, "--noise", "none", "--gains", str(gains), "--out", str(out),
                     *extra]) == 0  # fmt: skip
        with next(out.glob("*.csv")).open() as handle:
            runs[label] = list(csv.DictReader(handle))
    capsys.readouterr()
    assert runs["named"] == runs["default"]
    rows = [r for r in runs["named"] if float(r["t"]) >= 3.0]
    for true, est in (("torque_fault", "torque_fault_hat"), ("steer_fault", "steer_fault_hat")):
        err = [float(r[est]) - float(r[true]) for r in rows]
        amplitude = max(abs(float(r[true])) for r in rows)
        rmse = (sum(e * e for e in err) / len(err)) ** 0.5
        assert rmse < 0.1 * amplitude, (scenario, true, rmse, amplitude)
    assert json.loads(gains.read_text())["params"]["effective_mass_kg"] == 443.0
