"""Vehicles whose bucket has no owner, on a real PostgreSQL server with `agv-fe serve` replicas (separate processes,
Zenoh clients of one router on loopback) and a fleet at 100 Hz (service/ownership.py).

Static shards: replica r1 of two (``--shard 1/2``) is killed with SIGKILL; nothing takes its buckets over, and the
survivor lists its vehicles as unserved (GET /vehicles), raises an ``unserved`` alarm for each (GET /alarms, the
alarm keys on Zenoh) and counts them (/metrics); when r1 is back, the alarms clear and r1 holds them, cleared.

Leases: a member of the lock table that does not take its share (a test session holding a member lock, as a
replica stuck before it takes its buckets would) keeps the window before a takeover open: the buckets the two
replicas give up to it have no owner, and their vehicles are alarmed until it leaves and the replicas take them."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import psycopg
import pytest
import zenoh

from agv_fe.benchmarks.harness import SteadyFleet
from agv_protocol.wire import Alarm, bucket_of, fleet_selector
from service.bucket_leases import MEMBER_LOCKS
from service.transport import open_session
from tests.faults.helpers import RouterProcess
from tests.service.helpers import (
    FAST_DESIGN,
    WAIT_S,
    ServiceProcess,
    free_port,
    make_settings,
    parse_metrics,
    wait_for,
)

pytestmark = pytest.mark.network

VEHICLES = [f"veh-{k:02d}" for k in range(20)]
PROFILES = {"default": {"design": FAST_DESIGN, "alarms": {"stale_after_s": 1.0}}}
#: how long a bucket has no owner before its vehicles are alarmed, in these tests [s]
UNSERVED_AFTER_S = 0.5


class AlarmLog:
    """Every alarm event on Zenoh, by (vehicle, kind, state), from a subscriber of the fleet's alarm keys."""

    def __init__(self, session: zenoh.Session) -> None:
        self.events: list[Alarm] = []
        self._lock = threading.Lock()
        self._sub = session.declare_subscriber(fleet_selector("alarm"), self._arrived)

    def _arrived(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.events.append(Alarm.decode(sample.payload.to_bytes()))

    def vehicles(self, kind: str, state: str) -> set[str]:
        with self._lock:
            return {a.vehicle for a in self.events if a.kind == kind and a.state == state}

    def forget(self) -> None:
        with self._lock:
            self.events.clear()

    def close(self) -> None:
        self._sub.undeclare()


def replica(tmp_path: Path, name: str, router: RouterProcess, url: str, shard: dict[str, Any]) -> ServiceProcess:
    settings = make_settings(
        tmp_path / name,
        PROFILES,
        zenoh={"mode": "client", "endpoint": router.endpoint},
        database={"url": url},
        shard={"replica_id": name, "lease_interval_s": 0.2, "unserved_after_s": UNSERVED_AFTER_S, **shard},
    )
    return ServiceProcess(settings, tmp_path / f"{name}.log")


@contextmanager
def cluster(
    tmp_path: Path, url: str, shards: dict[str, dict[str, Any]]
) -> Iterator[tuple[dict[str, ServiceProcess], AlarmLog]]:
    """The replicas, ready; the fleet streaming (until the end), every vehicle estimated; the alarm events."""
    with ExitStack() as stack:
        router = RouterProcess(free_port()).start()
        stack.callback(router.stop)
        replicas = {name: replica(tmp_path, name, router, url, shard) for name, shard in shards.items()}
        for srv in replicas.values():
            stack.callback(lambda srv=srv: srv.close())
        first, *others = replicas.values()
        first.start().wait_ready()  # the first designs the gains; the others read them from the database
        for srv in others:
            srv.start().wait_ready()
        session = open_session("client", router.endpoint)
        stack.callback(session.close)
        fleet = SteadyFleet(session, VEHICLES, max_s=15 * WAIT_S).start()
        stack.callback(fleet.close)
        alarms = AlarmLog(session)
        stack.callback(alarms.close)
        wait_for(lambda: set(fleet.estimated_since(0.0, {})) == set(VEHICLES), what="estimates of every vehicle")
        yield replicas, alarms


def unserved_rows(srv: ServiceProcess) -> set[str]:
    rows = srv.get("/vehicles").json()
    assert all(r["level"] == "STALE" for r in rows if not r["served"])
    return {r["id"] for r in rows if not r["served"]}


def latched_unserved(srv: ServiceProcess) -> dict[str, dict[str, Any]]:
    return {a["vehicle"]: a for a in srv.get("/alarms").json() if a["kind"] == "unserved"}


def test_a_dead_static_shards_vehicles_are_listed_and_alarmed_as_unserved_until_it_returns(
    tmp_path: Path, postgres_url: str
) -> None:
    shards = {"r0": {"replicas": 2, "index": 0}, "r1": {"replicas": 2, "index": 1}}
    with cluster(tmp_path, postgres_url, shards) as (replicas, alarms):
        r0, r1 = replicas["r0"], replicas["r1"]
        its_buckets = set(r1.get("/health").json()["buckets"])
        its_vehicles = {v for v in VEHICLES if bucket_of(v) in its_buckets}
        assert its_vehicles and its_vehicles != set(VEHICLES)
        # r1's buckets had no owner until it started: r0 sees them owned from its next lock round on
        wait_for(lambda: r0.get("/replicas").json()["unowned_buckets"] == [], what="r1's buckets owned, seen by r0")
        assert unserved_rows(r0) == set() and alarms.vehicles("unserved", "raised") == set()
        r1.kill()
        # unserved: listed at once, alarmed once the bucket has had no owner for UNSERVED_AFTER_S
        wait_for(lambda: unserved_rows(r0) == its_vehicles, what="the dead replica's vehicles listed as unserved")
        assert sorted(r0.get("/replicas").json()["unowned_buckets"]) == sorted(its_buckets)
        wait_for(lambda: set(latched_unserved(r0)) == its_vehicles, what="an unserved alarm for each of them")
        assert all(a["state"] == "raised" and a["level"] == "STALE" for a in latched_unserved(r0).values())
        wait_for(lambda: alarms.vehicles("unserved", "raised") == its_vehicles, what="the alarms on Zenoh")
        scrape = parse_metrics(r0.get("/metrics").text)
        assert scrape.value("agv_fe_buckets_unowned") == len(its_buckets)
        assert scrape.value("agv_fe_vehicles_unserved") == len(its_vehicles)
        assert scrape.value("agv_fe_ownership_warden") == 1
        assert scrape.value("agv_fe_alarms_latched", kind="unserved", level="STALE", profile="default",
                            acknowledged="false") == len(its_vehicles)  # fmt: skip
        assert not alarms.vehicles("unserved", "raised") & (set(VEHICLES) - its_vehicles)  # r0's own: served
        back = ServiceProcess(r1.settings, tmp_path / "r1-again.log")
        try:
            back.start().wait_ready()
            wait_for(lambda: unserved_rows(r0) == set(), what="no vehicle unserved once r1 is back")
            wait_for(lambda: alarms.vehicles("unserved", "cleared") == its_vehicles, what="the clears on Zenoh")
            assert latched_unserved(r0) == {}  # the warden no longer holds them
            # the replica that serves them again holds them, cleared and latched until acknowledged
            held = latched_unserved(back)
            assert set(held) == its_vehicles and all(a["state"] == "cleared" for a in held.values())
            with psycopg.connect(postgres_url) as conn:
                rows = conn.execute("SELECT record::json->>'state' FROM alarms WHERE kind = 'unserved'").fetchall()
            assert sorted(r[0] for r in rows) == ["cleared"] * len(its_vehicles)  # one alarm each, stored cleared
            assert parse_metrics(r0.get("/metrics").text).value("agv_fe_buckets_unowned") == 0
        finally:
            back.close()


def test_buckets_waiting_for_a_takeover_by_leases_show_their_vehicles_as_unserved(
    tmp_path: Path, postgres_url: str
) -> None:
    shards: dict[str, dict[str, Any]] = {"r0": {}, "r1": {}}
    with cluster(tmp_path, postgres_url, shards) as (replicas, alarms):
        r0 = replicas["r0"]
        wait_for(
            lambda: sorted(len(s.get("/health").json()["buckets"]) for s in replicas.values()) == [8, 8],
            what="the buckets shared 8/8",
        )
        wait_for(lambda: r0.get("/replicas").json()["unowned_buckets"] == [], what="every bucket owned, seen by r0")
        assert unserved_rows(r0) == set()
        # a bucket handed from r0 to r1 at the start has no owner for a lease round; on a loaded machine that can
        # outlast UNSERVED_AFTER_S and raise an alarm, cleared when r1 takes it: start from a settled fleet
        wait_for(lambda: alarms.vehicles("unserved", "raised") <= alarms.vehicles("unserved", "cleared"),
                 what="no unserved alarm left from the start")  # fmt: skip
        alarms.forget()
        with psycopg.connect(postgres_url, autocommit=True) as member:  # a third member that takes nothing
            member.execute("SELECT pg_advisory_lock(%s, pg_backend_pid())", (MEMBER_LOCKS,))
            unowned = wait_for(
                lambda: (lambda b: set(b) if len(b) in (5, 6) else None)(r0.get("/replicas").json()["unowned_buckets"]),
                what="the replicas to give the third member its share",
            )
            waiting = {v for v in VEHICLES if bucket_of(v) in unowned}
            wait_for(lambda: unserved_rows(r0) == waiting, what="their vehicles listed as unserved")
            wait_for(lambda: alarms.vehicles("unserved", "raised") == waiting, what="their alarms on Zenoh")
            warden = [n for n, s in replicas.items() if parse_metrics(s.get("/metrics").text).value(
                "agv_fe_ownership_warden") == 1]  # fmt: skip
            assert len(warden) == 1  # one replica raises them
        wait_for(lambda: r0.get("/replicas").json()["unowned_buckets"] == [], what="the buckets taken again")
        wait_for(lambda: alarms.vehicles("unserved", "cleared") == waiting, what="the clears on Zenoh")
        assert unserved_rows(r0) == set()
        for srv in replicas.values():  # each cleared alarm is held by the replica that serves the vehicle
            held = latched_unserved(srv)
            served = {v for v in waiting if bucket_of(v) in srv.get("/health").json()["buckets"]}
            assert set(held) & waiting == served and all(a["state"] == "cleared" for a in held.values())
