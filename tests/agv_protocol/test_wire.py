import math

import numpy as np
import orjson
import pytest
from pydantic import BaseModel

from agv_protocol.wire import (
    FLAG_SEQUENCE_RESTART,
    MAGIC,
    MEASUREMENT_HEADER_DTYPE,
    MEASUREMENT_HEADER_SIZE,
    Alarm,
    Estimate,
    EstimateBatch,
    FleetEstimates,
    Measurement,
    PayloadReport,
    ProtocolError,
    all_buckets,
    bucket_of,
    check_vehicle_id,
    encode_fleet_estimates,
    parse_vehicle_key,
    shard_buckets,
    vehicle_key,
)


def test_measurement_round_trip_is_compact():
    m = Measurement("veh-001", 42, 1_700_000_000_123_456_789, 12.5, -0.125, 180.0, 0.0125)
    payload = m.encode()
    assert len(payload) == MEASUREMENT_HEADER_SIZE + len("veh-001") == 71
    assert Measurement.decode(payload) == m


def test_the_batch_decoders_read_what_encode_wrote():
    """The service decodes a tick's headers as one numpy record array; it must agree with the struct."""
    ms = [
        Measurement("a", 7, 1_700_000_000_000_000_001, 12.5, -0.125, 180.0, 0.0125),
        Measurement("veh-long-name", 2**40, -5, 0.0, 1e-300, -1e300, -0.5, FLAG_SEQUENCE_RESTART),
    ]
    header = np.frombuffer(b"".join(m.encode()[:MEASUREMENT_HEADER_SIZE] for m in ms), dtype=MEASUREMENT_HEADER_DTYPE)
    assert MEASUREMENT_HEADER_DTYPE.itemsize == MEASUREMENT_HEADER_SIZE
    for m, h in zip(ms, header, strict=True):
        assert (h["seq"], h["t_ns"], h["flags"], h["id_len"]) == (m.seq, m.timestamp_ns, m.flags, len(m.vehicle_id))
        assert (h["vx"], h["r"], h["torque"], h["steer"]) == (m.vx_mps, m.r_radps, m.torque_nm, m.steer_rad)
        assert (h["magic"], h["version"]) == (MAGIC, 1)


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda b: b[:20], "too short"),
        (lambda b: b"XXXX" + b[4:], "bad magic"),
        (lambda b: b[:4] + bytes([9]) + b[5:], "unsupported measurement format version 9"),
        (lambda b: b + b"junk", "does not match its header"),
        (lambda b: b[:64] + b"bad/id!", "invalid vehicle id"),
    ],
)
def test_malformed_measurements_say_what_is_wrong(mutate, message):
    good = Measurement("veh-001", 1, 0, 10.0, 0.0, 0.0, 0.0).encode()
    with pytest.raises(ProtocolError, match=message):
        Measurement.decode(mutate(good))


@pytest.mark.parametrize("vehicle_id", ["victim-01\n", "victim-01\r", "\nvictim-01", ""])
def test_a_vehicle_id_is_the_whole_string_not_a_prefix_before_a_newline(vehicle_id):
    """``$`` matches before a trailing newline: 'victim-01\\n' was registered and stored as a vehicle."""
    with pytest.raises(ProtocolError, match="invalid vehicle id"):
        check_vehicle_id(vehicle_id)
    header = Measurement("x", 1, 0, 10.0, 0.0, 0.0, 0.0).encode()[:MEASUREMENT_HEADER_SIZE]
    raw = vehicle_id.encode()
    payload = header[:6] + len(raw).to_bytes(2, "little") + header[8:] + raw
    with pytest.raises(ProtocolError, match="invalid vehicle id"):
        Measurement.decode(payload)
    with pytest.raises(ProtocolError):
        parse_vehicle_key(f"agv/v1/{bucket_of(vehicle_id)}/{vehicle_id}/meas")


def test_non_finite_values_survive_decoding_for_the_service_to_reject():
    m = Measurement.decode(Measurement("v1", 1, 0, math.nan, 0.0, math.inf, 0.0).encode())
    assert not m.is_finite()


def test_keys_buckets_and_shards():
    key = vehicle_key("truck-7", "meas")
    assert key == f"agv/v1/{bucket_of('truck-7')}/truck-7/meas"
    assert parse_vehicle_key(key) == ("truck-7", "meas")
    with pytest.raises(ProtocolError):
        parse_vehicle_key("agv/v1/b00/truck-7/other")
    with pytest.raises(ProtocolError):  # a service replica's liveliness token is not a vehicle
        parse_vehicle_key("agv/v1/service/replica-0/alive")
    with pytest.raises(ProtocolError):
        vehicle_key("a/b", "meas")
    shards = [set(shard_buckets(i, 3)) for i in range(3)]
    assert set().union(*shards) == set(all_buckets())
    assert sum(len(s) for s in shards) == len(all_buckets())


def _batch(states: list[list[float]], ids: list[str] | None = None, seq0: int = 1042) -> EstimateBatch:
    n = len(states)
    ids = ids if ids is not None else [f"truck-{k}" if k % 3 else f"a.b_c-{k}" for k in range(n)]
    return EstimateBatch(
        ids,
        np.arange(seq0, seq0 + n, dtype=np.int64),
        np.arange(n, dtype=np.int64) + 1_700_000_010_420_000_000,
        np.array(states, dtype=np.float64).reshape(n, 5),
        np.array([k % 2 == 0 for k in range(n)], dtype=bool),
        np.arange(n, dtype=np.int8) % 4,
        "3f9a1c0b7d2e",
    )


def test_an_estimate_batch_carries_level_codes_and_names_them_only_where_a_document_is_written():
    """The service's detectors give levels as numbers; the batch keeps them so, the JSON documents, the fleet
    stream and Estimate name them, the binary estimate writes the code, and level names in place of codes are
    refused at once rather than written as garbage."""
    from agv_protocol.wire import (
        ESTIMATE_BINARY_HEADER_DTYPE,
        LEVEL_CODES,
        LEVELS,
        decode_binary_estimate,
        encode_binary_estimates,
        level_codes,
    )

    batch = _batch([[float(k)] * 5 for k in range(6)])
    names = [LEVELS[k % 4] for k in range(6)]
    assert batch.level_codes.dtype == np.int8 and batch.levels() == names
    assert batch.levels([4, 1]) == [names[4], names[1]]
    assert [Estimate.decode(d).level for d in batch.documents()] == names
    assert [batch.estimate(k).level for k in range(6)] == names
    (group,) = orjson.loads(encode_fleet_estimates("r", [batch]))["groups"]
    assert group["level"] == names
    assert np.array_equal(EstimateBatch.from_group(group).level_codes, batch.level_codes)
    for k, payload in enumerate(encode_binary_estimates(batch)):
        assert payload[ESTIMATE_BINARY_HEADER_DTYPE.fields["level"][1]] == LEVEL_CODES[names[k]]
        assert decode_binary_estimate(payload, batch.vehicle_ids[k]).level == names[k]
    assert list(level_codes(["STALE", "OK"])) == [3, 0]
    with pytest.raises(KeyError):
        level_codes(["BROKEN"])
    with pytest.raises(TypeError, match="level_codes"):
        EstimateBatch(["a"], batch.seq[:1], batch.t_ns[:1], batch.values[:1], batch.in_domain[:1], ["OK"], "v")
    with pytest.raises(TypeError, match="level_codes"):  # one code per row
        EstimateBatch(["a"], batch.seq[:1], batch.t_ns[:1], batch.values[:1], batch.in_domain[:1], [0, 1], "v")


EXTREME_FLOATS = [10.0, -0.0, 1e-300, -3.25e-7, 29.700000000000003, 1.2345678901234567e8, -math.pi, 5e-324]


def test_the_fast_estimate_encoder_writes_the_estimate_model_exactly():
    """EstimateBatch.documents skips pydantic; each document must decode to the same Estimate, float for float."""
    import json

    from agv_protocol.wire import encode_estimate

    values = EXTREME_FLOATS
    states = [[values[(k + j) % len(values)] for j in range(5)] for k in range(len(values))]
    batch = _batch(states)
    payloads = batch.documents()
    assert len(payloads) == len(states)
    for k, payload in enumerate(payloads):
        json.loads(payload)  # plain JSON, no NaN or Infinity tokens
        e = Estimate.decode(payload)
        assert (e.vehicle, e.seq, e.t_ns, e.in_domain, e.gain_version, e.level) == (
            batch.vehicle_ids[k], 1042 + k, 1_700_000_010_420_000_000 + k, k % 2 == 0, "3f9a1c0b7d2e", batch.levels()[k]
        )  # fmt: skip
        got = [e.vx, e.vy, e.r, e.torque_fault, e.steer_fault]
        assert got == states[k]
        assert [math.copysign(1.0, a) for a in got] == [math.copysign(1.0, b) for b in states[k]]  # -0.0 kept
        assert encode_estimate(e) == payload
    assert batch.documents([5, 2]) == [payloads[5], payloads[2]]  # a subset, in the order asked
    assert batch.documents([]) == []


def test_the_fast_estimate_encoder_refuses_a_field_that_would_break_the_batch():
    with pytest.raises(ValueError, match="contains"):
        _batch([[0.0] * 5] * 2, ids=["a},{b", "c"]).documents()


def test_json_messages_round_trip():
    e = Estimate(
        vehicle="v1",
        seq=3,
        t_ns=5,
        vx=10,
        vy=0.1,
        r=0.0,
        torque_fault=30.0,
        steer_fault=0.01,
        in_domain=True,
        gain_version="abc123",
    )
    assert Estimate.decode(e.encode()) == e
    a = Alarm(
        vehicle="v1", id="al-1", kind="torque_fault", level="FAULT", state="raised", t_ns=1, value=31.0, threshold=20.0
    )
    assert Alarm.decode(a.encode()) == a
    with pytest.raises(ProtocolError, match="invalid Alarm"):
        Alarm.decode(b'{"v": 1, "vehicle": "v1"}')


def test_a_payload_report_is_a_small_json_document_on_the_vehicles_payload_key():
    report = PayloadReport(payload_kg=120.5)
    assert orjson.loads(report.encode()) == {"v": 1, "payload_kg": 120.5}
    assert PayloadReport.decode(b'{"v":1,"payload_kg":0}').payload_kg == 0.0
    for bad in (b'{"v":1,"payload_kg":-1}', b'{"v":1,"payload_kg":"NaN"}', b'{"v":1}', b'{"v":2,"payload_kg":1}', b"x"):
        with pytest.raises(ProtocolError, match="invalid PayloadReport"):
            PayloadReport.decode(bad)
    key = vehicle_key("truck-7", "payload")
    assert key.endswith("/truck-7/payload") and parse_vehicle_key(key) == ("truck-7", "payload")


def test_the_bucket_is_zlibs_crc32_of_the_utf8_id_as_documented():
    import zlib

    for vehicle_id in ("truck-7", "agv-\u00e9-01", "x" * 64):
        assert bucket_of(vehicle_id) == "b%02x" % (zlib.crc32(vehicle_id.encode("utf-8")) % 16)
    assert bucket_of("truck-7") == "b0f"  # the example of docs/protocol.md


def test_a_fleet_message_holds_each_batch_as_columns_that_read_as_the_per_vehicle_documents():
    from agv_protocol.wire import (
        FleetEstimates,
        encode_fleet_estimates,
        fleet_estimates_key,
        fleet_estimates_selector,
        fleet_selector,
    )

    values = EXTREME_FLOATS
    first = _batch([[values[(k + j) % len(values)] for j in range(5)] for k in range(3)], ["a", "b", "c"], 10)
    empty = _batch([], [], 0)
    second = _batch([[1.0, 0.5, -0.25, 30.0, 1e-3]], ["d"], 20)
    second.gain_version = "ab12"
    message = encode_fleet_estimates("replica-1", [first, empty, second])
    decoded = FleetEstimates.decode(message)
    assert decoded.replica == "replica-1"
    assert [g.gain_version for g in decoded.groups] == ["3f9a1c0b7d2e", "ab12"]  # an empty batch is left out
    expected = [Estimate.decode(d) for d in [*first.documents(), *second.documents()]]
    assert decoded.estimates() == expected  # float for float, in order
    assert FleetEstimates.decode(encode_fleet_estimates("replica-1", [])).estimates() == []
    with pytest.raises(ProtocolError, match="every column"):
        FleetEstimates.decode(message.replace(b'"vehicle":["a","b","c"]', b'"vehicle":["a","b"]'))
    with pytest.raises(ProtocolError):
        FleetEstimates.decode(b'{"v":1,"replica":"r","groups":[{"vehicle":[]}]}')
    # a profile stepped twice in one tick (a vehicle with two samples in it) gives two batches of one version:
    # one group, the vehicle's rows in their order, so a reader keying groups by gain version loses nothing
    again = _batch([[2.0, 0.0, 0.0, 1.0, 0.0]], ["a"], 11)
    merged = FleetEstimates.decode(encode_fleet_estimates("replica-1", [first, second, again]))
    assert [g.gain_version for g in merged.groups] == ["3f9a1c0b7d2e", "ab12"]
    assert merged.groups[0].vehicle == ["a", "b", "c", "a"] and merged.groups[0].seq == [10, 11, 12, 11]
    expected = [Estimate.decode(d) for d in [*first.documents(), *again.documents(), *second.documents()]]
    assert merged.estimates() == expected
    # the fleet key is outside every per-vehicle selector, and its selector matches every replica's key
    key = fleet_estimates_key("replica-1")
    assert key == "agv/v1/service/replica-1/estimates"
    assert not zenoh_intersects(fleet_selector("estimate"), key)
    assert zenoh_intersects(fleet_estimates_selector(), key)


def zenoh_intersects(selector: str, key: str) -> bool:
    import zenoh

    return bool(zenoh.KeyExpr(selector).intersects(zenoh.KeyExpr(key)))


def test_every_encoding_of_the_estimate_takes_its_fields_from_the_one_record():
    """The per-vehicle document, the fleet stream's group, the REST row, the ground truth and the dashboard's plot
    columns all carry exactly the fields of the record (agv_protocol.wire's Estimate and its bases): a field added
    there reaches every encoding, and none of them can spell out a field of its own."""
    from agv_protocol.wire import (
        EFFECTIVENESS_COLUMNS,
        ESTIMATE_COLUMNS,
        STATE_COLUMNS,
        EstimateRow,
        FleetEstimateGroup,
        GroundTruth,
    )
    from service.web.hub import POINT_COLUMNS, TRUTH_COLUMNS

    state_only = _batch([[1.0, 2.0, 3.0, 4.0, 5.0]] * 3)
    document = orjson.loads(state_only.documents()[0])  # a profile without the effectiveness stage
    assert list(document) == [f for f in Estimate.model_fields if f not in {*EFFECTIVENESS_COLUMNS, "gain_set", "rev"}]
    batch = _batch([[1.0, 2.0, 3.0, 4.0, 5.0]] * 3)
    batch.values = np.tile(np.arange(1.0, len(ESTIMATE_COLUMNS) + 1.0), (3, 1))
    batch.columns = ESTIMATE_COLUMNS
    batch.fast = np.array([True, False, True])
    document = orjson.loads(batch.documents()[0])
    assert list(document) == list(Estimate.model_fields)  # every field, in the record's order
    assert [document[c] for c in ESTIMATE_COLUMNS] == list(range(1, len(ESTIMATE_COLUMNS) + 1))
    group = FleetEstimates.decode(encode_fleet_estimates("r0", [batch])).groups[0]
    assert set(group.model_dump(exclude_none=True)) == set(FleetEstimateGroup.model_fields)
    assert set(FleetEstimateGroup.model_fields) == set(Estimate.model_fields) - {"v"}
    assert set(EstimateRow.model_fields) < set(Estimate.model_fields)
    assert [e.model_dump() for e in group.estimates()] == [Estimate.decode(d).model_dump() for d in batch.documents()]
    assert batch.estimate(1) == Estimate.decode(batch.documents()[1])
    assert ESTIMATE_COLUMNS[: len(STATE_COLUMNS)] == STATE_COLUMNS
    assert set(GroundTruth.model_fields) - set(STATE_COLUMNS) == {"v", "vehicle", "seq", "t_ns"}
    assert POINT_COLUMNS[3:] == ESTIMATE_COLUMNS and TRUTH_COLUMNS[1:] == STATE_COLUMNS


# --------------------------------------------------------------------------- revisions of the estimate record


#: The fields of an estimate document of revision 1.0 (before the effectiveness fields and ``rev``).
FIELDS_1_0 = ("v", "vehicle", "seq", "t_ns", "vx", "vy", "r", "torque_fault", "steer_fault", "in_domain",
              "gain_version", "level", "gain_set")  # fmt: skip


def _reader_1_0() -> type[BaseModel]:
    """A strict reader built on revision 1.0 of the record: its fields, unknown fields forbidden."""
    from pydantic import ConfigDict, create_model

    fields = {
        name: (Estimate.model_fields[name].annotation, Estimate.model_fields[name].default) for name in FIELDS_1_0
    }
    fields["vehicle"] = (str, ...)
    return create_model("Estimate10", __config__=ConfigDict(extra="forbid"), **fields)  # type: ignore[call-overload]


def _effectiveness_batch() -> EstimateBatch:
    from agv_protocol.wire import ESTIMATE_COLUMNS

    batch = _batch([[1.0, 2.0, 3.0, 4.0, 5.0]] * 2)
    batch.values = np.tile(np.arange(1.0, len(ESTIMATE_COLUMNS) + 1.0), (2, 1))
    batch.columns = ESTIMATE_COLUMNS
    return batch


def test_a_document_names_the_revision_of_the_fields_it_carries_and_a_1_0_reader_reads_the_others():
    """Documents without the effectiveness fields are revision 1.0, byte for byte without ``rev``: a strict 1.0
    reader reads them. Documents with them say "rev": 1 (document and fleet-stream group alike); a strict 1.0
    reader refuses them, and can tell why from ``rev`` before it validates."""
    reader = _reader_1_0()
    plain = _batch([[1.0, 2.0, 3.0, 4.0, 5.0]] * 2)
    for payload in plain.documents():
        assert b'"rev"' not in payload
        assert reader.model_validate_json(payload).model_dump() == {
            k: v for k, v in Estimate.decode(payload).model_dump().items() if k in FIELDS_1_0
        }
    with_alpha = _effectiveness_batch()
    for payload in with_alpha.documents():
        document = orjson.loads(payload)
        assert document["rev"] == 1 and Estimate.decode(payload).rev == 1
        with pytest.raises(ValueError, match="Extra inputs are not permitted"):
            reader.model_validate_json(payload)
    other = _batch([[1.0] * 5], seq0=7)
    other.gain_version = "0123456789ab"
    message = encode_fleet_estimates("r0", [with_alpha, other])
    assert [g.get("rev") for g in orjson.loads(message)["groups"]] == [1, None]
    decoded = FleetEstimates.decode(message).estimates()
    assert [e.rev for e in decoded] == [1, 1, None]
    assert (
        decoded[:2]
        == [Estimate.decode(d) for d in with_alpha.documents()]
        == [with_alpha.estimate(0), with_alpha.estimate(1)]
    )


def test_a_reader_drops_the_fields_of_a_newer_revision_and_refuses_unknown_fields_of_a_known_one():
    """Estimate.decode and FleetEstimates.decode read a document (group) of a revision newer than they know for
    the fields they know; at a revision they know, an unknown field is still an error (a typo is not an
    addition)."""
    from agv_protocol.wire import ESTIMATE_REVISION

    payload = _effectiveness_batch().documents()[0]
    newer = payload.replace(b'"rev":1', f'"rev":{ESTIMATE_REVISION + 1},"torque_jerk":1.5'.encode())
    estimate = Estimate.decode(newer)
    assert estimate.rev == ESTIMATE_REVISION + 1
    assert estimate.model_dump(exclude={"rev"}) == Estimate.decode(payload).model_dump(exclude={"rev"})
    with pytest.raises(ProtocolError, match="torque_jerk"):
        Estimate.decode(payload.replace(b'"rev":1', b'"rev":1,"torque_jerk":1.5'))
    with pytest.raises(ProtocolError, match="torque_jerk"):
        Estimate.decode(payload.replace(b'"rev":1', b'"torque_jerk":1.5'))
    message = encode_fleet_estimates("r0", [_effectiveness_batch()])
    newer = message.replace(b'"rev":1', f'"rev":{ESTIMATE_REVISION + 1},"torque_jerk":[1.0,2.0]'.encode())
    assert [e.torque_alpha for e in FleetEstimates.decode(newer).estimates()] == [8.0, 8.0]
    with pytest.raises(ProtocolError, match="torque_jerk"):
        FleetEstimates.decode(message.replace(b'"rev":1', b'"rev":1,"torque_jerk":[1.0,2.0]'))
