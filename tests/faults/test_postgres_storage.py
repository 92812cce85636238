"""The service on a shared PostgreSQL server (a real one, agv_fe/pg_cluster.py) behaves as on SQLite when the
database fails: the server stops as if it crashed, ingest goes on, /ready answers 503 naming the storage, a
change is refused rather than acknowledged and lost, and what was registered meanwhile is stored once the server
is back (and survives a restart of the service). The service runs as `agv-fe serve --database-url` in its own
process."""

from __future__ import annotations

from pathlib import Path

import psycopg
import pytest

from agv_fe.pg_cluster import PostgresServer
from tests.faults.helpers import Stream, ready_body
from tests.faults.test_storage import BEFORE, DURING, ingest_survives_a_storage_fault
from tests.service.helpers import make_settings, probe, running, service_process, wait_for

pytestmark = pytest.mark.network


def stored_vehicles(url: str) -> set[str]:
    with psycopg.connect(url) as conn:
        return {row[0] for row in conn.execute("SELECT id FROM vehicles")}


def test_the_service_stores_in_postgresql_when_given_its_url(tmp_path: Path, postgres_url: str) -> None:
    """--database-url: nothing in the data directory but the token; a second service on the same database finds
    the profiles, gains and vehicles the first stored."""
    settings = make_settings(tmp_path)
    with (
        service_process(settings, tmp_path / "service.log", "--database-url", postgres_url) as srv,
        probe(settings.zenoh.endpoint) as p,
    ):
        srv.wait_ready()
        stream = Stream(p, BEFORE)
        wait_for(lambda: stream.estimated_beyond({}), what="estimates")
        wait_for(lambda: set(BEFORE) <= stored_vehicles(postgres_url), what="the vehicles to be stored")
        active = srv.get("/profiles/default").json()["active_version"]
    assert not settings.database_path.exists()
    again = make_settings(tmp_path / "second", database={"url": postgres_url})
    with running(again) as second:
        assert second.get("/profiles/default").json()["active_version"] == active
        for vehicle_id in BEFORE:
            assert second.vehicle(vehicle_id)["profile"] == "default"


def test_a_stopped_database_server_delays_the_writes_but_not_ingest_and_loses_nothing(
    tmp_path: Path, postgres_server: PostgresServer
) -> None:
    url = postgres_server.database()
    settings = make_settings(tmp_path, database={"url": url})
    with service_process(settings, tmp_path / "service.log") as srv, probe(settings.zenoh.endpoint) as p:
        srv.wait_ready()
        stream = Stream(p, BEFORE)
        wait_for(lambda: stream.estimated_beyond({}), what="estimates before the database stops")
        wait_for(lambda: set(BEFORE) <= stored_vehicles(url), what="the first vehicles to be stored")
        postgres_server.stop("immediate")
        try:
            stream.add(DURING)  # vehicles that register while the database is down
            ingest_survives_a_storage_fault(srv, stream, "127.0.0.1")
            assert {v["id"] for v in srv.get("/vehicles").json()} >= set(DURING)
            refused = srv.http.put("/vehicles/manual-1", json={"profile": "default"}, headers=srv.auth)
            assert refused.status_code == 503 and "storage degraded" in refused.json()["detail"]
            unreadable = srv.get("/jobs")  # a read only the database answers: 503 with the reason, not a 500
            assert unreadable.status_code == 503 and "cannot be reached" in unreadable.json()["detail"]
        finally:
            postgres_server.start()
        wait_for(lambda: ready_body(srv)[0] == 200, what="/ready 200 once the database is back")
        assert set(BEFORE + DURING) <= stored_vehicles(url)
        assert ready_body(srv)[1]["storage"]["lost_writes"] == 0
        assert srv.get("/jobs").status_code == 200
    with running(settings) as again:
        for vehicle_id in BEFORE + DURING:
            assert again.vehicle(vehicle_id)["profile"] == "default"
