"""Real parts for the dashboard tests: the service on uvicorn, a live simulated fleet on Zenoh, headless Chromium."""

from __future__ import annotations

import os
import shutil
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import uvicorn
import zenoh

from agv_protocol.wire import GroundTruth, Measurement, vehicle_key
from edge_client.faults import BiasFault
from edge_client.plant import PlantSimulator
from edge_client.scenario import Manoeuvre, Scenario, SpeedPoint
from service.settings import Settings
from service.transport import open_session
from tests.service.helpers import WAIT_S, RunningService

#: Where the browser tests put their screenshots (gitignored).
OUTPUT_DIR = Path(__file__).resolve().parents[2] / "test-output" / "web"
#: Chromium flags for a headless run with no network beyond loopback.
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-quic",
    "--no-first-run",
    "--disable-component-update",
    "--disable-sync",
]
#: The live fleet stops by itself after this long, whatever the tests do [s].
FLEET_MAX_S = 240.0


def chromium_executable() -> str | None:
    """Debian's chromium, or the executable named by AGV_FE_CHROMIUM alone when set; None when not installed."""
    override = os.environ.get("AGV_FE_CHROMIUM")
    candidates = [override] if override else ["/usr/bin/chromium", shutil.which("chromium")]
    for candidate in candidates:
        if candidate and Path(candidate).is_file() and os.access(candidate, os.X_OK):
            return candidate
    return None


class DashboardServer(RunningService):
    """The service on uvicorn; open browser streams are cut 2 s into a shutdown instead of holding it forever."""

    def __init__(self, settings: Settings) -> None:
        super().__init__(settings)
        self.server = uvicorn.Server(
            uvicorn.Config(
                self.app,
                host="127.0.0.1",
                port=settings.http.port,
                log_level="warning",
                lifespan="on",
                timeout_graceful_shutdown=2,
            )
        )
        self.thread = threading.Thread(target=self.server.run, name="uvicorn", daemon=True)

    def stop(self) -> None:
        if self.server.started:
            self.service.dashboard.end_streams_threadsafe()  # as agv-fe serve does on a signal
        super().stop()


@contextmanager
def dashboard_server(settings: Settings) -> Iterator[DashboardServer]:
    server = DashboardServer(settings)
    server.start()
    try:
        server.wait_ready()
        yield server
    finally:
        server.stop()


def cruise(name: str, *faults: Any, duration_s: float = 600.0, seed: int = 0) -> Scenario:
    """A vehicle at about 10 m/s doing slow lane changes, with the given faults."""
    return Scenario(
        name=name,
        duration_s=duration_s,
        initial_speed_mps=10.0,
        speed_profile=(SpeedPoint(t_s=0.0, speed_mps=10.0), SpeedPoint(t_s=30.0, speed_mps=12.0)),
        manoeuvres=tuple(
            Manoeuvre(kind="lane_change", start_s=2.0 + 8.0 * k, duration_s=6.0, amplitude_rad=0.02)
            for k in range(int(duration_s // 8))
        ),
        faults=faults,
        seed=seed,
    )


def torque_bias(magnitude_nm: float, onset_s: float = 2.0) -> BiasFault:
    return BiasFault(channel="torque", onset_s=onset_s, magnitude=magnitude_nm)


def steer_bias(magnitude_rad: float, onset_s: float = 2.0) -> BiasFault:
    return BiasFault(channel="steer", onset_s=onset_s, magnitude=magnitude_rad)


class LiveFleet:
    """Simulated vehicles publishing measurements and ground truth at 100 Hz in real time, in a thread.

    ``silent_after_s`` makes a vehicle stop publishing after that long (it goes STALE); a vehicle in
    ``grades`` sends that road grade [rad] with every sample (flag bit 1; the plant stays on level ground,
    so send 0 to leave its estimates as they are). The thread stops on :meth:`close` or after ``max_s``,
    whichever comes first.
    """

    def __init__(
        self,
        endpoint: str,
        scenarios: dict[str, Scenario],
        silent_after_s: dict[str, float] | None = None,
        max_s: float = FLEET_MAX_S,
        grades: dict[str, float] | None = None,
    ) -> None:
        self.ids = list(scenarios)
        self.plant = PlantSimulator(list(scenarios.values()))
        self.silent_after_s = silent_after_s or {}
        self.grades = grades or {}
        self.max_s = max_s
        self.session = open_session("client", endpoint)
        block = zenoh.CongestionControl.BLOCK
        declare = self.session.declare_publisher
        self._meas = [declare(vehicle_key(v, "meas"), congestion_control=block) for v in self.ids]
        self._truth = [declare(vehicle_key(v, "truth"), congestion_control=block) for v in self.ids]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="live-fleet", daemon=True)
        self.samples = 0
        self.t0_ns = 0

    def start(self) -> LiveFleet:
        self._thread.start()
        return self

    def _run(self) -> None:
        period_s = self.plant.sample_period_s
        self.t0_ns = time.time_ns()
        started = time.monotonic()
        k = 0
        while not self._stop.is_set() and time.monotonic() - started < self.max_s:
            delay = started + k * period_s - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            s = self.plant.step()
            t_ns = self.t0_ns + round(k * period_s * 1e9)
            for i, vehicle_id in enumerate(self.ids):
                if k * period_s >= self.silent_after_s.get(vehicle_id, float("inf")):
                    continue
                vx, r = s.y[i].tolist()
                torque, steer = s.u[i].tolist()
                grade = self.grades.get(vehicle_id)
                self._meas[i].put(Measurement(vehicle_id, k, t_ns, vx, r, torque, steer, grade_rad=grade).encode())
                true_vx, true_vy, true_r = s.x[i].tolist()
                true_tf, true_df = s.f[i].tolist()
                truth = GroundTruth(
                    vehicle=vehicle_id,
                    seq=k,
                    t_ns=t_ns,
                    vx=true_vx,
                    vy=true_vy,
                    r=true_r,
                    torque_fault=true_tf,
                    steer_fault=true_df,
                )
                self._truth[i].put(truth.encode())
            k += 1
            self.samples = k

    def close(self) -> None:
        self._stop.set()
        self._thread.join(WAIT_S)
        for publisher in [*self._meas, *self._truth]:
            publisher.undeclare()
        self.session.close()  # type: ignore[no-untyped-call]


@contextmanager
def live_fleet(endpoint: str, scenarios: dict[str, Scenario], **kw: Any) -> Iterator[LiveFleet]:
    fleet = LiveFleet(endpoint, scenarios, **kw).start()
    try:
        yield fleet
    finally:
        fleet.close()


#: Demanded torque that holds v_x = 10 m/s against drag, C_x v_x^2 (eq. 1) [N m].
CRUISE_TORQUE_NM = 0.37 * 10.0**2


class SteadyFleet:
    """Many vehicles cruising straight at 10 m/s, one sample each per round at ``rate_hz`` (a thread).

    A vehicle with a torque fault T_f demands ``CRUISE_TORQUE_NM - T_f``: the measurement is then exactly
    a steady state of eq. (1) with that fault, so its estimate converges to T_f. Samples are 10 ms apart in
    vehicle time whatever ``rate_hz``. Vehicles in ``silent_after_s`` stop after that long (wall clock).
    ``vx_jitter_mps`` alternates the measured speed by that much, like a little sensor noise, so that
    every estimate (and every fleet row) keeps changing.
    """

    def __init__(
        self,
        endpoint: str,
        torque_faults_nm: dict[str, float],
        rate_hz: float = 10.0,
        silent_after_s: dict[str, float] | None = None,
        vx_jitter_mps: float = 0.0,
        max_s: float = FLEET_MAX_S,
    ) -> None:
        self.session = open_session("client", endpoint)
        self.vx_jitter_mps = vx_jitter_mps
        self.vehicles = [(vehicle_key(v, "meas"), v, CRUISE_TORQUE_NM - fault) for v, fault in torque_faults_nm.items()]
        self.rate_hz = rate_hz
        self.silent_after_s = silent_after_s or {}
        self.max_s = max_s
        self.rounds = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="steady-fleet", daemon=True)

    def start(self) -> SteadyFleet:
        self._thread.start()
        return self

    def _run(self) -> None:
        started = time.monotonic()
        put = self.session.put
        block = zenoh.CongestionControl.BLOCK
        t0_ns = time.time_ns()
        while not self._stop.is_set() and time.monotonic() - started < self.max_s:
            delay = started + self.rounds / self.rate_hz - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            k = self.rounds
            elapsed = time.monotonic() - started
            t_ns = t0_ns + k * 10_000_000
            vx = 10.0 + (self.vx_jitter_mps if k % 2 else -self.vx_jitter_mps)
            for key, vehicle_id, torque in self.vehicles:
                if elapsed >= self.silent_after_s.get(vehicle_id, float("inf")):
                    continue
                put(key, Measurement(vehicle_id, k, t_ns, vx, 0.0, torque, 0.0).encode(), congestion_control=block)
            self.rounds = k + 1

    def close(self) -> None:
        self._stop.set()
        self._thread.join(WAIT_S)
        self.session.close()  # type: ignore[no-untyped-call]


@contextmanager
def steady_fleet(endpoint: str, torque_faults_nm: dict[str, float], **kw: Any) -> Iterator[SteadyFleet]:
    fleet = SteadyFleet(endpoint, torque_faults_nm, **kw).start()
    try:
        yield fleet
    finally:
        fleet.close()
