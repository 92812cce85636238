import json

import pytest

from agv_fe.benchmarks import publisher as bench

pytestmark = pytest.mark.network


def test_publisher_benchmark_writes_a_report_with_its_measurements(tmp_path):
    """A 1 s run of 5 vehicles through the benchmark's own router process: a row per size, delivery checked. The
    rate and the latencies are the host's figures at that moment: reported, not asserted."""
    path = bench.run(tmp_path, sizes=(5,), run_s=1.0)
    text = path.read_text()
    assert "# Publisher pacing and capacity" in text and "| 5 |" in text and "**Capacity.**" in text
    (row,) = json.loads((tmp_path / "publisher.json").read_text())
    assert row["vehicles"] == 5 and row["ticks"] == 100
    assert row["rate_hz"] > 0 and f"| 5 | {row['rate_hz']:.2f} |" in text
    assert row["delivered_fraction"] == 1.0
    assert row["source_p50_ms"] > 0 and row["publish_p50_ms"] > 0
