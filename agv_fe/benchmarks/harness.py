"""A real service to measure or to test: ``agv-fe serve`` in a process of its own, on loopback.

The benchmarks (service_load, soak) and the test suite (tests/service/helpers.py) start the service the same
way: from a :class:`~service.settings.Settings`, passed down as the ``AGV_FE_*`` environment the command reads.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

import httpx
import zenoh

from agv_protocol.wire import Estimate, Measurement, fleet_selector, vehicle_key
from service.settings import Settings

#: Upper bound of a wait for the service [s]; a wait polls for its condition and fails after it.
WAIT_S = 60.0


def free_port() -> int:
    """A TCP port of 127.0.0.1 that nothing listens on now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_for(condition: Callable[[], Any], timeout: float = WAIT_S, what: str = "condition") -> Any:
    """Poll ``condition`` every 20 ms until it returns a true value, and return it; raise :class:`TimeoutError`
    naming ``what`` after ``timeout`` seconds [s]."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.02)
    raise TimeoutError(f"timed out after {timeout} s waiting for {what}")


def settings_env(settings: Settings, changed_only: bool = False) -> dict[str, str]:
    """The environment that makes ``agv-fe serve`` build ``settings``: AGV_FE_* variables, nested with ``__``.

    ``changed_only``: only the settings that differ from their defaults, for the service of an earlier checkout,
    which refuses settings it did not have yet."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("AGV_FE_")}
    dumped = settings.model_dump(
        mode="json", exclude={"auth": {"token"}, "database": {"url"}}, exclude_defaults=changed_only
    )
    if settings.auth.token is not None:
        dumped.setdefault("auth", {})["token"] = settings.auth.token.get_secret_value()
    if settings.database_url is not None:
        dumped.setdefault("database", {})["url"] = settings.database_url

    def text(value: Any) -> str:
        return json.dumps(value) if isinstance(value, bool | list | dict) else str(value)

    for key, value in dumped.items():
        if isinstance(value, dict):
            env.update({f"AGV_FE_{key}__{k}".upper(): text(v) for k, v in value.items() if v is not None})
        elif value is not None:
            env[f"AGV_FE_{key}".upper()] = text(value)
    return env


class ServiceProcess:
    """``agv-fe serve`` as a separate process, in its own session, so that a test can kill it as a crash would.

    The process and the synthesis workers it spawns form one process group; :meth:`close` ends what is left of it.
    Its log (stdout and stderr) goes to ``log_path``; ``args`` follow ``agv-fe serve`` on its command line and
    ``env`` is laid over the environment of ``settings``. ``cwd``, when given, is the directory the process starts
    in: a checkout there is the code it runs (``python -m`` puts the working directory first on the import path),
    which lets a benchmark run an earlier commit's service beside this one.
    """

    def __init__(
        self,
        settings: Settings,
        log_path: Path,
        *args: str,
        env: Mapping[str, str] | None = None,
        cwd: Path | None = None,
    ) -> None:
        self.settings = settings
        self.log_path = log_path
        self.args = args
        # another checkout's service gets only what differs from the defaults (it may not know every setting)
        self.env = {**settings_env(settings, changed_only=cwd is not None), **(env or {})}
        self.cwd = cwd
        self.url = f"http://127.0.0.1:{settings.http.port}"
        self.http = httpx.Client(base_url=self.url, timeout=30.0)
        token = settings.auth.token
        self.auth = {} if token is None else {"Authorization": f"Bearer {token.get_secret_value()}"}
        self.process: subprocess.Popen[bytes] | None = None

    def start(self, wait_healthy: bool = True) -> ServiceProcess:
        """Start the process; by default, wait until /health answers 200."""
        with self.log_path.open("ab") as log:
            self.process = subprocess.Popen(
                [sys.executable, "-m", "agv_fe", "serve", *self.args],
                env=self.env,
                cwd=self.cwd,
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        if wait_healthy:
            wait_for(self._answers, what=f"the service process to answer on {self.url}")
        return self

    def _answers(self) -> bool:
        if self.process is None or self.process.poll() is not None:
            raise RuntimeError(f"the service process exited:\n{self.log()}")
        try:
            return self.http.get("/health", timeout=1.0).status_code == 200
        except httpx.TransportError:
            return False

    def wait_ready(self, timeout: float = WAIT_S) -> None:
        """Wait until /ready answers 200: every profile has certified gains [s]."""
        wait_for(lambda: self.http.get("/ready").status_code == 200, timeout, what="/ready")

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def get(self, path: str, **kw: Any) -> httpx.Response:
        return self.http.get(path, **kw)

    def kill(self) -> None:
        """SIGKILL the service process, as a crash or the OOM killer would: no shutdown code runs."""
        if self.process is None:
            raise RuntimeError("the service process was not started")
        self.process.send_signal(signal.SIGKILL)
        self.process.wait(WAIT_S)

    def survivors(self) -> list[int]:
        """Live processes (not zombies) left in the service's process group: its synthesis workers, if any."""
        if self.process is None:
            return []
        pids = []
        for stat in Path("/proc").glob("[0-9]*/stat"):
            try:
                state, _ppid, pgrp = stat.read_text().rsplit(")", 1)[1].split()[:3]
            except (OSError, ValueError):
                continue  # the process ended while we looked
            if int(pgrp) == self.process.pid and state != "Z":
                pids.append(int(stat.parent.name))
        return pids

    def close(self) -> None:
        """Stop the process if it still runs (SIGTERM, then SIGKILL), then any process left in its group."""
        self.http.close()
        if self.process is None:
            return
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(WAIT_S)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(WAIT_S)
        with suppress(ProcessLookupError):
            os.killpg(self.process.pid, signal.SIGKILL)


@contextmanager
def service_process(
    settings: Settings,
    log_path: Path,
    *args: str,
    env: Mapping[str, str] | None = None,
    cwd: Path | None = None,
) -> Iterator[ServiceProcess]:
    """A started :class:`ServiceProcess` (healthy, not necessarily ready), closed on the way out."""
    server = ServiceProcess(settings, log_path, *args, env=env, cwd=cwd)
    try:
        yield server.start()
    finally:
        server.close()


class SteadyFleet:
    """Vehicles each sending a constant sample at 100 Hz from a thread of their own (bounded by ``max_s``), and when
    every estimate arrived, by vehicle: the load of the failover benchmark and of the bucket-lease tests.

    The caller owns ``session`` (and closes it after :meth:`close`); a vehicle put in :attr:`silenced` stops sending.
    """

    def __init__(self, session: zenoh.Session, vehicles: list[str], max_s: float = 600.0) -> None:
        self.seq = dict.fromkeys(vehicles, 0)
        self.silenced: set[str] = set()
        #: (time.monotonic(), vehicle, seq) of each estimate, appended by Zenoh's thread
        self.arrivals: list[tuple[float, str, int]] = []
        self._pubs = {
            v: session.declare_publisher(vehicle_key(v, "meas"), congestion_control=zenoh.CongestionControl.BLOCK)
            for v in vehicles
        }
        self._sub = session.declare_subscriber(fleet_selector("estimate"), self._arrived)
        self._max_s = max_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._send, name="steady-fleet", daemon=True)

    def start(self) -> SteadyFleet:
        self._thread.start()
        return self

    def _arrived(self, sample: zenoh.Sample) -> None:
        estimate = Estimate.decode(sample.payload.to_bytes())
        self.arrivals.append((time.monotonic(), estimate.vehicle, estimate.seq))

    def _send(self) -> None:
        t0_ns = time.time_ns()
        deadline = time.monotonic() + self._max_s
        while not self._stop.is_set() and time.monotonic() < deadline:
            for vehicle, pub in self._pubs.items():
                if vehicle not in self.silenced:
                    k = self.seq[vehicle]
                    pub.put(Measurement(vehicle, k, t0_ns + k * 10_000_000, 10.0, 0.0, 60.0, 0.0).encode())
                    self.seq[vehicle] = k + 1
            self._stop.wait(0.01)

    def estimated_since(self, t0: float, marks: dict[str, int]) -> dict[str, float]:
        """For each vehicle: when its first estimate of a sample at or beyond its mark arrived after ``t0``."""
        first: dict[str, float] = {}
        for arrived, vehicle, seq in list(self.arrivals):
            if arrived >= t0 and seq >= marks.get(vehicle, 0) and vehicle not in first:
                first[vehicle] = arrived
        return first

    def close(self) -> None:
        self._stop.set()
        self._thread.join(30)
        entities: list[Any] = [self._sub, *self._pubs.values()]
        for entity in entities:
            entity.undeclare()
