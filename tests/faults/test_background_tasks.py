"""A background task that raises: restarted while it can be, else /ready and /health answer 503 naming it and
`agv-fe serve` exits with status 4, so that an orchestrator restarts it.

The failure is real, not a mock: a latched alarm stored with a level this service does not know (a corrupt row,
or one written by another version) is loaded at start; when its vehicle goes STALE, the housekeeping loop
escalates that alarm and raises KeyError."""

from __future__ import annotations

import subprocess
from pathlib import Path
from typing import Any

import httpx
import pytest

from service.storage import SqliteStorage
from tests.faults.helpers import ready_body
from tests.service.helpers import (
    FAST_DESIGN,
    WAIT_S,
    ServiceProcess,
    make_settings,
    parse_metrics,
    running,
    wait_for,
)

pytestmark = pytest.mark.network

GHOST = "ghost-1"
EXIT_SERVICE_FAILED = 4


def store_a_corrupt_stale_alarm(database: Path) -> None:
    """A registered vehicle and a latched STALE alarm of it whose level is not a level."""
    storage = SqliteStorage(database)
    try:
        storage.put_vehicles([(GHOST, "default", 1)])
        record = {
            "id": "al-0123456789ab",
            "vehicle": GHOST,
            "profile": "default",
            "kind": "stale",
            "level": "BOGUS",
            "peak_level": "BOGUS",
            "state": "cleared",
            "acknowledged": False,
            "raised_t_ns": 1,
            "cleared_t_ns": 2,
            "updated_t_ns": 2,
            "message": "",
            "occurrences": 1,
        }
        storage.record_alarm_changes([(record, {"t_ns": 2})])
    finally:
        storage.close()


def settings_with_a_corrupt_alarm(tmp_path: Path, **overrides: Any) -> Any:
    settings = make_settings(
        tmp_path, {"default": {"design": FAST_DESIGN, "alarms": {"stale_after_s": 1.0}}}, **overrides
    )
    store_a_corrupt_stale_alarm(settings.database_path)
    return settings


def housekeeping_down(server: ServiceProcess) -> dict[str, Any] | None:
    try:
        code, body = ready_body(server)
    except httpx.TransportError:
        return None
    return body if code == 503 and "housekeeping" in body["tasks"] else None


def test_a_background_task_that_cannot_be_kept_running_makes_the_process_exit_non_zero(tmp_path: Path) -> None:
    settings = settings_with_a_corrupt_alarm(tmp_path, health={"task_restarts": 0, "fatal_exit_grace_s": 10.0})
    srv = ServiceProcess(settings, tmp_path / "service.log")
    try:
        srv.start(wait_healthy=False)  # the task may fail before a first /health is answered
        body = wait_for(lambda: housekeeping_down(srv), what="/ready to name the failed housekeeping task")
        assert "KeyError" in body["tasks"]["housekeeping"] and "'housekeeping'" in body["detail"]
        health = srv.get("/health")
        assert health.status_code == 503 and health.json()["status"] == "failed"
        assert srv.process is not None
        try:
            returncode = srv.process.wait(WAIT_S)
        except subprocess.TimeoutExpired as exc:
            raise AssertionError(f"the failed service did not exit:\n{srv.log()}") from exc
        assert returncode == EXIT_SERVICE_FAILED, srv.log()
        assert "exiting with status 4" in srv.log()
    finally:
        srv.close()


def test_a_background_task_that_fails_once_is_restarted(tmp_path: Path) -> None:
    settings = settings_with_a_corrupt_alarm(tmp_path)  # health.task_restarts: 3

    with running(settings, ready=False) as srv:

        def failures() -> float:
            scrape = parse_metrics(srv.get("/metrics").text)
            return scrape.value("agv_fe_background_task_failures_total", task="housekeeping")

        wait_for(lambda: failures() >= 1, what="the housekeeping task to fail")
        # restarted: the vehicle is STALE now, so the next rounds do not touch the corrupt alarm again
        wait_for(lambda: ready_body(srv)[0] == 200, what="/ready 200 once the task runs again")
        body = ready_body(srv)[1]
        assert body["tasks"] == {} and failures() == 1
        listed = {v["id"]: v for v in srv.get("/vehicles").json()}
        assert listed[GHOST]["stale"]
