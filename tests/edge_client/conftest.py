"""Real zenoh on loopback for the edge tests: a killable router process and the estimation service.

Everything listens on 127.0.0.1 with explicit endpoints and multicast
scouting off; ports come from binding port 0.

``estimation_service`` is the one place that starts the service the edge side
talks to: the real `agv-fe serve`, in its own process, as a Zenoh client of
the test's router (the docker compose topology).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from agv_fe.benchmarks.harness import free_port as free_port
from edge_client.transport import TransportOptions

ROUTER_SCRIPT = Path(__file__).with_name("zenoh_router.py")


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


class RealService:
    """`agv-fe serve` in a child process: client of the router, HTTP on a free port, data in a temp dir."""

    #: The service publishes an estimate for every accepted sample (AGV_FE_INGEST__ESTIMATE_EVERY_N=1).
    answers_every_sample = True
    TOKEN = "edge-tests-token"

    def __init__(self, router: Router, data_dir: Path) -> None:
        self.http_port = free_port()
        self.url = f"http://127.0.0.1:{self.http_port}"
        env = {**os.environ, "AGV_FE_AUTH__TOKEN": self.TOKEN, "AGV_FE_ZENOH__CONNECT_TIMEOUT_MS": "-1"}
        command = [
            sys.executable, "-m", "agv_fe", "serve", "--zenoh-mode", "client", "--zenoh-endpoint", router.endpoint,
            "--http-port", str(self.http_port), "--data-dir", str(data_dir), "--log-level", "warning",
        ]  # fmt: skip
        self.log = (data_dir / "service.log").open("w")
        self.process = subprocess.Popen(command, env=env, stdout=self.log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 120  # the first start designs the default profile's gains
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"agv-fe serve exited with {self.process.returncode}: {self.read_log()}")
            try:
                if httpx.get(f"{self.url}/ready", timeout=1.0).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        else:
            self.close()
            raise RuntimeError(f"agv-fe serve was not ready within 120 s: {self.read_log()}")
        time.sleep(0.3)  # let its subscriptions reach the router

    def read_log(self) -> str:
        self.log.flush()
        return Path(self.log.name).read_text()[-3000:]

    def close(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout=10)
        self.log.close()


@pytest.fixture
def estimation_service(router: Router, tmp_path: Path) -> Iterator[RealService]:
    """The real service under the edge side, a client of ``router``."""
    data_dir = tmp_path / "service-data"
    data_dir.mkdir()
    service = RealService(router, data_dir)
    try:
        yield service
    finally:
        service.close()
