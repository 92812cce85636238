"""The ROS 2 bridge's latency benchmark (agv_fe/benchmarks/ros2_bridge.py): a short run through its own router and
a real `agv-fe ros2-bridge` process. The latencies are the host's figures at that moment: reported, not asserted."""

import json

import pytest

pytest.importorskip("rosbags")

from agv_fe.benchmarks import ros2_bridge as bench
from agv_fe.commands.bench import BENCHMARKS
from tests.agv_fe.markdown import assert_rows_match_headers

pytestmark = pytest.mark.network


def test_the_bridge_benchmark_writes_a_report_with_its_measurements(tmp_path):
    path = bench.run(tmp_path, run_s=2.0)
    text = path.read_text()
    result = json.loads((tmp_path / "ros2_bridge.json").read_text())
    assert text.startswith("# ROS 2 bridge: latency added") and "agv-fe bench --only ros2_bridge" in text
    assert_rows_match_headers(text, at_least=1, rows_required=True)
    # about 200 ticks in 2 s, each carrying one sample of the vehicle's (or the same one again, held)
    assert 100 <= result["measurements"] <= 260 and 0 < result["carried"] <= result["samples"]
    assert 0 <= result["hold_p50_ms"] <= result["total_p50_ms"]
    assert f"| {result['samples']} | {result['carried']} | {result['measurements']} |" in text
    assert BENCHMARKS["ros2_bridge"] == "agv_fe.benchmarks.ros2_bridge"
