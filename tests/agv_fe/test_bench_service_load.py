import json
import re

import pytest

from agv_fe.benchmarks import service_load as bench

pytestmark = pytest.mark.network


def test_service_load_benchmark_reports_what_it_measured(tmp_path, monkeypatch):
    """A short step of 10 vehicles against a real `agv-fe serve`: the table, the engine alone and the verdict
    all come from the run's own figures."""
    monkeypatch.setattr(bench, "STEP_S", 3.0)
    monkeypatch.setattr(bench, "WARMUP_S", 1.0)
    monkeypatch.setattr(bench, "ENGINE_TICKS", 30)
    path = bench.run(tmp_path, sizes=(10,))
    text = path.read_text()
    data = json.loads(text.rsplit("```json\n", 1)[1].split("\n```")[0])
    (row,) = data["service"]
    (engine,) = data["engine"]
    assert row["vehicles"] == 10 and row["sent"] == 3000 and row["zero_loss"] and row["paced"]
    assert row["estimates_received"] == row["estimates_expected"] == 300
    assert 0 < row["p50_ms"] <= row["p99_ms"] <= row["max_ms"]
    assert engine["vehicles"] == 10 and engine["us_per_msg"] > 0
    assert "Largest fleet sustained at 100 Hz per vehicle with zero loss: **10 vehicles**" in text
    verdict = text.split("**Against the targets (this run).**", 1)[1].split("\n", 1)[0]
    assert f"p99 {row['p99_ms']:.1f} ms" in verdict
    assert f"{engine['us_per_msg']:.2f} us per measurement" in verdict
    held = re.search(r"held up to ([\d,]+) vehicles", verdict)
    assert (held is not None) == (row["p99_ms"] < 10.0)


def test_the_verdict_says_when_the_latency_target_is_missed():
    rows = [
        {"vehicles": n, "zero_loss": True, "paced": True, "p50_ms": p50, "p99_ms": p99, "service_cpu": 0.5}
        for n, p50, p99 in ((100, 4.0, 8.0), (250, 6.0, 12.0), (1000, 50.0, 200.0))
    ]
    engine = [{"vehicles": 1000, "us_per_msg": 2.5, "cores_at_100hz": 0.25}]
    verdict = bench._against_target(rows, engine)
    assert "1,000 vehicles at 100 Hz ran with zero loss (p50 50.0 ms, p99 200.0 ms" in verdict
    assert "held up to 100 vehicles" in verdict and "2.50 us per measurement, 0.25 of a core" in verdict
    assert "not met" in bench._against_target(rows[1:], engine)
    again = [{**rows[2], "p99_ms": 8.0}, {**rows[2], "p99_ms": 9.0}]
    repeated = bench._against_target(rows, engine, again)
    assert "Over 3 steps of 1,000 vehicles" in repeated and "200.0, 8.0, 9.0 ms, median 9.0 ms" in repeated
    assert "the target is met by the median" in repeated
    lossy = [{**again[0], "zero_loss": False}, again[1]]
    assert "not every step was clean): the target is not met" in bench._against_target(rows, engine, lossy)
