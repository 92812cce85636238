"""Real zenoh on loopback for the edge tests: a killable router process and the estimation service.

Everything listens on 127.0.0.1 with explicit endpoints and multicast
scouting off; ports come from binding port 0.

``estimation_service`` is the one place that starts the service the edge side
talks to. Today it is the TEST-ONLY responder (tests/edge_client/responder.py);
when the real service is merged, start it here instead (as a client of
``router.endpoint``) and every end-to-end test runs against it.
"""

from __future__ import annotations

import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from edge_client.transport import TransportOptions
from tests.edge_client.responder import ResponderService

ROUTER_SCRIPT = Path(__file__).with_name("zenoh_router.py")


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


class Router:
    """A zenoh router in a child process on a fixed port, which a test may kill and restart."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.endpoint = f"tcp/127.0.0.1:{port}"
        self.process: subprocess.Popen[str] | None = None

    def start(self) -> None:
        self.process = subprocess.Popen(
            [sys.executable, str(ROUTER_SCRIPT), str(self.port)], stdout=subprocess.PIPE, text=True
        )
        assert self.process.stdout is not None
        line = self.process.stdout.readline().strip()
        if line != "ready":
            self.stop()
            raise RuntimeError(f"router on port {self.port} did not start: {line!r}")

    def kill(self) -> None:
        """Crash it: SIGKILL, no goodbye to the clients."""
        if self.process is not None:
            self.process.kill()
            self.process.wait(timeout=10)
            self.process = None

    def stop(self) -> None:
        if self.process is not None:
            self.process.terminate()
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout=10)
            self.process = None

    def client(self, **overrides: object) -> TransportOptions:
        """Transport options of a client of this router."""
        options: dict[str, object] = {"mode": "client", "connect": (self.endpoint,), "connect_timeout_s": 5.0}
        options.update(overrides)
        return TransportOptions(**options)  # type: ignore[arg-type]


@pytest.fixture
def router() -> Iterator[Router]:
    r = Router(free_port())
    r.start()
    try:
        yield r
    finally:
        r.stop()


@pytest.fixture
def estimation_service(router: Router, paper_gains_order1) -> Iterator[ResponderService]:
    """The service under the edge side, a client of ``router``. Swap in the real service here."""
    service = ResponderService(router.client(), paper_gains_order1)
    time.sleep(0.3)  # let its subscription reach the router
    try:
        yield service
    finally:
        service.close()
