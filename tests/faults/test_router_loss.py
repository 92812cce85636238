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
