"""Real parts for the service tests: a uvicorn server in a thread, Zenoh clients on loopback, plant data."""

from __future__ import annotations

import json
import re
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import uvicorn
import zenoh

# the harness the benchmarks and the tests share, imported by the tests from here
from agv_fe.benchmarks.harness import WAIT_S as WAIT_S
from agv_fe.benchmarks.harness import ServiceProcess as ServiceProcess
from agv_fe.benchmarks.harness import free_port as free_port
from agv_fe.benchmarks.harness import service_process as service_process
from agv_fe.benchmarks.harness import settings_env as settings_env
from agv_fe.benchmarks.harness import wait_for as wait_for
from agv_protocol.wire import Alarm, Estimate, Measurement, fleet_selector, vehicle_key
from edge_client.library import paper_1
from edge_client.plant import PlantSimulator
from service.app import Service
from service.main import create_app
from service.settings import Settings
from service.transport import open_session

#: A design that solves in well under a second: tests that need some certified gains use it.
FAST_DESIGN: dict[str, Any] = {"design": "paper", "fault_order": 1, "lyapunov": "common", "optimise_decay_rate": False}
TOKEN = "test-token-0123456789"
T0_NS = 1_700_000_000_000_000_000
PERIOD_NS = 10_000_000


def write_profiles(path: Path, profiles: dict[str, dict[str, Any]]) -> Path:
    path.write_text(json.dumps({"profiles": profiles}))
    return path


def make_settings(tmp_path: Path, profiles: dict[str, dict[str, Any]] | None = None, **overrides: Any) -> Settings:
    profiles = profiles if profiles is not None else {"default": {"design": FAST_DESIGN}}
    tmp_path.mkdir(parents=True, exist_ok=True)
    data: dict[str, Any] = {
        "data_dir": str(tmp_path / "data"),
        "profiles_file": str(write_profiles(tmp_path / "profiles.json", profiles)),
        "http": {"port": free_port()},
        "auth": {"token": TOKEN},
        "zenoh": {"endpoint": f"tcp/127.0.0.1:{free_port()}", "estimate_congestion": "block"},
        "ingest": {"housekeeping_interval_s": 0.05},
    }
    for key, value in overrides.items():
        data[key] = {**data[key], **value} if isinstance(value, dict) and isinstance(data.get(key), dict) else value
    return Settings.model_validate(data)


class RunningService:
    """The real app on a real uvicorn server, in a background thread."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.app = create_app(settings)
        self.server = uvicorn.Server(
            uvicorn.Config(self.app, host="127.0.0.1", port=settings.http.port, log_level="warning", lifespan="on")
        )
        self.thread = threading.Thread(target=self.server.run, name="uvicorn", daemon=True)
        self.url = f"http://127.0.0.1:{settings.http.port}"
        self.http = httpx.Client(base_url=self.url, timeout=30.0)
        self.auth = {"Authorization": f"Bearer {TOKEN}"}

    @property
    def service(self) -> Service:
        service: Service = self.app.state.service
        return service

    def start(self) -> RunningService:
        self.thread.start()
        wait_for(lambda: self.server.started or not self.thread.is_alive(), what="uvicorn start")
        if not self.server.started:
            raise AssertionError("the server did not start")
        return self

    def wait_ready(self) -> None:
        wait_for(lambda: self.http.get("/ready").json()["ready"], what="/ready")

    def stop(self) -> None:
        self.http.close()
        self.server.should_exit = True
        self.thread.join(WAIT_S)
        if self.thread.is_alive():
            raise AssertionError("the server did not stop")

    def get(self, path: str, **kw: Any) -> httpx.Response:
        return self.http.get(path, **kw)

    def vehicle(self, vehicle_id: str) -> dict[str, Any]:
        response = self.http.get(f"/vehicles/{vehicle_id}")
        assert response.status_code == 200, response.text
        return dict(response.json())


@contextmanager
def running(settings: Settings, ready: bool = True) -> Iterator[RunningService]:
    server = RunningService(settings).start()
    try:
        if ready:
            server.wait_ready()
        yield server
    finally:
        server.stop()


@dataclass
class Received:
    estimates: list[Estimate]
    alarms: list[Alarm]


class Probe:
    """A Zenoh client on loopback: publishes measurements (BLOCK, nothing lost) and collects estimates and alarms."""

    def __init__(self, endpoint: str, prefix: str = "agv") -> None:
        self.session = open_session("client", endpoint)
        self.prefix = prefix
        self._est = self.session.declare_subscriber(
            fleet_selector("estimate", prefix), zenoh.handlers.FifoChannel(1 << 20)
        )
        self._alarm = self.session.declare_subscriber(
            fleet_selector("alarm", prefix), zenoh.handlers.FifoChannel(1 << 16)
        )
        self._pubs: dict[str, Any] = {}
        self.received = Received([], [])

    def put_raw(self, key: str, payload: bytes) -> None:
        pub = self._pubs.get(key)
        if pub is None:
            pub = self._pubs[key] = self.session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK
            )
        pub.put(payload)

    def put(self, m: Measurement) -> None:
        self.put_raw(vehicle_key(m.vehicle_id, "meas", self.prefix), m.encode())

    def collect(self) -> Received:
        while (s := self._est.try_recv()) is not None:
            self.received.estimates.append(Estimate.decode(s.payload.to_bytes()))
        while (s := self._alarm.try_recv()) is not None:
            self.received.alarms.append(Alarm.decode(s.payload.to_bytes()))
        return self.received

    def estimates_of(self, vehicle_id: str) -> list[Estimate]:
        return [e for e in self.collect().estimates if e.vehicle == vehicle_id]

    def close(self) -> None:
        for entity in [self._est, self._alarm, *self._pubs.values()]:
            entity.undeclare()
        self.session.close()


@contextmanager
def probe(endpoint: str) -> Iterator[Probe]:
    p = Probe(endpoint)
    try:
        time.sleep(0.3)  # let the subscriptions reach the router
        yield p
    finally:
        p.close()


def plant_measurements(
    vehicle_ids: list[str], n_samples: int, seq0: int = 0, scenario: Any = None
) -> list[list[Measurement]]:
    """Noise-free paper scenario 1 (or ``scenario``) for each vehicle: samples[k][i] is vehicle i at sample k."""
    scen = scenario or paper_1()
    sim = PlantSimulator([scen] * len(vehicle_ids))
    out = []
    for k in range(n_samples):
        s = sim.step()
        out.append(
            [
                Measurement(vid, seq0 + k, T0_NS + (seq0 + k) * PERIOD_NS, *s.y[i].tolist(), *s.u[i].tolist())
                for i, vid in enumerate(vehicle_ids)
            ]
        )
    return out


def constant_measurement(
    vehicle_id: str, seq: int, vx: float = 10.0, r: float = 0.0, torque: float = 60.0
) -> Measurement:
    return Measurement(vehicle_id, seq, T0_NS + seq * PERIOD_NS, vx, r, torque, 0.0)


def as_array(estimates: list[Estimate]) -> np.ndarray:
    return np.array([[e.vx, e.vy, e.r, e.torque_fault, e.steer_fault] for e in estimates])


_METRIC_SAMPLE = re.compile(r"^([A-Za-z_:][A-Za-z0-9_:]*)(?:\{(.*)\})? (\S+)$")
_METRIC_LABEL = re.compile(r'([A-Za-z_][A-Za-z0-9_]*)="((?:[^"\\]|\\.)*)"')


@dataclass
class Metrics:
    """One Prometheus text scrape: each metric family's type, and each sample by name and labels."""

    types: dict[str, str]
    samples: dict[tuple[str, frozenset[tuple[str, str]]], float]

    def value(self, name: str, **labels: str) -> float:
        key = (name, frozenset(labels.items()))
        if key not in self.samples:
            raise AssertionError(f"no sample {name}{labels or ''} in the scrape")
        return self.samples[key]

    def buckets(self, name: str) -> list[tuple[float, float]]:
        """(le, cumulative count) of histogram ``name``, in order of le."""
        rows = [(float(dict(labels)["le"]), v) for (n, labels), v in self.samples.items() if n == f"{name}_bucket"]
        return sorted(rows)


def parse_metrics(text: str) -> Metrics:
    """Parse the Prometheus text format (0.0.4); a line that is neither a comment nor a sample fails the test."""
    types: dict[str, str] = {}
    samples: dict[tuple[str, frozenset[tuple[str, str]]], float] = {}
    for line in text.splitlines():
        if line.startswith("# TYPE "):
            _, _, name, kind = line.split(" ", 3)
            types[name] = kind
        elif line and not line.startswith("#"):
            match = _METRIC_SAMPLE.match(line)
            if match is None:
                raise AssertionError(f"not a Prometheus sample: {line!r}")
            name, label_text, value = match.groups()
            labels = frozenset(_METRIC_LABEL.findall(label_text or ""))
            samples[(name, labels)] = float(value)
    return Metrics(types, samples)


def job_done(server: RunningService | ServiceProcess, job_id: str) -> dict[str, Any] | None:
    """The job once it has finished (succeeded, failed, superseded or interrupted), else None."""
    job: dict[str, Any] = server.get(f"/jobs/{job_id}").json()
    return job if job["status"] in ("succeeded", "failed", "superseded", "interrupted") else None
