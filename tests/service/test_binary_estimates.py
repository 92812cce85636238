"""Each vehicle's estimates in the binary encoding (`.../<vehicle>/estimate.bin`), from a real service on loopback.

The binary record must carry exactly what the JSON document on `.../<vehicle>/estimate` carries, and the service
makes it only while someone subscribes to that key.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import zenoh

from agv_protocol.wire import (
    BINARY_ESTIMATE_KIND,
    ESTIMATE_BINARY_HEADER_SIZE,
    Estimate,
    EstimateBatch,
    ProtocolError,
    decode_binary_estimate,
    encode_binary_estimates,
    level_codes,
    vehicle_key,
)
from service.transport import open_session
from tests.service.helpers import make_settings, plant_measurements, running, wait_for

pytestmark = pytest.mark.network


def test_binary_and_json_keys_carry_the_same_estimates_and_only_a_subscribed_encoding_is_made(tmp_path):
    settings = make_settings(tmp_path)
    with running(settings) as server:
        session = open_session("client", server.settings.zenoh.endpoint)
        ids = ["bin-a", "bin-b"]
        binary = {
            v: session.declare_subscriber(vehicle_key(v, BINARY_ESTIMATE_KIND), zenoh.handlers.FifoChannel(1 << 16))
            for v in ids
        }
        json_sub = session.declare_subscriber(vehicle_key("bin-a", "estimate"), zenoh.handlers.FifoChannel(1 << 16))
        pubs = {
            v: session.declare_publisher(vehicle_key(v, "meas"), congestion_control=zenoh.CongestionControl.BLOCK)
            for v in ids
        }
        got: dict[str, list[Estimate]] = {v: [] for v in ids}
        got_json: list[Estimate] = []

        def drain() -> int:
            for v, sub in binary.items():
                while (s := sub.try_recv()) is not None:
                    payload = s.payload.to_bytes()
                    assert str(s.encoding).startswith("application/octet-stream")
                    got[v].append(decode_binary_estimate(payload, v))
            while (s := json_sub.try_recv()) is not None:
                got_json.append(Estimate.decode(s.payload.to_bytes()))
            return min(len(x) for x in got.values())

        try:
            time.sleep(0.3)  # the subscriptions reach the router
            for row in plant_measurements(ids, 200):
                for m in row:
                    pubs[m.vehicle_id].put(m.encode())
            wait_for(lambda: drain() >= 200 and len(got_json) >= 200, what="200 binary and JSON estimates each")
            for v in ids:
                assert [e.seq for e in got[v]] == list(range(200))  # every sample, in order, once
                assert {e.vehicle for e in got[v]} == {v}
            assert got["bin-a"] == got_json  # the same records, to the last bit of every float
            # bin-b's JSON key has no subscriber: once the service has looked, it makes no JSON document for it
            vehicles = server.service.transport.vehicle_estimates
            wait_for(lambda: "bin-b" in vehicles.unmatched_keys["estimate"], what="bin-b's JSON key unmatched")
            assert "bin-b" not in vehicles.unmatched_keys[BINARY_ESTIMATE_KIND]
        finally:
            for entity in [*binary.values(), json_sub, *pubs.values()]:
                entity.undeclare()
            session.close()


def _batch(n: int) -> EstimateBatch:
    rng = np.random.default_rng(3)
    return EstimateBatch(
        [f"v{i}" for i in range(n)],
        np.arange(n, dtype=np.int64),
        np.arange(n, dtype=np.int64) * 10_000_000,
        rng.standard_normal((n, 5)),
        np.ones(n, dtype=bool),
        np.zeros(n, np.int8),
        "0123456789ab",
    )


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda b: b[:20], "the header alone"),
        (lambda b: b"XXXX" + b[4:], "magic"),
        (lambda b: b[:4] + b"\x02" + b[5:], "protocol version 2"),
        (lambda b: b[:6] + b"\x80" + b[7:], "reserved bits"),
        (lambda b: b[:7] + b"\x09" + b[8:], "unknown level code 9"),
        (lambda b: b[:-8], "5 columns make 80"),
        (lambda b: b[:36] + b"\x00\x00" + b[38:], "0 columns make 40"),
    ],
)
def test_a_malformed_binary_estimate_is_refused_with_its_reason(change, message):
    payload = encode_binary_estimates(_batch(1))[0]
    assert len(payload) == ESTIMATE_BINARY_HEADER_SIZE + 5 * 8
    decode_binary_estimate(payload, "v0")  # the original reads
    with pytest.raises(ProtocolError, match=message):
        decode_binary_estimate(change(payload), "v0")


@pytest.mark.parametrize("columns", ["state", "state+effectiveness"])
@pytest.mark.parametrize("switched", [False, True])
def test_a_binary_estimate_reads_as_the_json_document_of_the_same_row(columns, switched):
    from agv_protocol.wire import ESTIMATE_COLUMNS, STATE_COLUMNS

    cols = STATE_COLUMNS if columns == "state" else ESTIMATE_COLUMNS
    n = 6
    rng = np.random.default_rng(5)
    batch = EstimateBatch(
        [f"veh-{i}" for i in range(n)],
        np.arange(n, dtype=np.int64) + 2**40,
        np.arange(n, dtype=np.int64) * 10_000_000 + 1_700_000_000_000_000_000,
        rng.standard_normal((n, len(cols))) * 1e3,
        np.array([True, False] * 3),
        level_codes(["OK", "WARN", "FAULT", "STALE", "OK", "WARN"]),
        "fedcba987654",
        np.array([True, False, False, True, True, False]) if switched else None,
        cols,
    )
    rows = [4, 0, 5]
    for row, payload, document in zip(rows, encode_binary_estimates(batch, rows), batch.documents(rows), strict=True):
        assert decode_binary_estimate(payload, f"veh-{row}") == Estimate.decode(document)


def test_a_later_revision_is_read_for_the_columns_this_side_knows():
    from agv_protocol.wire import ESTIMATE_COLUMNS, ESTIMATE_REVISION

    payload = bytearray(encode_binary_estimates(_batch(1))[0])
    original = decode_binary_estimate(bytes(payload), "v0")
    # a later revision: every column this side knows, NaN where the record has none, and two new ones
    known = np.frombuffer(bytes(payload[ESTIMATE_BINARY_HEADER_SIZE:]), "<f8").tolist()
    values = known + [float("nan")] * (len(ESTIMATE_COLUMNS) - len(known)) + [1.5, -2.5]
    later = bytearray(payload[:ESTIMATE_BINARY_HEADER_SIZE]) + np.array(values, "<f8").tobytes()
    later[5] = ESTIMATE_REVISION + 1
    later[36:38] = len(values).to_bytes(2, "little")
    assert decode_binary_estimate(bytes(later), "v0") == original
    later[5] = ESTIMATE_REVISION  # the same record claiming a revision this side knows has columns too many
    with pytest.raises(ProtocolError, match="columns at revision"):
        decode_binary_estimate(bytes(later), "v0")
