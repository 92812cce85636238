import json

import pytest

from agv_fe.benchmarks import service_config as bench
from agv_fe.benchmarks import service_load

pytestmark = pytest.mark.network


def test_the_configurations_alternate_and_each_service_runs_with_its_settings(tmp_path, monkeypatch):
    """Two rounds of history on and off against real `agv-fe serve` processes, 10 vehicles, short steps: the runs
    alternate ABAB, the history runs exactly in the services told to run it, nothing is lost, and the report's
    summary is computed from the runs it lists. Latencies are the machine's figures, not asserted."""
    monkeypatch.setattr(service_load, "STEP_S", 2.0)
    monkeypatch.setattr(service_load, "WARMUP_S", 0.5)
    runs = bench.measure(bench.HISTORY, rounds=2, vehicles=10, hold_s=3.0)
    assert [(r["round"], r["configuration"]) for r in runs] == [
        (1, "history on (default)"),
        (1, "history off"),
        (2, "history on (default)"),
        (2, "history off"),
    ]
    assert [r["history"] for r in runs] == [True, False, True, False]
    for r in runs:
        assert r["hold"]["vehicles"] == 10 and r["hold"]["zero_loss"]
        assert r["hold"]["estimates_received"] == r["hold"]["sent"] > 0
    text = bench.render("t", bench.HISTORY, runs, 10, "cmd")
    assert json.loads(text.rsplit("```json\n", 1)[1].split("\n```")[0]) == runs
    on, off = (bench._summary(c.label, runs) for c in bench.HISTORY)
    assert on["runs"] == off["runs"] == 2
    ratio = off["p99_median_ms"] / on["p99_median_ms"]
    assert f"| history off | 2 | {'yes' if off['clean'] else '**no**'} | {off['p99_median_ms']:.2f} / " in text
    assert f"| {ratio:.2f} |" in text and "`cmd` this one" in text


def test_a_baseline_that_is_not_a_checkout_is_refused(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        bench.main(["--baseline", str(tmp_path), "old", "--out", str(tmp_path / "r.md")])
    assert exc.value.code == 2
    assert "is not a checkout of this project" in capsys.readouterr().err


def test_a_setting_that_is_not_the_services_is_refused(tmp_path, capsys):
    (tmp_path / "agv_fe").mkdir()
    with pytest.raises(SystemExit) as exc:
        bench.main(["--baseline", str(tmp_path), "old", "--out", str(tmp_path / "r.md"), "--env", "PATH=/x"])
    assert exc.value.code == 2
    assert "--env takes AGV_FE_NAME=VALUE, got PATH=/x" in capsys.readouterr().err
