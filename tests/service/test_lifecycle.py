"""Resynthesis under load, infeasible designs, restarts and two-replica sharding, with the real service."""

from __future__ import annotations

import threading
import time

import pytest

from agv_protocol.wire import service_liveliness_selector
from service.transport import open_session
from tests.service.helpers import (
    FAST_DESIGN,
    constant_measurement,
    free_port,
    job_done,
    make_settings,
    plant_measurements,
    probe,
    running,
    wait_for,
)

pytestmark = pytest.mark.network

#: Load of the resynthesis test: vehicles at 100 Hz, bounded in time and count.
LOAD_VEHICLES = 20
LOAD_MAX_S = 40.0


def test_resynthesis_under_load_misses_no_sample_and_infeasible_designs_keep_the_gains(tmp_path):
    settings = make_settings(tmp_path)
    with running(settings) as srv, probe(settings.zenoh.endpoint) as p:
        old = srv.get("/profiles/default").json()["active_version"]
        ids = [f"load-{i:02d}" for i in range(LOAD_VEHICLES)]
        sent = {"n": 0}
        stop = threading.Event()

        def feed() -> None:  # 100 Hz per vehicle until told to stop, bounded by LOAD_MAX_S
            start = time.monotonic()
            k = 0
            while not stop.is_set() and time.monotonic() - start < LOAD_MAX_S:
                for vid in ids:
                    p.put(constant_measurement(vid, k, vx=12.0, r=0.05, torque=80.0))
                k += 1
                sent["n"] = k
                time.sleep(max(0.0, start + k * 0.01 - time.monotonic()))

        feeder = threading.Thread(target=feed, daemon=True)
        feeder.start()
        try:
            wait_for(lambda: sent["n"] > 50, what="load started")
            auth = srv.auth
            # three requests in a row: the first runs, the second is queued, the third supersedes the second
            first = srv.http.put("/profiles/default", json={"design": {**FAST_DESIGN, "fault_order": 2}}, headers=auth)
            second = srv.http.put("/profiles/default", json={"design": {**FAST_DESIGN, "fault_order": 3}}, headers=auth)
            third = srv.http.put(
                "/profiles/default", json={"design": FAST_DESIGN | {"fault_order": 2, "margin": 2e-5}}, headers=auth
            )
            assert [r.status_code for r in (first, second, third)] == [202, 202, 202]
            assert first.headers["location"] == f"/jobs/{first.json()['job']}"
            jobs = [wait_for(lambda r=r: job_done(srv, r.json()["job"]), what="job") for r in (first, second, third)]
            assert [j["status"] for j in jobs] == ["succeeded", "superseded", "succeeded"]
            assert jobs[1]["superseded_by"] == jobs[2]["id"]
            assert jobs[2]["certificate"]["verified"] and jobs[2]["gain_version"] != old
            active = srv.get("/profiles/default").json()
            assert active["active_version"] == jobs[2]["gain_version"] and active["spec"]["design"]["margin"] == 2e-5
            # an impossible design fails with the reason and keeps the gains
            bad = srv.http.put(
                "/profiles/default", json={"design": {**FAST_DESIGN, "design": "paper-decoupled"}}, headers=auth
            )
            failed = wait_for(lambda: job_done(srv, bad.json()["job"]), what="infeasible job")
            assert (
                failed["status"] == "failed" and failed["error"] == "infeasible" and "unobservable" in failed["reason"]
            )
            assert srv.get("/profiles/default").json()["active_version"] == jobs[2]["gain_version"]
            assert srv.get("/ready").json()["ready"]
            time.sleep(0.5)
        finally:
            stop.set()
            feeder.join(LOAD_MAX_S)
        n = sent["n"]
        wait_for(lambda: all(len(p.estimates_of(v)) >= n for v in ids), what="every estimate")
        versions = set()
        for vid in ids:
            est = p.estimates_of(vid)
            assert [e.seq for e in est] == list(range(n)), vid  # zero missed samples, in order
            versions.update(e.gain_version for e in est)
        assert versions == {old, jobs[0]["gain_version"], jobs[2]["gain_version"]}
        metrics = srv.get("/metrics").text
        assert "agv_fe_samples_missing_total 0" in metrics
        assert 'agv_fe_synthesis_jobs_total{status="failed"} 1' in metrics
        assert all(srv.vehicle(v)["counters"]["accepted"] == n for v in ids)


def test_restart_keeps_gains_alarms_vehicles_and_payloads_without_resynthesis(tmp_path):
    alarms = {"torque_warn_nm": 10.0, "torque_fault_nm": 20.0, "raise_after_s": 0.2, "warmup_s": 1.0}
    settings = make_settings(tmp_path, {"default": {"design": FAST_DESIGN, "alarms": alarms}})
    with running(settings) as srv, probe(settings.zenoh.endpoint) as p:
        version = srv.get("/profiles/default").json()["active_version"]
        for row in plant_measurements(["keep-1"], 900):
            p.put(row[0])
        alarm = wait_for(lambda: [a for a in srv.get("/alarms").json() if a["kind"] == "torque_fault"], what="alarm")[0]
        acked = srv.http.post(f"/alarms/{alarm['id']}/ack", headers=srv.auth, json={"by": "night shift"})
        assert acked.status_code == 200
        loaded = srv.http.put("/vehicles/keep-1/payload", json={"payload_kg": 95.0}, headers=srv.auth)
        assert loaded.status_code == 200 and loaded.json()["payload_kg"] == 95.0
        jobs_before = srv.get("/jobs").json()
    # the process is gone; a new one reads the same data directory
    with running(settings) as srv:
        assert srv.get("/profiles/default").json()["active_version"] == version
        assert srv.get("/jobs").json() == jobs_before  # no new synthesis
        latched = {a["id"]: a for a in srv.get("/alarms").json()}
        assert latched[alarm["id"]]["acknowledged"] and latched[alarm["id"]]["acknowledged_by"] == "night shift"
        assert srv.vehicle("keep-1")["profile"] == "default"
        assert srv.vehicle("keep-1")["payload_kg"] == 95.0  # the stored payload applies again


def test_two_replicas_share_the_fleet_each_vehicle_handled_by_exactly_one(tmp_path):
    router_endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session("router", router_endpoint)
    try:
        replicas = [
            make_settings(
                tmp_path / f"r{i}",
                zenoh={"mode": "client", "endpoint": router_endpoint},
                shard={"index": i, "replicas": 2},
            )
            for i in range(2)
        ]
        with running(replicas[0]) as a, running(replicas[1]) as b, probe(router_endpoint) as p:
            tokens = p.session.liveliness().get(service_liveliness_selector())
            names = sorted(str(reply.ok.key_expr).split("/")[3] for reply in tokens if reply.ok is not None)
            assert names == ["replica-0", "replica-1"]
            ids = [f"fleet-{i:03d}" for i in range(40)]
            for k in range(20):
                for vid in ids:
                    p.put(constant_measurement(vid, k))
            wait_for(lambda: len(p.collect().estimates) >= 40 * 20, what="estimates")
            time.sleep(0.5)  # a duplicate answer, if any, would arrive now
            answers: dict[tuple[str, int], int] = {}
            for e in p.collect().estimates:
                answers[(e.vehicle, e.seq)] = answers.get((e.vehicle, e.seq), 0) + 1
            assert set(answers) == {(v, k) for v in ids for k in range(20)}
            assert set(answers.values()) == {1}  # exactly one replica answered each sample
            served = [{v["id"] for v in srv.get("/vehicles").json()} for srv in (a, b)]
            assert served[0].isdisjoint(served[1]) and served[0] | served[1] == set(ids)
            assert served[0] and served[1]
            buckets = [set(srv.get("/health").json()["buckets"]) for srv in (a, b)]
            assert buckets[0].isdisjoint(buckets[1]) and len(buckets[0] | buckets[1]) == 16
    finally:
        router.close()


def test_a_client_replica_reconnects_when_the_router_comes_back(tmp_path):
    """Not a sharding requirement, but the compose deployment relies on it: zenoh clients reconnect."""
    router_endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session("router", router_endpoint)
    settings = make_settings(tmp_path, zenoh={"mode": "client", "endpoint": router_endpoint})
    try:
        with running(settings) as srv:
            router.close()
            router = open_session("router", router_endpoint)
            with probe(router_endpoint) as p:

                def answered() -> bool:
                    p.put(constant_measurement("back-1", int(time.time() * 100) % 10**9))
                    return bool(p.estimates_of("back-1"))

                wait_for(answered, what="estimate after the router restarted")
            assert srv.get("/ready").json()["ready"]
    finally:
        router.close()


@pytest.mark.parametrize("freeze", [True, False])
def test_the_started_service_freezes_its_heap_for_the_collector_by_setting(tmp_path, freeze):
    """gc_freeze moves what start-up built to the permanent generation, so full collections stop walking it."""
    import gc

    gc.unfreeze()
    try:
        with running(make_settings(tmp_path, ingest={"gc_freeze": freeze})):
            frozen = gc.get_freeze_count()
        if freeze:
            assert frozen > 10_000  # the libraries, the app, the gains: far more than a test leaves behind
        else:
            assert frozen == 0
    finally:
        gc.unfreeze()
