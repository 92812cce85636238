"""Real zenoh on loopback for the edge tests: a killable router process and the estimation service.

Everything listens on 127.0.0.1 with explicit endpoints and multicast
scouting off; ports come from binding port 0.

``estimation_service`` is the one place that starts the service the edge side
talks to: the real `agv-fe serve`, in its own process, as a Zenoh client of
the test's router (the docker compose topology).
"""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from agv_fe.benchmarks.harness import ServiceProcess
from agv_fe.benchmarks.harness import free_port as free_port
from edge_client.transport import TransportOptions
from service.settings import Settings

ROUTER_SCRIPT = Path(__file__).with_name("zenoh_router.py")
#: The longest the service may take to become ready: the first start designs the default profile's gains [s].
READY_S = 120.0


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


class RealService(ServiceProcess):
    """`agv-fe serve` in a child process: client of the router, HTTP on a free port, data in ``data_dir``."""

    #: The service publishes an estimate for every accepted sample (AGV_FE_INGEST__ESTIMATE_EVERY_N=1).
    answers_every_sample = True
    TOKEN = "edge-tests-token"

    def __init__(self, router: Router, data_dir: Path) -> None:
        settings = Settings(
            data_dir=data_dir,
            http={"port": free_port()},
            auth={"token": self.TOKEN},
            zenoh={"mode": "client", "endpoint": router.endpoint, "connect_timeout_ms": -1},
        )
        super().__init__(settings, data_dir / "service.log", "--log-level", "warning")


@pytest.fixture
def estimation_service(router: Router, tmp_path: Path) -> Iterator[RealService]:
    """The real service under the edge side, a client of ``router``."""
    data_dir = tmp_path / "service-data"
    data_dir.mkdir()
    service = RealService(router, data_dir)
    try:
        service.start()
        service.wait_ready(READY_S)
        time.sleep(0.3)  # let its subscriptions reach the router
        yield service
    finally:
        service.close()
