"""The real service: uvicorn on a free port, Zenoh on loopback, SQLite in tmp_path.

Assertions are on counts, order and equality, never on speed: the machine is shared.
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np
import pytest

from agv_protocol.wire import FLAG_SEQUENCE_RESTART, Measurement, ProtocolError, vehicle_key
from edge_client.library import paper_1
from edge_client.transport import report_payload
from service.main import create_app
from service.profiles import ProfileSpec
from synth.gains import ObserverGains
from synth.observer import FuzzyObserver
from tests.service.helpers import (
    FAST_DESIGN,
    PERIOD_NS,
    T0_NS,
    as_array,
    constant_measurement,
    make_settings,
    parse_metrics,
    plant_measurements,
    probe,
    running,
    wait_for,
)
from tests.tolerances import BATCH_EQUALITY_ATOL

pytestmark = pytest.mark.network

ALARMS = {
    "torque_warn_nm": 10.0,
    "torque_fault_nm": 20.0,
    "raise_after_s": 0.2,
    "clear_after_s": 0.5,
    "warmup_s": 1.0,
    "stale_after_s": 2.0,
}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("svc")
    settings = make_settings(tmp, {"default": {"design": FAST_DESIGN, "alarms": ALARMS}})
    with running(settings) as srv:
        yield srv


@pytest.fixture
def zprobe(server):
    with probe(server.settings.zenoh.endpoint) as p:
        yield p


def test_measurements_in_estimates_out(server, zprobe):
    ids = ["e2e-a", "e2e-b"]
    samples = plant_measurements(ids, 300)
    for row in samples:
        for m in row:
            zprobe.put(m)
    wait_for(lambda: all(len(zprobe.estimates_of(v)) >= 300 for v in ids), what="600 estimates")
    gains_doc = server.get("/profiles/default/gains", params={"matrices": "true"}).json()
    gains = ObserverGains.from_dict(gains_doc)  # the answer is a loadable gains document
    observer = FuzzyObserver(gains, np.array([[m.vx_mps, m.r_radps] for m in samples[0]]))
    expected = [
        observer.step([[m.vx_mps, m.r_radps] for m in row], [[m.torque_nm, m.steer_rad] for m in row]).x_hat[:, :5]
        for row in samples
    ]
    for i, vid in enumerate(ids):
        got = zprobe.estimates_of(vid)
        assert [e.seq for e in got] == list(range(300))  # every sample answered, in order
        assert {e.gain_version for e in got} == {gains_doc["version"]}
        np.testing.assert_allclose(as_array(got), np.array([x[i] for x in expected]), atol=BATCH_EQUALITY_ATOL)
    detail = server.vehicle("e2e-a")
    assert detail["latest_estimate"]["seq"] == 299 and detail["counters"]["accepted"] == 300
    history = server.get("/vehicles/e2e-a/estimates", params={"limit": 50}).json()["estimates"]
    assert [h["seq"] for h in history] == list(range(250, 300))


def test_every_bad_input_class_is_rejected_counted_and_leaves_the_state_intact(server, zprobe):
    good = plant_measurements(["bad-1"], 100)
    ref = plant_measurements(["ref-1"], 100)
    for k in range(50):
        zprobe.put(good[k][0])
        zprobe.put(ref[k][0])
    key = vehicle_key("bad-1", "meas")
    last = good[49][0]
    bad = [
        ("duplicate", key, last.encode()),
        ("out_of_order", key, good[10][0].encode()),
        ("malformed", key, last.encode()[:40]),
        ("malformed", key, b"XXXX" + last.encode()[4:]),
        ("id_mismatch", key, Measurement("ref-1", 50, 0, 10.0, 0.0, 0.0, 0.0).encode()),
        ("non_finite", key, Measurement("bad-1", 50, 0, math.nan, 0.0, 0.0, 0.0).encode()),
        ("out_of_range", key, Measurement("bad-1", 51, 0, 10.0, 9.0, 0.0, 0.0).encode()),
        ("malformed", "agv/v1/b00/bad-1/meas" if "b00" not in key else "agv/v1/b01/bad-1/meas", last.encode()),
    ]
    for _, k, payload in bad:
        zprobe.put_raw(k, payload)
    for k in range(52, 100):  # the two rejected samples took seq 50 and 51
        zprobe.put(good[k][0])
    for k in range(50, 100):
        zprobe.put(ref[k][0])
    wait_for(
        lambda: len(zprobe.estimates_of("bad-1")) >= 98 and len(zprobe.estimates_of("ref-1")) >= 100, what="estimates"
    )
    status = server.vehicle("bad-1")
    # every reject of its samples is in its own counters, the wrong bucket's too (3 malformed)
    expected = {"malformed": 3, "id_mismatch": 1, "non_finite": 1, "out_of_range": 1, "duplicate": 1, "out_of_order": 1}
    assert {k: v for k, v in status["rejected"].items() if v} == expected
    # the two rejected samples never reached the observer: two missing samples, no restart
    assert status["counters"]["missing"] == 2 and status["counters"]["restarts"] == 0
    metrics = server.get("/metrics").text
    for reason in expected:
        assert f'agv_fe_measurements_rejected_total{{reason="{reason}"}}' in metrics
    # both vehicles saw the same good samples up to 49; then bad-1 lost 50 and 51 to rejection
    bad_est = {e.seq: e for e in zprobe.estimates_of("bad-1")}
    ref_est = {e.seq: e for e in zprobe.estimates_of("ref-1")}
    for k in range(50):
        np.testing.assert_allclose(as_array([bad_est[k]]), as_array([ref_est[k]]), atol=BATCH_EQUALITY_ATOL)
    assert sorted(bad_est) == [*range(50), *range(52, 100)]
    assert all(math.isfinite(e.torque_fault) for e in bad_est.values())
    # state intact: every estimate equals an offline observer fed the good samples only (50 and 51 lost)
    gains = ObserverGains.from_dict(server.get("/profiles/default/gains", params={"matrices": "true"}).json())
    kept = [good[k][0] for k in (*range(50), *range(52, 100))]
    observer = FuzzyObserver(gains, np.array([[kept[0].vx_mps, kept[0].r_radps]]))
    offline = [observer.step([[m.vx_mps, m.r_radps]], [[m.torque_nm, m.steer_rad]]).x_hat[0, :5] for m in kept]
    got = as_array([bad_est[m.seq] for m in kept])
    np.testing.assert_allclose(got, np.array(offline), atol=BATCH_EQUALITY_ATOL)


def test_alarm_raised_published_stored_latched_and_acknowledged(server, zprobe, caplog):
    caplog.set_level(logging.INFO, logger="agv_fe.events")
    for row in plant_measurements(["faulty-1"], 900, scenario=paper_1()):  # 30 N m torque bias from 5 s
        zprobe.put(row[0])
    wait_for(lambda: len(zprobe.estimates_of("faulty-1")) >= 900, what="estimates")
    raised = wait_for(
        lambda: [a for a in zprobe.collect().alarms if a.vehicle == "faulty-1" and a.kind == "torque_fault"],
        what="torque alarm on Zenoh",
    )
    alarm_id = raised[0].id
    assert raised[0].state == "raised" and raised[-1].level == "FAULT"
    assert zprobe.estimates_of("faulty-1")[-1].level == "FAULT"
    listed = {a["id"]: a for a in server.get("/alarms").json()}
    assert listed[alarm_id]["latched"] and not listed[alarm_id]["acknowledged"]
    denied = server.http.post(f"/alarms/{alarm_id}/ack")
    assert denied.status_code == 401 and denied.headers["www-authenticate"].startswith("Bearer")
    wrong = server.http.post(f"/alarms/{alarm_id}/ack", headers={"Authorization": "Bearer nope"})
    assert wrong.status_code == 401
    ok = server.http.post(f"/alarms/{alarm_id}/ack", headers=server.auth, json={"by": "test"})
    assert ok.status_code == 200 and ok.json()["acknowledged"] and ok.json()["latched"]  # condition still holds
    wait_for(lambda: any(a.id == alarm_id and a.state == "acknowledged" for a in zprobe.collect().alarms), what="ack")
    events = server.get(f"/alarms/{alarm_id}").json()["events"]
    assert events[0]["state"] == "raised" and events[-1]["state"] == "acknowledged"
    # every transition is also a log event with its fields: raised (WARN, then FAULT), acknowledged
    logged = wait_for(
        lambda: (
            [
                (r.fields["state"], r.fields["level"])  # type: ignore[attr-defined]
                for r in caplog.records
                if r.name == "agv_fe.events" and getattr(r, "fields", {}).get("id") == alarm_id
            ]
            or None
        ),
        what="alarm events in the log",
    )
    assert logged[0][0] == "raised" and ("raised", "FAULT") in logged and logged[-1][0] == "acknowledged"
    assert server.http.post("/alarms/al-unknown/ack", headers=server.auth).status_code == 404


def test_a_forged_sequence_number_is_refused_and_late_samples_raise_an_alarm(server, zprobe):
    """One put of seq 2^64 - 1 on a vehicle's key between its genuine samples: refused as implausible_seq, nothing
    missing, no genuine sample lost. A forgery whose time stamp agrees with its seq is believed, and the genuine
    samples after it are late: after sequence_reject_count of them in a row the vehicle raises sequence_rejected,
    stored and published on Zenoh, which clears when the vehicle restarts its sequence."""
    vid = "forged-1"
    for k in range(30):
        zprobe.put(constant_measurement(vid, k))
    zprobe.put(Measurement(vid, (1 << 64) - 1, T0_NS + 30 * PERIOD_NS, 10.0, 0.0, 60.0, 0.0))
    for k in range(30, 60):
        zprobe.put(constant_measurement(vid, k))
    wait_for(lambda: len(zprobe.estimates_of(vid)) >= 60, what="every genuine sample's estimate")
    status = server.vehicle(vid)
    assert status["rejected"]["implausible_seq"] == 1 and status["rejected"]["out_of_order"] == 0
    assert status["counters"]["missing"] == 0 and status["last_seq"] == 59
    assert all(a.vehicle != vid for a in zprobe.collect().alarms)
    count = ProfileSpec.model_validate({}).alarms.sequence_reject_count
    zprobe.put(constant_measurement(vid, 10**9))  # seq and time stamp forged together
    for k in range(60, 60 + count):
        zprobe.put(constant_measurement(vid, k))
    raised = wait_for(
        lambda: [a for a in zprobe.collect().alarms if a.vehicle == vid and a.kind == "sequence_rejected"],
        what="sequence_rejected on Zenoh",
    )
    assert raised[0].state == "raised" and raised[0].level == "WARN" and raised[0].value == count
    assert server.vehicle(vid)["rejected"]["out_of_order"] == count
    stored = [a for a in server.get("/alarms", params={"vehicle": vid}).json() if a["kind"] == "sequence_rejected"]
    assert [a["id"] for a in stored] == [raised[0].id] and stored[0]["latched"]
    zprobe.put(Measurement(vid, 0, T0_NS + 200 * PERIOD_NS, 10.0, 0.0, 60.0, 0.0, flags=FLAG_SEQUENCE_RESTART))
    wait_for(
        lambda: any(a.id == raised[0].id and a.state == "cleared" for a in zprobe.collect().alarms),
        what="sequence_rejected cleared",
    )
    assert server.vehicle(vid)["last_seq"] == 0


def test_stale_by_lost_liveliness_and_by_timeout(server, zprobe):
    token = zprobe.session.liveliness().declare_token(vehicle_key("live-1", "alive"))
    for k in range(20):
        zprobe.put(constant_measurement("live-1", k))
        zprobe.put(constant_measurement("quiet-1", k))
    wait_for(lambda: server.get("/vehicles/live-1").json().get("alive") is True, what="liveliness seen")
    token.undeclare()
    lost = wait_for(
        lambda: [a for a in zprobe.collect().alarms if a.vehicle == "live-1" and a.kind == "stale"], what="stale"
    )
    assert lost[0].level == "STALE" and "liveliness" in lost[0].message
    quiet = wait_for(
        lambda: [a for a in zprobe.collect().alarms if a.vehicle == "quiet-1" and a.kind == "stale"], what="timeout"
    )
    assert "no measurement" in quiet[0].message and server.vehicle("quiet-1")["level"] == "STALE"
    zprobe.put(constant_measurement("quiet-1", 20))
    wait_for(
        lambda: any(a.vehicle == "quiet-1" and a.state == "cleared" for a in zprobe.collect().alarms), what="resumed"
    )


def test_rest_errors_say_what_is_wrong(server):
    r = server.get("/vehicles/nobody")
    assert r.status_code == 404 and "nobody" in r.json()["detail"]
    assert server.get("/profiles/nothing").status_code == 404
    assert server.get("/jobs/job-none").status_code == 404
    assert server.get("/alarms/al-none").status_code == 404
    r = server.http.put("/profiles/van", json={"params": {"mass_kg": -3}}, headers=server.auth)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"][-2:] == ["params", "mass_kg"]
    r = server.http.put("/profiles/van", json={"alarms": {"torque_warn_nm": 500}}, headers=server.auth)
    assert r.status_code == 422 and "torque_warn_nm" in r.text
    r = server.http.put("/profiles/van", json={})
    assert r.status_code == 401 and r.headers["www-authenticate"] == "Bearer"
    assert server.http.post("/profiles/default/synthesis").status_code == 401
    assert server.http.put("/vehicles/x", json={"profile": "default"}).status_code == 401
    r = server.http.put("/vehicles/x", json={"profile": "nope"}, headers=server.auth)
    assert r.status_code == 404 and "nope" in r.json()["detail"]
    assert server.get("/health").json()["status"] == "ok"


def test_a_vehicles_payload_is_reported_shown_and_checked(server):
    assert server.http.put("/vehicles/loaded-1", json={"profile": "default"}, headers=server.auth).status_code == 200
    assert server.http.put("/vehicles/loaded-1/payload", json={"payload_kg": 80.0}).status_code == 401
    r = server.http.put("/vehicles/loaded-1/payload", json={"payload_kg": 80.0}, headers=server.auth)
    assert r.status_code == 200 and r.json()["payload_kg"] == 80.0
    assert server.get("/vehicles/loaded-1").json()["payload_kg"] == 80.0
    for body in ({"payload_kg": -5}, {"payload_kg": "nan"}, {"payload_kg": 80.0, "unit": "lb"}, {}):
        r = server.http.put("/vehicles/loaded-1/payload", json=body, headers=server.auth)
        assert r.status_code == 422, body
    r = server.http.put("/vehicles/loaded-1/payload", json={"payload_kg": 1e6}, headers=server.auth)
    assert r.status_code == 422 and "at most the vehicle's mass" in r.json()["detail"]
    r = server.http.put("/vehicles/nobody/payload", json={"payload_kg": 1.0}, headers=server.auth)
    assert r.status_code == 404 and "nobody" in r.json()["detail"]
    assert server.get("/vehicles/loaded-1").json()["payload_kg"] == 80.0  # the refusals changed nothing


def test_a_vehicle_reports_its_own_payload_on_its_payload_key(server, zprobe):
    """The vehicle puts a PayloadReport on its own key (edge_client.transport.report_payload): applied as the
    REST route applies it, the vehicle registered if it was not; a malformed or too heavy report is counted by
    its outcome and changes nothing."""

    def outcome(name: str) -> float:
        metrics = parse_metrics(server.get("/metrics").text)
        return metrics.samples.get(("agv_fe_payload_reports_total", frozenset({("outcome", name)})), 0.0)

    before = {name: outcome(name) for name in ("applied", "malformed", "out_of_range")}
    assert report_payload(zprobe.session, "self-loading-1", 65.0)
    wait_for(
        lambda: (
            server.http.get("/vehicles/self-loading-1").status_code == 200
            and server.vehicle("self-loading-1")["payload_kg"] == 65.0
        ),
        what="the reported payload",
    )
    zprobe.put_raw(vehicle_key("self-loading-1", "payload"), b'{"v":1,"payload_kg":"lots"}')
    assert report_payload(zprobe.session, "self-loading-1", 1e6)
    wait_for(lambda: outcome("out_of_range") == before["out_of_range"] + 1, what="the too heavy report counted")
    assert outcome("malformed") == before["malformed"] + 1 and outcome("applied") == before["applied"] + 1
    assert server.vehicle("self-loading-1")["payload_kg"] == 65.0
    with pytest.raises(ProtocolError, match="payload_kg"):
        report_payload(zprobe.session, "self-loading-1", -3.0)


def test_replicas_lists_the_live_ones_by_their_liveliness_tokens(server):
    answer = server.get("/replicas").json()
    assert answer == {"replica": "replica-0", "replicas": ["replica-0"], "lease_replicas": None} | {
        "unowned_buckets": None  # no shared database: not known
    }


def test_openapi_documents_every_route_with_examples(server):
    spec = server.get("/openapi.json").json()
    paths = set(spec["paths"])
    for path in (
        "/vehicles/{vehicle_id}/estimates",
        "/alarms/{alarm_id}/ack",
        "/profiles/{name}/gains",
        "/jobs/{job_id}",
    ):
        assert path in paths
    schemas = spec["components"]["schemas"]
    for name in ("ProfileSpec", "Estimate", "VehicleStatus", "AlarmInfo", "JobInfo", "GainsInfo"):
        assert schemas[name].get("examples"), name
    assert spec["components"]["securitySchemes"]["HTTPBearer"]["scheme"] == "bearer"
    listing = spec["paths"]["/vehicles"]["get"]
    parameters = {p["name"]: p for p in listing["parameters"]}
    assert set(parameters) == {"profile", "level", "limit", "after"}
    assert all(p["schema"].get("examples") for p in parameters.values())
    assert "Link" in listing["responses"]["200"]["headers"] and "404" in listing["responses"]


def _secured(spec: dict) -> dict[tuple[str, str], bool]:
    return {
        (method, path): bool(op.get("security"))
        for path, item in spec["paths"].items()
        for method, op in item.items()
        if method in ("get", "put", "post", "delete")
    }


def test_openapi_marks_only_what_needs_the_token_as_secured(server, tmp_path):
    """Reads are open by default: their operations carry no security requirement, while every mutating one does;
    with auth.open_reads = false the reads need the token too, and say so."""
    secured = _secured(server.get("/openapi.json").json())
    for (method, path), needs_token in secured.items():
        assert needs_token == (method != "get"), (method, path)
    assert ("get", "/vehicles") in secured and ("put", "/profiles/{name}") in secured
    closed = create_app(make_settings(tmp_path, auth={"open_reads": False}))
    closed_secured = _secured(closed.openapi())
    health = {"/health", "/ready", "/replicas", "/metrics", "/"}
    for (method, path), needs_token in closed_secured.items():
        assert needs_token == (path not in health), (method, path)


def test_unknown_vehicles_are_rejected_when_the_setting_says_so(tmp_path):
    settings = make_settings(tmp_path, ingest={"unknown_vehicles": "reject"})
    with running(settings) as srv, probe(settings.zenoh.endpoint) as p:
        r = srv.http.put("/vehicles/known-1", json={"profile": "default"}, headers=srv.auth)
        assert r.status_code == 200
        for k in range(10):
            p.put(constant_measurement("stranger-1", k))
            p.put(constant_measurement("known-1", k))
        wait_for(lambda: len(p.estimates_of("known-1")) >= 10, what="estimates")
        line = 'agv_fe_measurements_rejected_total{reason="unknown_vehicle"} 10'
        wait_for(lambda: line in srv.get("/metrics").text, what="10 unknown-vehicle rejects")
        assert srv.get("/vehicles/stranger-1").status_code == 404
        assert p.estimates_of("stranger-1") == []


@pytest.mark.parametrize("vehicle_estimates", ["always", "subscribed"])
def test_the_fleet_stream_carries_every_estimate_once_and_vehicle_keys_follow_the_setting(
    server, tmp_path, vehicle_estimates
):
    """One FleetEstimates message per tick holds every estimate. With vehicle_estimates='always', vehicle keys
    get every estimate; with 'subscribed' (the default), a key nobody subscribes to gets none until someone
    does, and the change is applied at the next tick: the housekeeping pass is set to run once an hour
    here, so everything this test waits for comes from the ingest loop."""
    assert server.settings.zenoh.vehicle_estimates == "subscribed"  # the default
    if vehicle_estimates == "subscribed":
        settings = make_settings(tmp_path, ingest={"housekeeping_interval_s": 3600.0})
        with running(settings) as own:
            _fleet_stream_case(own, skips=True)
    else:
        settings = make_settings(tmp_path, zenoh={"vehicle_estimates": "always"})
        with running(settings) as own:
            _fleet_stream_case(own, skips=False)


def _fleet_stream_case(server, skips: bool) -> None:
    import zenoh

    from agv_protocol.wire import FleetEstimates, fleet_estimates_selector
    from service.transport import MATCH_SETTLE_S, open_session
    from tests.service.helpers import parse_metrics

    ids = ["fleet-a", "fleet-b", "fleet-c"]
    session = open_session("client", server.settings.zenoh.endpoint)
    fleet = session.declare_subscriber(fleet_estimates_selector(), zenoh.handlers.FifoChannel(1 << 16))
    pubs = {
        v: session.declare_publisher(vehicle_key(v, "meas"), congestion_control=zenoh.CongestionControl.BLOCK)
        for v in ids
    }
    got: list[tuple[str, int]] = []
    replicas: set[str] = set()

    def drain() -> int:
        while (s := fleet.try_recv()) is not None:
            message = FleetEstimates.decode(s.payload.to_bytes())
            replicas.add(message.replica)
            got.extend((e.vehicle, e.seq) for e in message.estimates() if e.vehicle in ids)
        return len(got)

    def send(seqs: range) -> None:
        for k in seqs:
            for v in ids:
                pubs[v].put(constant_measurement(v, k).encode())

    def counters() -> tuple[float, float, float]:
        m = parse_metrics(server.get("/metrics").text)
        return (
            m.value("agv_fe_estimates_published_total", encoding="json"),
            m.value("agv_fe_fleet_estimates_published_total"),
            m.value("agv_fe_estimate_keys_unmatched"),
        )

    watcher = None
    try:
        time.sleep(0.3)  # the subscription reaches the router
        send(range(200))
        wait_for(lambda: drain() >= 600, what="600 estimates in fleet messages")
        assert len(got) == len(set(got)) == 600  # each estimate exactly once
        for v in ids:
            assert [k for vid, k in got if vid == v] == list(range(200))  # in order
        assert replicas == {server.service.replica_id}
        if not skips:  # 'always': every estimate on its vehicle's key too, watched or not
            time.sleep(MATCH_SETTLE_S + 0.3)
            per_vehicle0, _, unmatched = counters()
            send(range(200, 300))
            wait_for(lambda: drain() >= 900, what="300 more estimates in fleet messages")
            wait_for(lambda: counters()[0] >= per_vehicle0 + 300, what="300 more estimates on the vehicle keys")
            assert unmatched == 0
            return
        # nobody subscribes to these vehicles' own keys: once the service has looked, it stops sending there
        time.sleep(MATCH_SETTLE_S + 0.3)
        wait_for(lambda: counters()[2] >= len(ids), what="the three keys seen unmatched")
        per_vehicle0, in_fleet0, _ = counters()
        send(range(200, 300))
        wait_for(lambda: drain() >= 900, what="300 more estimates in fleet messages")
        per_vehicle1, in_fleet1, _ = counters()
        assert per_vehicle1 == per_vehicle0 and in_fleet1 - in_fleet0 >= 300
        # a subscriber to one vehicle's key gets its estimates again
        watcher = session.declare_subscriber(vehicle_key("fleet-a", "estimate"), zenoh.handlers.FifoChannel(1 << 16))
        seqs = iter(range(300, 100_000))

        def watched() -> bool:
            k = next(seqs)
            send(range(k, k + 1))  # keep the vehicles sending while waiting
            return watcher.try_recv() is not None

        wait_for(watched, what="fleet-a's estimates on its own key")
        per_vehicle2, _, unmatched2 = counters()
        assert per_vehicle2 > per_vehicle1 and unmatched2 >= len(ids) - 1
        # the subscriber leaves: the service sees it go and stops sending there again
        watcher.undeclare()
        watcher = None
        wait_for(lambda: counters()[2] >= len(ids), what="fleet-a's key unmatched again")
        per_vehicle3, in_fleet3, _ = counters()
        send(range(100_000, 100_100))
        wait_for(lambda: counters()[1] >= in_fleet3 + 300, what="300 more estimates in fleet messages")
        assert counters()[0] == per_vehicle3
    finally:
        for entity in [fleet, *pubs.values(), *([watcher] if watcher is not None else [])]:
            entity.undeclare()
        session.close()
