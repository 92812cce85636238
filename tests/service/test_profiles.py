"""Several vehicle profiles in one real service: each vehicle observed with its own profile's gains; the metrics
of that work."""

from __future__ import annotations

import sqlite3

import numpy as np
import pytest
from pydantic import TypeAdapter

from agv_protocol.wire import Measurement
from service.api.models import VehicleStatus
from service.storage import SqliteStorage
from synth.gains import ObserverGains
from synth.observer import FuzzyObserver
from tests.service.helpers import (
    FAST_DESIGN,
    RunningService,
    as_array,
    constant_measurement,
    job_done,
    make_settings,
    parse_metrics,
    plant_measurements,
    probe,
    running,
    wait_for,
)
from tests.tolerances import BATCH_EQUALITY_ATOL

pytestmark = pytest.mark.network

#: A delivery van: heavier and slower to turn than the paper's car (Table 1).
HEAVY = {"mass_kg": 2100.0, "yaw_inertia_kgm2": 2600.0}
N_SAMPLES = 300
#: Vehicle id -> profile.
FLEET = {"car-1": "default", "van-1": "heavy"}


def offline_estimates(gains: ObserverGains, samples: list[Measurement]) -> np.ndarray:
    """Algorithm 1 run offline on one vehicle's samples: rows of (v_x, v_y, r, T_f, delta_f)."""
    observer = FuzzyObserver(gains, np.array([[samples[0].vx_mps, samples[0].r_radps]]))
    return np.array(
        [observer.step([[m.vx_mps, m.r_radps]], [[m.torque_nm, m.steer_rad]]).x_hat[0, :5] for m in samples]
    )


def test_each_vehicle_is_observed_with_its_own_profiles_gains(tmp_path):
    settings = make_settings(tmp_path)
    with running(settings) as srv, probe(settings.zenoh.endpoint) as p:
        created = srv.http.put("/profiles/heavy", json={"params": HEAVY, "design": FAST_DESIGN}, headers=srv.auth)
        assert created.status_code == 202
        job = wait_for(lambda: job_done(srv, created.json()["job"]), what="the heavy profile's design")
        assert job["status"] == "succeeded"
        for vehicle_id, profile in FLEET.items():
            assigned = srv.http.put(f"/vehicles/{vehicle_id}", json={"profile": profile}, headers=srv.auth)
            assert assigned.status_code == 200 and assigned.json()["profile"] == profile
        samples = plant_measurements(list(FLEET), N_SAMPLES)  # the same drive for both vehicles
        for row in samples:
            for m in row:
                p.put(m)
        wait_for(lambda: all(len(p.estimates_of(v)) >= N_SAMPLES for v in FLEET), what="every estimate")
        gains = {}
        for profile in FLEET.values():
            doc = srv.get(f"/profiles/{profile}/gains", params={"matrices": "true"}).json()
            gains[profile] = ObserverGains.from_dict(doc)
            assert doc["version"] == srv.get(f"/profiles/{profile}").json()["active_version"]
        assert gains["heavy"].version == job["gain_version"] != gains["default"].version
        assert gains["heavy"].params.mass_kg == HEAVY["mass_kg"]
        for i, (vehicle_id, profile) in enumerate(FLEET.items()):
            got = p.estimates_of(vehicle_id)
            assert [e.seq for e in got] == list(range(N_SAMPLES))
            assert {e.gain_version for e in got} == {gains[profile].version}
            own = offline_estimates(gains[profile], [row[i] for row in samples])
            np.testing.assert_allclose(as_array(got), own, atol=BATCH_EQUALITY_ATOL)
            # the other profile's gains give other estimates of the same drive: the comparison tells them apart
            other = next(g for name, g in gains.items() if name != profile)
            mixed_up = offline_estimates(other, [row[i] for row in samples])
            assert np.abs(as_array(got) - mixed_up).max() > 1e6 * BATCH_EQUALITY_ATOL
        assert_metrics_show_the_work(srv, measurements=N_SAMPLES * len(FLEET))
        assert_the_vehicle_list_filters_and_keeps_its_schema(srv)


def assert_the_vehicle_list_filters_and_keeps_its_schema(srv: RunningService) -> None:
    """GET /vehicles is written without a model per vehicle: every item still validates as the documented
    VehicleStatus and agrees with GET /vehicles/{id}; the profile and level filters select."""
    listed = srv.get("/vehicles").json()
    assert [v["id"] for v in listed] == sorted(FLEET)
    statuses = TypeAdapter(list[VehicleStatus]).validate_python(listed, strict=True)
    for status in statuses:
        assert status.profile == FLEET[status.id] and status.counters["accepted"] == N_SAMPLES
        one = srv.get(f"/vehicles/{status.id}").json()
        assert {k: one[k] for k in ("id", "profile", "level", "gain_version", "last_seq")} == {
            k: listed[statuses.index(status)][k] for k in ("id", "profile", "level", "gain_version", "last_seq")
        }
    assert [v["id"] for v in srv.get("/vehicles", params={"profile": "heavy"}).json()] == ["van-1"]
    for level in {v["level"] for v in listed}:
        chosen = srv.get("/vehicles", params={"level": level}).json()
        assert [v["id"] for v in chosen] == [v["id"] for v in listed if v["level"] == level]
    # a typo in a filter is an error that says so, not an empty fleet
    unknown = srv.get("/vehicles", params={"profile": "nobody"})
    assert unknown.status_code == 404 and "no profile named 'nobody'; known: default, heavy" in unknown.text
    bad_level = srv.get("/vehicles", params={"level": "NOT-A-LEVEL"})
    assert bad_level.status_code == 422 and "'OK', 'WARN', 'FAULT' or 'STALE'" in bad_level.text
    for params in ({"limit": 0}, {"after": "no spaces"}):
        assert srv.get("/vehicles", params=params).status_code == 422, params


def assert_metrics_show_the_work(srv: RunningService, measurements: int) -> None:
    """Step latency (tick time), queue depth (batch size) and synthesis durations are exposed, with values that
    add up to what the service did."""
    metrics = parse_metrics(srv.get("/metrics").text)
    uptime_s = srv.get("/health").json()["uptime_s"]
    for name in ("agv_fe_tick_seconds", "agv_fe_tick_batch_measurements", "agv_fe_synthesis_seconds"):
        assert metrics.types[name] == "histogram", name
        count, buckets = metrics.value(f"{name}_count"), metrics.buckets(name)
        assert count > 0 and metrics.value(f"{name}_sum") > 0, name
        cumulative = [n for _, n in buckets]
        assert cumulative == sorted(cumulative) and buckets[-1] == (float("inf"), count), name
    assert metrics.types["agv_fe_ingest_last_batch"] == "gauge"
    assert metrics.value("agv_fe_ingest_last_batch") >= 1
    # tick time: every tick took some time, all of them together less than the service has been up
    assert 0 < metrics.value("agv_fe_tick_seconds_sum") < uptime_s
    # batch size: each tick drained at least one measurement, and the ticks drained every measurement once
    received = metrics.value("agv_fe_measurements_received_total")
    assert received == measurements
    assert metrics.value("agv_fe_tick_batch_measurements_sum") == received
    assert metrics.value("agv_fe_tick_batch_measurements_count") <= received
    # synthesis: one observation per finished design, each the duration its job reports
    finished = [j for j in srv.get("/jobs").json() if j["status"] in ("succeeded", "failed")]
    assert len(finished) == 2  # the default profile's first design and the heavy profile's
    assert metrics.value("agv_fe_synthesis_seconds_count") == len(finished)
    assert metrics.value("agv_fe_synthesis_seconds_sum") == pytest.approx(sum(j["duration_s"] for j in finished))
    assert metrics.value("agv_fe_synthesis_jobs_total", status="succeeded") == 2
    for profile in set(FLEET.values()):
        assert metrics.value("agv_fe_vehicles", profile=profile) == 1


def test_a_bad_profile_body_is_refused_before_anything_is_stored(tmp_path):
    """The hardening issue's request: a duration that no clock can hold was stored, answered 500, and made every
    later start fail. Each bad value is a 422 naming the field, and nothing is stored or added."""
    settings = make_settings(tmp_path)
    with running(settings) as srv:
        for alarms in ({"clear_after_s": 1e300}, {"warmup_s": 1e15}, {"stale_after_s": 1e300}):
            r = srv.http.put("/profiles/poison", json={"alarms": alarms}, headers=srv.auth)
            assert r.status_code == 422 and next(iter(alarms)) in r.text, r.text
        for name in ("..", "."):  # path segments, not names (sent encoded: a client would resolve them)
            r = srv.http.put(f"/profiles/{name.replace('.', '%2E')}", json={}, headers=srv.auth)
            assert r.status_code == 422 and "invalid profile name" in r.text, (name, r.text)
        # the loss-of-effectiveness stage on a design it cannot read (the paper's triple-integrator fault model)
        body = {"effectiveness": {"enabled": True}, "design": {"design": "paper"}}
        r = srv.http.put("/profiles/poison", json=body, headers=srv.auth)
        assert r.status_code == 422 and "effectiveness.enabled needs design 'robust' with fault_order 1" in r.text
        assert srv.get("/profiles/poison").status_code == 404
        assert [p["name"] for p in srv.get("/profiles").json()] == ["default"]
        assert [p.name for p in srv.service.db.profiles()] == ["default"]


def test_a_stored_profile_that_cannot_be_loaded_is_reported_and_the_others_run(tmp_path):
    """A database written before the bounds existed, or edited by hand: a profile with a duration no clock can
    hold, one whose spec is not JSON, and the default profile's active gains garbled. The service starts, runs the
    default profile (its unusable gains resynthesised, as the log says), reports the two others as failed in
    GET /profiles, /ready and /metrics, keeps their vehicles for them, and a valid PUT replaces a failed one."""
    settings = make_settings(tmp_path)
    db = SqliteStorage(settings.database_path)
    db.activate_gains("default", {"design": FAST_DESIGN}, {"version": "garbled", "certificate": {}}, 1)
    db.put_profile("poison", {"alarms": {"clear_after_s": 1e300}}, 1)
    db.put_profile("garbled", {}, 1)
    db.put_vehicles([("car-1", "default", 1), ("held-1", "poison", 2)])
    db.close()
    with sqlite3.connect(settings.database_path) as raw:
        raw.execute("UPDATE profiles SET spec = '{\"alarms\": {' WHERE name = 'garbled'")
        raw.execute("UPDATE gain_versions SET gains = '{not json' WHERE version = 'garbled'")
    with running(settings) as srv, probe(settings.zenoh.endpoint) as p:
        ready = srv.get("/ready").json()
        assert ready["ready"] and set(ready["failed_profiles"]) == {"poison", "garbled"}
        assert srv.get("/profiles/default").json()["active_version"] not in (None, "garbled")  # resynthesised
        profiles = {q["name"]: q for q in srv.get("/profiles").json()}
        assert profiles["default"]["state"] == "running" and profiles["default"]["error"] is None
        poison = srv.get("/profiles/poison").json()
        assert poison == profiles["poison"]
        assert poison["state"] == "failed" and poison["spec"] is None and poison["vehicles"] == 1
        assert "alarms.clear_after_s" in poison["error"]
        assert profiles["garbled"]["state"] == "failed" and "not JSON" in profiles["garbled"]["error"]
        assert parse_metrics(srv.get("/metrics").text).value("agv_fe_profiles_failed") == 2
        # the vehicle of a failed profile is neither observed nor moved to the default profile
        for k in range(5):
            p.put(constant_measurement("held-1", k))
            p.put(constant_measurement("car-1", k))
        wait_for(lambda: len(p.estimates_of("car-1")) >= 5, what="the running profile's estimates")
        line = 'agv_fe_measurements_rejected_total{reason="no_gains"} 5'
        wait_for(lambda: line in srv.get("/metrics").text, what="the held vehicle's samples refused")
        assert p.estimates_of("held-1") == [] and srv.get("/vehicles/held-1").status_code == 404
        assert srv.service.db.vehicles() == [("car-1", "default", 1), ("held-1", "poison", 2)]
        # a valid profile of that name replaces the failed one and takes its vehicles back
        put = srv.http.put("/profiles/poison", json={"design": FAST_DESIGN}, headers=srv.auth)
        assert put.status_code == 202, put.text
        assert wait_for(lambda: job_done(srv, put.json()["job"]), what="the design")["status"] == "succeeded"
        assert srv.get("/profiles/poison").json()["state"] == "running"
        assert set(srv.get("/ready").json()["failed_profiles"]) == {"garbled"}
        assert srv.vehicle("held-1")["profile"] == "poison"


def test_profiles_and_jobs_are_bounded(tmp_path):
    """The hardening issue: 124 profiles and 500 jobs in 240 s, kept for ever. A profile beyond max_profiles is
    a 409 that says so (changing an existing one still works); finished jobs beyond jobs_kept are forgotten,
    in memory and in the database."""
    settings = make_settings(tmp_path).model_copy(update={"max_profiles": 3, "jobs_kept": 10})
    with running(settings) as srv:
        fast = {"design": FAST_DESIGN}
        for name in ("p1", "p2"):  # with 'default': three
            assert srv.http.put(f"/profiles/{name}", json=fast, headers=srv.auth).status_code == 202
        refused = srv.http.put("/profiles/p3", json=fast, headers=srv.auth)
        assert refused.status_code == 409 and "max_profiles = 3" in refused.json()["detail"]
        assert srv.get("/profiles/p3").status_code == 404
        # a change of an existing profile is not a new one; twelve designs in a row leave ten jobs
        ids = []
        for k in range(12):
            body = {"design": FAST_DESIGN, "params": {"mass_kg": 1400.0 + k}}
            answer = srv.http.put("/profiles/p1", json=body, headers=srv.auth)
            assert answer.status_code == 202, answer.text
            ids.append(answer.json()["job"])
            wait_for(lambda job=ids[-1]: job_done(srv, job), what=f"job {ids[-1]}")
        wait_for(lambda: len(srv.service.jobs) <= 10, what="old jobs forgotten")
        assert srv.get(f"/jobs/{ids[-1]}").status_code == 200
        wait_for(lambda: len(srv.service.db.jobs(limit=1000)) <= 10, what="old jobs pruned from the database")
