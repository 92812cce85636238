"""A service in client mode loses its Zenoh router: /ready answers 503 naming it, and 200 once it is back."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.faults.helpers import RouterProcess, ready_body
from tests.service.helpers import free_port, make_settings, running, wait_for

pytestmark = pytest.mark.network


def test_ready_follows_the_router_link_of_a_client_replica(tmp_path: Path) -> None:
    router = RouterProcess(free_port()).start()
    settings = make_settings(tmp_path, zenoh={"mode": "client", "endpoint": router.endpoint})
    try:
        with running(settings) as srv:
            code, body = ready_body(srv)
            assert code == 200 and body["router_connected"] is True
            router.kill()
            body = wait_for(
                lambda: (answer := ready_body(srv))[0] == 503 and answer[1], what="/ready 503 without the router"
            )
            assert body["router_connected"] is False and "no Zenoh router" in body["detail"]
            assert router.endpoint in body["detail"]
            health = srv.get("/health")
            assert health.status_code == 200 and health.json()["router_connected"] is False
            router.start()  # the same port
            wait_for(lambda: ready_body(srv)[0] == 200, what="/ready 200 once the router is back")
            assert ready_body(srv)[1]["router_connected"] is True
    finally:
        router.stop()


def test_ready_follows_the_ingest_loops_heartbeat(tmp_path: Path) -> None:
    """/ready answers 503 when the ingest loop has not run for heartbeat_timeout_s. Here the loop ticks every
    100 ms and the timeout is 20 ms, so between two ticks the replica reports itself not ready, naming the loop;
    with the default timeout (5 s) the same loop keeps it ready (the other tests)."""
    settings = make_settings(tmp_path, ingest={"tick_interval_s": 0.1}, health={"heartbeat_timeout_s": 0.02})
    with running(settings) as srv:
        body = wait_for(
            lambda: (
                (answer := ready_body(srv))[0] == 503 and "ingest loop has not run" in answer[1]["detail"] and answer[1]
            ),
            what="/ready 503 between two ticks",
        )
        assert "the ingest loop has not run for" in body["detail"]
        # the loop keeps ticking: the heartbeat it writes is fresh again at some later moment
        wait_for(lambda: srv.service.ingest_heartbeat_age_s() < 0.02, what="a fresh heartbeat")
