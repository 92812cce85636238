import json
import os
import re
import subprocess
import sys
import time

import pytest

from agv_fe.benchmarks import service_load as bench

pytestmark = pytest.mark.network


def test_service_load_benchmark_reports_what_it_measured(tmp_path, monkeypatch):
    """Short steps of 10 vehicles against a real `agv-fe serve`, with an estimate for every sample (a subscriber on
    every key), for every 10th, and for every sample from the fleet stream, the vehicles at spread phases; and the
    last with all of them aligned: the tables, the engine alone and the verdicts all come from the run's own figures.

    Behaviour only: nothing lost, the counts, the report's structure, and verdicts that agree with the figures the
    run measured. Whether a latency or the generator's pace met a target is a figure of the machine at that moment,
    for the benchmark to report, not for a test to assert (a busy machine must not fail it)."""
    monkeypatch.setattr(bench, "STEP_S", 3.0)
    monkeypatch.setattr(bench, "WARMUP_S", 1.0)
    monkeypatch.setattr(bench, "ENGINE_TICKS", 30)
    modes = (
        (1, "vehicle", "spread"),
        (1, "vehicle-bin", "spread"),
        (10, "vehicle", "spread"),
        (1, "fleet", "spread"),
        (1, "fleet", "aligned"),
    )
    path = bench.run(tmp_path, sizes=(10,), modes=modes)
    assert "Machine speed during this run: one observer step for 1,000 vehicles" in path.read_text()
    text = path.read_text()
    sweeps = json.loads(text.rsplit("```json\n", 1)[1].split("\n```")[0])
    assert [(sw["estimate_every_n"], sw["stream"], sw["arrival"]) for sw in sweeps] == list(modes)
    for sweep, expected in zip(sweeps, (3000, 3000, 300, 3000, 3000), strict=True):
        (row,) = sweep["service"]
        (engine,) = sweep["engine"]
        assert row["vehicles"] == 10 and row["sent"] == 3000 and row["zero_loss"]
        assert row["estimates_received"] == row["estimates_expected"] == expected
        assert 0 < row["p50_ms"] <= row["p99_ms"] <= row["max_ms"]
        assert row["receiver_cpu"] > 0 and row["generator_cpu"] > 0
        assert 0 < row["event_loop_cpu"] + row["zenoh_cpu"] <= row["service_cpu"] + 0.05
        assert engine["vehicles"] == 10 and engine["us_per_msg"] > 0 and engine["us_per_msg_spread"] > 0
        assert f"{engine['us_per_msg']:.2f} us per measurement" in text
        assert f"| 10 | {engine['us_per_msg']:.2f} | {engine['cores_at_100hz']:.3f} " in text
        assert f"| {engine['us_per_msg_spread']:.2f} | {engine['cores_at_100hz_spread']:.3f} |" in text
        # the same engine without the grip gate, timed in turn: the gate's cost as a ratio
        off, off_spread = engine["us_per_msg_no_grip_gate"], engine["us_per_msg_spread_no_grip_gate"]
        assert off > 0 and off_spread > 0
        whole, spread = engine["us_per_msg"] / off - 1, engine["us_per_msg_spread"] / off_spread - 1
        cost = f"{100 * whole:+.0f} % / {100 * spread:+.0f} %"
        assert f"| {off:.2f} / {off_spread:.2f} | {cost} |" in text
        # every tick drained at least one sample; the ticks' measurements add up to what was accepted
        assert 0 < row["service_ticks"] <= row["accepted"]
        assert f"({row['accepted'] / row['service_ticks']:.0f}) | {bench._verdict(row)} |" in text
    # the fleet stream carried every estimate; the vehicle keys, which nobody watched, stopped after the first second
    (fleet,) = sweeps[3]["service"]
    assert fleet["published_in_fleet_stream"] == 3000 and fleet["published_per_vehicle"] < 3000
    (keys,) = sweeps[0]["service"]
    assert keys["published_per_vehicle"] == 3000 and keys["published_in_fleet_stream"] == 0
    assert keys["published_per_vehicle_binary"] < 3000  # nobody watched the binary keys
    (binary,) = sweeps[1]["service"]
    assert binary["published_per_vehicle_binary"] == 3000 and binary["published_per_vehicle"] < 3000
    # each mode's headline says what its own step measured: a lower bound when the step kept up, none otherwise
    for sweep, ending in zip(
        sweeps,
        (
            "vehicle's key (a subscriber on every key)",
            "vehicle's binary key (a subscriber on every key)",
            "every 10th sample, on each vehicle's key",
            "the fleet stream (one message per tick)",
            "aligned clocks, the worst case)",
        ),
        strict=True,
    ):
        (row,) = sweep["service"]
        said = "at least 10 vehicles (the largest size tried)" if bench._sustained(row) else "none of the sizes tried"
        assert f"{ending}: **{said}**" in text
    verdicts = text.split("**Against the targets (this run).**")[1:]
    assert len(verdicts) == 5
    for sweep, verdict in zip(sweeps, verdicts, strict=True):
        (row,) = sweep["service"]
        line = verdict.split("\n", 1)[0]
        assert f"p99 {row['p99_ms']:.1f} ms" in line
        held = re.search(r"held up to ([\d,]+) vehicles", line)
        assert (held is not None) == (bench._sustained(row) and row["p99_ms"] < bench.TARGET_P99_MS)


def test_the_verdict_says_when_the_latency_target_is_missed():
    rows = [
        {"vehicles": n, "zero_loss": True, "paced": True, "p50_ms": p50, "p99_ms": p99, "service_cpu": 0.5}
        for n, p50, p99 in ((100, 4.0, 8.0), (250, 6.0, 12.0), (1000, 50.0, 80.0))
    ]
    engine = [{"vehicles": 1000, "us_per_msg": 2.5, "cores_at_100hz": 0.25}]
    verdict = bench._against_target(rows, engine)
    assert "1,000 vehicles at 100 Hz ran with zero loss (p50 50.0 ms, p99 80.0 ms" in verdict
    assert "held up to 100 vehicles" in verdict and "2.50 us per measurement, 0.25 of a core" in verdict
    assert "in ticks of a fifth" not in verdict
    spread = [{**engine[0], "us_per_msg_spread": 2.75, "cores_at_100hz_spread": 0.275}]
    assert "(2.75 us, 0.28 of a core, in ticks of a fifth)" in bench._against_target(rows, spread)
    assert "not met" in bench._against_target(rows[1:], engine)
    hold = {**rows[2], "duration_s": 30.0, "p50_ms": 5.0, "p99_windows_ms": [8.0, 12.5, 9.0]}
    held = bench._against_target(rows, engine, hold)
    assert "Held at 1,000 vehicles for 30 s, p99 per 10 s window was 8.0, 12.5, 9.0 ms" in held
    assert "under 10 ms in 2 of 3 windows" in held
    lossy = bench._against_target(rows, engine, {**hold, "zero_loss": False})
    assert "(not cleanly: loss or pacing)" in lossy and "under 10 ms in 0 of 3 windows" in lossy
    slow = {**rows[2], "p99_ms": 165.0}
    behind = bench._against_target([*rows[:2], slow], engine, {**hold, "p99_ms": 2000.0})
    assert "ran with zero loss but fell behind (p50 50.0 ms, p99 165.0 ms" in behind
    assert "for 30 s (falling behind)" in behind
    # where the service's CPU went, when the step has the thread split (older runs do not)
    assert "of which" not in held
    split = {**hold, "event_loop_cpu": 0.46, "zenoh_cpu": 0.28, "service_waited": 0.7}
    assert (
        "service CPU 0.50 cores, of which the event loop 0.46 and Zenoh's threads 0.28; it waited 0.70 s a "
        "second for a core)" in bench._against_target(rows, engine, split)
    )


def test_the_largest_fleet_is_a_lower_bound_when_nothing_failed():
    ok = {"zero_loss": True, "paced": True}
    assert bench._largest([{"vehicles": 100, **ok}, {"vehicles": 250, **ok}], (100, 250)) == (
        "at least 250 vehicles (the largest size tried)"
    )
    failed = [{"vehicles": 100, **ok}, {"vehicles": 250, "zero_loss": False, "paced": True}]
    assert bench._largest(failed, (100, 250, 500)) == "100 vehicles"
    # zero loss at a growing latency is falling behind, not sustained
    behind = [{"vehicles": 100, **ok, "p99_ms": 9.0}, {"vehicles": 250, **ok, "p99_ms": 165.0}]
    assert bench._largest(behind, (100, 250)) == "100 vehicles"
    assert [bench._verdict(r) for r in behind] == ["sustained", "falling behind"]
    assert bench._largest([{"vehicles": 100, "zero_loss": False, "paced": False}], (100,)) == "none of the sizes tried"


@pytest.mark.skipif(not os.path.exists("/proc/self/schedstat"), reason="the kernel keeps no run-queue counts")
def test_the_wait_for_a_core_counts_the_children_that_wait():
    """More busy children than cores: together they wait for a core (the run queue), and the count of the parent
    and its live children says so; a process that is not there has no count."""
    busy = "import time\nend = time.monotonic() + 1.5\nwhile time.monotonic() < end: pass"
    before = bench._waited_s(os.getpid())
    children = [subprocess.Popen([sys.executable, "-c", busy]) for _ in range((os.cpu_count() or 1) + 2)]
    try:
        time.sleep(1.0)
        during = bench._waited_s(os.getpid())
    finally:
        for child in children:
            child.wait(30)
    assert before is not None and during is not None
    # at least two of them were always ready without a core for the second they all ran: ~2 s; 0.2 leaves room
    assert during - before > 0.2
    assert bench._waited_s(2**22 + 1) is None  # above the largest process id Linux hands out


def test_a_wait_for_a_core_is_never_negative():
    """Threads that ended take their counts with them: a step's difference is a lower bound, at least 0."""
    assert bench._difference(1.0, 1.5) == 0.5
    assert bench._difference(1.0, 0.99) == 0.0
    assert bench._difference(None, 1.0) is None and bench._difference(1.0, None) is None
