"""Each vehicle's estimates put on its keys by a process of its own (``zenoh.vehicle_publisher='process'``,
service/vehicle_fanout.py): the same records on the same keys as the service's own thread puts, from a real
service and its child process on loopback; the counters on /metrics; a dead child makes the replica not ready.
And the fleet stream's groups read back as the batches they were written from."""

from __future__ import annotations

import time

import numpy as np
import orjson
import pytest
import zenoh

from agv_protocol.wire import (
    BINARY_ESTIMATE_KIND,
    EFFECTIVENESS_COLUMNS,
    ESTIMATE_COLUMNS,
    STATE_COLUMNS,
    Estimate,
    EstimateBatch,
    ProtocolError,
    decode_binary_estimate,
    encode_fleet_estimates,
    level_codes,
    vehicle_key,
)
from service.fleet_child import fleet_batches
from service.transport import open_session
from tests.service.helpers import T0_NS, make_settings, parse_metrics, plant_measurements, running, wait_for


def _batch(columns: tuple[str, ...], switched: bool, version: str) -> EstimateBatch:
    n = 4
    rng = np.random.default_rng(len(columns))
    return EstimateBatch(
        [f"veh-{k}" for k in range(n)],
        np.arange(n, dtype=np.int64) + 7,
        np.arange(n, dtype=np.int64) * 10_000_000 + 1_700_000_000_000_000_000,
        rng.standard_normal((n, len(columns))) * 1e3,
        np.array([True, False, True, True]),
        level_codes(["OK", "WARN", "FAULT", "OK"]),
        version,
        np.array([True, False, False, True]) if switched else None,
        columns,
    )


def test_a_fleet_message_reads_back_as_its_batches_with_the_same_documents():
    batches = [_batch(STATE_COLUMNS, False, "0123456789ab"), _batch(ESTIMATE_COLUMNS, True, "ba9876543210")]
    assert EFFECTIVENESS_COLUMNS  # the second batch carries the optional group
    back = fleet_batches(encode_fleet_estimates("replica-0", batches))
    assert [b.columns for b in back] == [b.columns for b in batches]
    for mine, theirs in zip(batches, back, strict=True):
        assert theirs.documents() == mine.documents()  # byte for byte: every float round-trips through JSON
        assert theirs.vehicle_ids == mine.vehicle_ids and np.array_equal(theirs.t_ns, mine.t_ns)


@pytest.mark.parametrize(
    ("payload", "reason"),
    [
        (b"not json", "not a fleet estimates message"),
        (orjson.dumps({"v": 2, "replica": "r", "groups": []}), "version 2"),
        (orjson.dumps({"v": 1, "replica": "r"}), "not a fleet estimates message"),
        (orjson.dumps({"v": 1, "replica": "r", "groups": [{"vehicle": ["a"], "seq": [1]}]}), "not a fleet"),
    ],
)
def test_what_is_not_a_fleet_message_is_refused_with_its_reason(payload, reason):
    with pytest.raises(ProtocolError, match=reason):
        fleet_batches(payload)


@pytest.mark.network
def test_the_process_puts_every_estimate_on_its_keys_as_the_thread_would_and_its_death_is_not_ready(tmp_path):
    settings = make_settings(tmp_path, zenoh={"vehicle_publisher": "process"})
    with running(settings) as server:
        session = open_session("client", server.settings.zenoh.endpoint)
        ids = ["fan-a", "fan-b"]
        fifo = zenoh.handlers.FifoChannel
        binary = {v: session.declare_subscriber(vehicle_key(v, BINARY_ESTIMATE_KIND), fifo(1 << 16)) for v in ids}
        json_sub = session.declare_subscriber(vehicle_key("fan-a", "estimate"), fifo(1 << 16))
        block = zenoh.CongestionControl.BLOCK
        pubs = {v: session.declare_publisher(vehicle_key(v, "meas"), congestion_control=block) for v in ids}
        got: dict[str, list[Estimate]] = {v: [] for v in ids}
        got_json: list[Estimate] = []

        def drain() -> int:
            for v, sub in binary.items():
                while (s := sub.try_recv()) is not None:
                    got[v].append(decode_binary_estimate(s.payload.to_bytes(), v))
            while (s := json_sub.try_recv()) is not None:
                got_json.append(Estimate.decode(s.payload.to_bytes()))
            return min(len(x) for x in got.values())

        try:
            process = server.service.vehicle_process
            assert process is not None and process.alive
            time.sleep(0.5)  # the subscriptions reach the router and the child's matching listeners
            for row in plant_measurements(ids, 200):
                for m in row:
                    pubs[m.vehicle_id].put(m.encode())
            wait_for(lambda: drain() >= 200 and len(got_json) >= 200, what="200 binary and JSON estimates each")
            for v in ids:
                assert [e.seq for e in got[v]] == list(range(200)) and {e.vehicle for e in got[v]} == {v}
            assert got["fan-a"] == got_json  # the same records in both encodings, to the last bit

            def counted() -> bool:  # the child's counters, through shared memory
                scrape = parse_metrics(server.get("/metrics").text)
                return (
                    scrape.value("agv_fe_estimates_published_total", encoding="binary") >= 400
                    and scrape.value("agv_fe_estimates_published_total", encoding="json") >= 200
                    and scrape.value("agv_fe_vehicle_estimate_latency_seconds_count") >= 400
                )

            wait_for(counted, what="the child's counts on /metrics")
            # the child's delay histogram: every estimate once (each vehicle's, put in one encoding or two), the
            # samples stamped in 2023 above every bound
            scrape = parse_metrics(server.get("/metrics").text)
            delay = scrape.buckets("agv_fe_vehicle_estimate_latency_seconds")
            assert delay[-1] == (float("inf"), 400) and delay[-2][1] == 0
            years_s = time.time() - T0_NS / 1e9
            assert 0.99 * 400 * years_s < scrape.value("agv_fe_vehicle_estimate_latency_seconds_sum") < 400 * years_s
            assert 0 <= scrape.value("agv_fe_vehicle_estimate_backlog_seconds") < 2.0
            process._process.kill()
            wait_for(lambda: not process.alive, what="the child gone")
            ready = server.get("/ready").json()
            assert not ready["ready"]
            assert "each vehicle's estimates on its keys has exited" in ready["detail"]
        finally:
            for entity in [*binary.values(), json_sub, *pubs.values()]:
                entity.undeclare()
            session.close()
