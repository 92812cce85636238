"""A database that another process locks, or whose disk fills: ingest goes on, /ready tells the truth, and what
was registered meanwhile is stored once the database recovers (and survives a restart). The service runs as
`agv-fe serve` in its own process, on a real SQLite file."""

from __future__ import annotations

import signal
from pathlib import Path
from typing import Any

import pytest

from tests.faults.helpers import (
    Stream,
    exclusive_lock,
    fill,
    ready_body,
    small_filesystem,
    stored_vehicles,
    truncate_journal,
)
from tests.service.helpers import (
    WAIT_S,
    ServiceProcess,
    make_settings,
    parse_metrics,
    probe,
    running,
    service_process,
    wait_for,
)

pytestmark = pytest.mark.network

BEFORE = ["steady-1", "steady-2"]
DURING = ["newcomer-1", "newcomer-2", "newcomer-3"]


def storage_degraded(srv: ServiceProcess, stream: Stream, words: str) -> dict[str, Any] | None:
    """Send a round; the /ready body once it answers 503 because the storage fails with ``words``."""
    stream.round()
    code, body = ready_body(srv)
    storage = body["storage"]
    if code == 503 and storage["state"] == "degraded" and words in (storage["reason"] or ""):
        return body
    return None


def stopped_by_sigterm(srv: ServiceProcess) -> bool:
    """The process ended by its graceful shutdown (uvicorn re-raises the signal once the shutdown is complete)."""
    assert srv.process is not None
    return srv.process.returncode == -signal.SIGTERM and "Application shutdown complete" in srv.log()


def failed_writes(srv: ServiceProcess) -> float:
    return parse_metrics(srv.get("/metrics").text).value("agv_fe_storage_write_failures_total")


def ingest_survives_a_storage_fault(srv: ServiceProcess, stream: Stream, words: str) -> dict[str, Any]:
    """While the fault lasts: /ready is 503 naming the storage, and every vehicle's estimates keep coming."""
    body = wait_for(lambda: storage_degraded(srv, stream, words), what=f"/ready to report '{words}'")
    assert body["ready"] is False and "storage degraded" in body["detail"]
    assert body["storage"]["pending_writes"] >= 1 and failed_writes(srv) >= 1
    # ingest goes on for every vehicle, old and new, while the writes wait
    marks = {v: stream.latest_estimate(v) for v in stream.vehicle_ids}
    wait_for(lambda: stream.estimated_beyond(marks), what="new estimates of every vehicle during the fault")
    still = ready_body(srv)
    assert still[0] == 503 and still[1]["storage"]["state"] == "degraded"  # the fault is still there
    return body


def test_a_locked_database_delays_the_writes_but_not_ingest_and_loses_nothing(tmp_path: Path) -> None:
    settings = make_settings(tmp_path)
    database = settings.database_path
    with service_process(settings, tmp_path / "service.log") as srv, probe(settings.zenoh.endpoint) as p:
        srv.wait_ready()
        stream = Stream(p, BEFORE)
        wait_for(lambda: stream.estimated_beyond({}), what="estimates before the lock")
        wait_for(lambda: set(BEFORE) <= stored_vehicles(database), what="the first vehicles to be stored")
        with exclusive_lock(database):
            stream.add(DURING)  # vehicles that register while the database is locked
            ingest_survives_a_storage_fault(srv, stream, "database is locked")
            assert not set(DURING) & stored_vehicles(database)  # the lock really kept them out
            listed = {v["id"] for v in srv.get("/vehicles").json()}
            assert set(DURING) <= listed
            # a change an operator makes now is refused, not acknowledged and lost
            refused = srv.http.put("/vehicles/manual-1", json={"profile": "default"}, headers=srv.auth)
            assert refused.status_code == 503 and "storage degraded" in refused.json()["detail"]
        # the lock is gone: the queued writes land, in order, and /ready is 200 again
        wait_for(lambda: ready_body(srv)[0] == 200, what="/ready 200 after the lock was released")
        assert set(DURING) <= stored_vehicles(database)
        assert ready_body(srv)[1]["storage"] | {"failures": 0} == {
            "state": "ok",
            "reason": None,
            "pending_writes": 0,
            "failures": 0,
            "lost_writes": 0,
            "degraded_for_s": None,
        }
        srv.close()  # SIGTERM
        assert stopped_by_sigterm(srv)
    with running(settings) as again:  # a new process on the same database
        for vehicle_id in BEFORE + DURING:
            assert again.vehicle(vehicle_id)["profile"] == "default"


def test_sigterm_stops_the_service_while_the_database_is_locked(tmp_path: Path) -> None:
    """The shutdown retries the queued writes for storage.shutdown_flush_s, then gives them up and says so."""
    settings = make_settings(tmp_path, storage={"shutdown_flush_s": 1.0})
    with service_process(settings, tmp_path / "service.log") as srv, probe(settings.zenoh.endpoint) as p:
        srv.wait_ready()
        stream = Stream(p, ["doomed-1"])
        with exclusive_lock(settings.database_path):
            wait_for(lambda: storage_degraded(srv, stream, "database is locked"), what="the storage to degrade")
            assert srv.process is not None
            srv.process.terminate()
            srv.process.wait(WAIT_S)  # raises if SIGTERM did not stop it
            assert stopped_by_sigterm(srv)
        assert "writes the database did not accept: they are lost" in srv.log()


def test_a_full_disk_delays_the_writes_but_not_ingest_and_loses_nothing(tmp_path: Path) -> None:
    """The data directory on a 4 MB tmpfs that a file fills up: SQLite gets ENOSPC (SQLITE_FULL) as on a full
    disk. Removing the file frees the space."""
    with small_filesystem(tmp_path / "disk", "4m") as disk:
        settings = make_settings(tmp_path, data_dir=str(disk / "data"))
        database = settings.database_path
        with service_process(settings, tmp_path / "service.log") as srv, probe(settings.zenoh.endpoint) as p:
            srv.wait_ready()
            stream = Stream(p, BEFORE)
            wait_for(lambda: stream.estimated_beyond({}), what="estimates before the disk fills")
            wait_for(lambda: set(BEFORE) <= stored_vehicles(database), what="the first vehicles to be stored")
            truncate_journal(database)  # so that the next write needs new space, not the journal's old pages
            filler = disk / "filler"
            assert fill(filler) > 0
            stream.add(DURING)
            ingest_survives_a_storage_fault(srv, stream, "database or disk is full")
            assert not set(DURING) & stored_vehicles(database)
            filler.unlink()  # space again
            wait_for(lambda: ready_body(srv)[0] == 200, what="/ready 200 once the disk has space")
            assert set(DURING) <= stored_vehicles(database)
            assert ready_body(srv)[1]["storage"]["lost_writes"] == 0
        with running(settings) as again:
            for vehicle_id in BEFORE + DURING:
                assert again.vehicle(vehicle_id)["profile"] == "default"
