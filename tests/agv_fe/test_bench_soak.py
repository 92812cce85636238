import argparse
import json
import math

import pytest

from agv_fe.benchmarks import soak
from agv_fe.commands import bench as bench_command


@pytest.mark.network
def test_soak_benchmark_reports_what_it_measured(tmp_path, monkeypatch):
    """Three 3 s windows of 10 vehicles against a real `agv-fe serve`, the REST side load every second: the table,
    the totals and the verdict all come from the run's own figures."""
    monkeypatch.setattr(soak, "WARMUP_S", 1.0)
    monkeypatch.setattr(soak, "POLL_S", 1.0)
    path = soak.run(tmp_path, vehicles=10, minutes=0.15, window_s=3.0)
    text = path.read_text()
    result = json.loads(text.rsplit("```json\n", 1)[1].split("\n```")[0])
    assert result["windows"] == 3 and result["vehicles"] == 10
    assert result["zero_loss"] and result["sent"] == result["accepted"] == result["received"] > 0
    assert result["missing"] == result["rejected"] == 0
    rows = result["rows"]
    assert [r["window"] for r in rows] == [1, 2, 3]
    for r in rows:
        # a window holds the samples stamped in it: 10 vehicles x 100 Hz x 3 s, give or take a period at its edges
        assert abs(r["estimates"] - 3000) <= 20
        assert 0 < r["p50_ms"] <= r["p99_ms"] <= r["p999_ms"] <= r["max_ms"]
        assert r["rss_mb"] > 10 and r["hwm_mb"] >= r["rss_mb"] and r["threads"] > 1 and r["open_files"] > 3
        assert r["service_cpu"] > 0 and r["data_mb"] > 0 and r["step_us"] > 0 and r["steal_cores"] >= 0
        assert f"| {r['step_us']:.1f} | {r['steal_cores']:.3f} |" in text
        assert r["metrics_ms"]["n"] >= 2 and r["vehicles_ms"]["n"] >= 2 and r["vehicles_ms"]["max"] > 0
        assert (
            f"| {r['window']} | {r['minute']:.3g} | {r['estimates']} | {r['p50_ms']:.2f} | {r['p99_ms']:.2f} " in text
        )
    met = sum(1 for r in rows if r["p99_ms"] < 10.0)
    assert f"p99 under 10 ms in {met} of 3 windows" in text
    assert f"Zero loss: {result['sent']:,} samples sent" in text
    assert f"{rows[0]['rss_mb']:.1f} MB after the first window, {rows[-1]['rss_mb']:.1f} MB at the end" in text


def test_percentiles_come_from_the_histogram_and_never_exceed_the_maximum():
    hist = [0] * (soak.HIST_BINS + 1)
    hist[0], hist[10], hist[soak.HIST_BINS] = 998, 1, 1
    assert soak.percentile_ms(hist, 0.5, 350.0) == pytest.approx(soak.HIST_BIN_US / 1000)
    assert soak.percentile_ms(hist, 0.999, 350.0) == pytest.approx(11 * soak.HIST_BIN_US / 1000)
    assert soak.percentile_ms(hist, 1.0, 350.0) == 350.0  # the overflow bin answers with the exact maximum
    one = [0] * (soak.HIST_BINS + 1)
    one[3] = 1
    assert soak.percentile_ms(one, 0.99, 0.17) == 0.17  # bin edge 0.2 ms, but nothing took longer than 0.17
    assert math.isnan(soak.percentile_ms([0] * (soak.HIST_BINS + 1), 0.5, 0.0))


def test_memory_growth_is_the_least_squares_slope_per_hour():
    assert soak.growth_mb_per_hour([1.0, 2.0, 3.0], [100.0, 100.5, 101.0]) == pytest.approx(30.0)
    assert soak.growth_mb_per_hour([1.0, 2.0, 3.0, 4.0], [100.0, 101.0, 100.0, 101.0]) == pytest.approx(12.0)
    assert soak.growth_mb_per_hour([2.0, 3.0], [50.0, 50.0]) == 0.0
    assert math.isnan(soak.growth_mb_per_hour([1.0], [1.0]))


def _result(**changes):
    row = {"p50_ms": 2.0, "p99_ms": 6.0, "max_ms": 12.0, "threads": 30, "open_files": 40, "data_mb": 0.2}
    rows = [{**row, "window": k, "minute": float(k), "rss_mb": 120.0, "hwm_mb": 121.0} for k in (1, 2, 3, 4)]
    result = {"sent": 1000, "accepted": 1000, "received": 1000, "missing": 0, "rejected": 0, "zero_loss": True}
    return {**result, "rows": rows, **changes}


def test_the_verdict_names_loss_missed_windows_stalls_and_growth():
    clean = soak._verdict(_result())
    assert "Zero loss: 1,000 samples sent" in clean and "p99 under 10 ms in 4 of 4 windows" in clean
    assert "no stall" in clean and "grew +0.0 MB per hour, steady" in clean
    rows = _result()["rows"]
    rows[2] = {**rows[2], "p99_ms": 14.0, "max_ms": 2500.0}
    for k, r in enumerate(rows):
        r["rss_mb"] = 120.0 + k  # 1 MB a minute
    bad = soak._verdict(_result(rows=rows, zero_loss=False, accepted=990, missing=10))
    assert "Not clean: 1,000 sent, 990 accepted, 10 missing" in bad
    assert "p99 under 10 ms in 3 of 4 windows (6.00 to 14.00 ms)" in bad
    assert "a stall (over 1 s)" in bad and "grew +60.0 MB per hour" in bad and "growing" in bad
    # a fast rate over a short run is within the allocator's jitter
    short = [{**r, "minute": r["minute"] / 60.0, "rss_mb": 120.0 + 0.1 * k} for k, r in enumerate(_result()["rows"])]
    jitter = soak._verdict(_result(rows=short))
    assert "grew +360.0 MB per hour, steady" in jitter


def test_bench_passes_the_soak_duration(tmp_path, monkeypatch):
    calls = []

    def fake_run(out_dir, **options):
        calls.append(options)
        path = out_dir / "soak.md"
        path.write_text("report\n")
        return path

    monkeypatch.setattr(soak, "run", fake_run)
    args = argparse.Namespace(only="soak", out=str(tmp_path), soak_minutes=120.0)
    assert bench_command.run(args) == 0
    args = argparse.Namespace(only="soak", out=str(tmp_path), soak_minutes=None)
    assert bench_command.run(args) == 0
    assert calls == [{"minutes": 120.0}, {}]
