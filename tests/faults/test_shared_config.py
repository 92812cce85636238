"""One configuration for three replicas of a real PostgreSQL database (separate `agv-fe serve` processes, Zenoh
clients of one router on loopback): started together on an empty database they design the profile once; a
profile change through one replica runs one synthesis job there and activates the same gain version on the two
others, which read it from the database (LISTEN/NOTIFY), verify it and never design it."""

from __future__ import annotations

from concurrent.futures import Future
from pathlib import Path

import psycopg
import pytest

from agv_fe.pg_cluster import PostgresServer
from service.shared_config import DESIGN_LOCKS, SharedConfig, design_key
from tests.faults.helpers import RouterProcess
from tests.faults.test_bucket_leases import replica
from tests.service.helpers import FAST_DESIGN, free_port, job_done, parse_metrics, wait_for

pytestmark = pytest.mark.network


def stored_jobs(url: str) -> list[tuple[str, str]]:
    """(kind, status) of every job in the shared database."""
    with psycopg.connect(url) as conn:
        rows = conn.execute("SELECT record::json->>'kind', record::json->>'status' FROM jobs ORDER BY created_t_ns")
        return [(r[0], r[1]) for r in rows.fetchall()]


def test_a_profile_change_through_one_replica_activates_the_same_gains_on_all_with_one_job(
    tmp_path: Path, postgres_url: str
) -> None:
    router = RouterProcess(free_port()).start()
    replicas = {name: replica(tmp_path, name, router, postgres_url) for name in ("a", "b", "c")}
    try:
        for srv in replicas.values():  # together, on an empty database: one of them designs the profile
            srv.start()
        for srv in replicas.values():
            srv.wait_ready()
        versions = {n: srv.get("/profiles/default/gains").json()["version"] for n, srv in replicas.items()}
        assert len(set(versions.values())) == 1, versions
        assert stored_jobs(postgres_url) == [("initial", "succeeded")]
        a, b, c = replicas["a"], replicas["b"], replicas["c"]
        change = {"design": {**FAST_DESIGN, "fault_order": 2}, "alarms": {"stale_after_s": 1.0}}
        accepted = a.http.put("/profiles/default", json=change, headers=a.auth)
        assert accepted.status_code == 202, accepted.text
        job = wait_for(lambda: job_done(a, accepted.json()["job"]), what="the design through replica a")
        assert job["status"] == "succeeded", job
        new = a.get("/profiles/default/gains").json()["version"]
        assert new != versions["a"]
        for other in (b, c):
            wait_for(
                lambda other=other: other.get("/profiles/default/gains").json()["version"] == new,
                what="the new gains on another replica",
            )
            assert other.get("/profiles/default").json()["spec"]["design"]["fault_order"] == 2
        assert [kind for kind, _ in stored_jobs(postgres_url)] == ["initial", "update"]
        # each replica's own count of finished designs: the two the database holds, run where they were claimed
        finished = {
            n: parse_metrics(srv.get("/metrics").text).value("agv_fe_synthesis_jobs_total", status="succeeded")
            for n, srv in replicas.items()
        }
        assert sum(finished.values()) == 2 and finished["a"] >= 1, finished
    finally:
        for srv in replicas.values():
            srv.close()
        router.stop()


def test_a_claim_opens_the_claims_session_again_once_the_stopped_server_is_back(
    postgres_server: PostgresServer,
) -> None:
    """The claims session broken by a stopped server and a new one refused meanwhile: the first claim after the
    server is back opens a new session and takes the design lock, which another session then cannot take."""
    url = postgres_server.database()
    shared = SharedConfig(url, on_change=lambda _: Future())  # the listener is not started: never called
    shared.open()
    try:
        postgres_server.stop("immediate")
        try:
            assert not shared.claim("default")  # the session breaks
            assert not shared.claim("default")  # a new one is refused
        finally:
            postgres_server.start()
        assert shared.claim("default")
        with psycopg.connect(url, autocommit=True) as other:
            row = other.execute("SELECT pg_try_advisory_lock(%s, %s)", (DESIGN_LOCKS, design_key("default")))
            assert row.fetchone() == (False,)
    finally:
        shared.close()
