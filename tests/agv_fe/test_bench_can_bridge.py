"""The CAN bridge's latency benchmark (agv_fe/benchmarks/can_bridge.py): a short run of a vehicle's frames on
python-can's virtual bus through a real `agv-fe can-bridge` and its own router. The latencies are the host's figures
at that moment: reported, not asserted."""

import json

import pytest

pytest.importorskip("can")
pytest.importorskip("cantools")

from agv_fe.benchmarks import can_bridge as bench
from agv_fe.commands.bench import BENCHMARKS
from tests.agv_fe.markdown import assert_rows_match_headers

pytestmark = pytest.mark.network


def test_the_can_bridge_benchmark_writes_a_report_with_its_measurements(tmp_path):
    path = bench.run(tmp_path, run_s=2.0)
    text = path.read_text()
    result = json.loads((tmp_path / "can_bridge.json").read_text())
    assert text.startswith("# CAN bridge: latency added") and "agv-fe bench --only can_bridge" in text
    assert_rows_match_headers(text, at_least=1, rows_required=True)
    # at most about 200 ticks in 2 s, each carrying one sample of the vehicle's (or the same one again, held)
    assert 0 < result["measurements"] <= 260 and 0 < result["carried"] <= result["samples"]
    assert 0 <= result["hold_p50_ms"] <= result["total_p50_ms"] and result["run_s"] == 2.0
    assert f"| {result['samples']} | {result['carried']} | {result['measurements']} |" in text
    assert BENCHMARKS["can_bridge"] == "agv_fe.benchmarks.can_bridge"


def test_a_run_longer_than_the_torque_signal_can_number_is_refused():
    with pytest.raises(ValueError, match="the torque signal numbers at most 16383 samples"):
        bench.measure(run_s=200.0)
