# mypy: disable-error-code="no-untyped-call"
"""Failover with bucket leases: how long a dead replica's vehicles go without estimates.

A throwaway PostgreSQL server (agv_fe/pg_cluster.py, Debian's binaries), a Zenoh router (this process, on
loopback) and three `agv-fe serve` replicas, Zenoh clients of it, sharing the 16 buckets by leases with the
default settings (lease_interval_s 0.5). 60 vehicles publish at 100 Hz from this process, which also subscribes
to every estimate. Five times, the replica serving the most buckets is killed with SIGKILL; each of its vehicles'
takeover time is the time from the kill to the arrival of the first estimate of a sample it sent after the
process was gone, which only a survivor can have made; the replica is then started again and the buckets are
left to rebalance before the next kill.
"""

from __future__ import annotations

import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import httpx
import zenoh

from agv_fe.benchmarks import report_header
from agv_fe.pg_cluster import PostgresServer, free_port
from service.protocol import N_BUCKETS, Estimate, Measurement, bucket_of, fleet_selector
from service.transport import open_session

KILLS = 5
VEHICLES = [f"veh-{k:02d}" for k in range(60)]
REPLICAS = ("r0", "r1", "r2")
WAIT_S = 300.0


class Replica:
    """`agv-fe serve` with bucket leases on the shared database, as a process of its own."""

    def __init__(self, name: str, endpoint: str, url: str, data_dir: Path) -> None:
        self.name, self.port = name, free_port()
        self.cmd = [sys.executable, "-m", "agv_fe", "serve", "--zenoh-mode", "client", "--zenoh-endpoint", endpoint,
                    "--database-url", url, "--data-dir", str(data_dir / name), "--http-port", str(self.port),
                    "--log-level", "warning"]  # fmt: skip
        self.env = {**os.environ, "AGV_FE_AUTH__TOKEN": "bench", "AGV_FE_SHARD__REPLICA_ID": name}
        self.http = httpx.Client(base_url=f"http://127.0.0.1:{self.port}", timeout=10)
        self.log_path = data_dir / f"{name}.log"
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        with self.log_path.open("ab") as log:
            self.proc = subprocess.Popen(
                self.cmd, env=self.env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True
            )

    def ready(self) -> bool:
        try:
            return bool(self.http.get("/ready").json()["ready"])
        except (httpx.TransportError, ValueError):
            return False

    def buckets(self) -> set[str]:
        return set(self.http.get("/health").json()["buckets"])

    def kill(self) -> None:
        if self.proc is not None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(60)
            self.proc = None

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
            self.proc = None
        self.http.close()


def _wait(condition: Any, what: str) -> Any:
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.05)
    raise RuntimeError(f"failover benchmark: no {what} within {WAIT_S:g} s")


def _balanced(replicas: list[Replica]) -> dict[str, set[str]] | None:
    shares = {r.name: r.buckets() for r in replicas}
    sizes = sorted(len(s) for s in shares.values())
    union = set().union(*shares.values())
    ok = sum(sizes) == N_BUCKETS and len(union) == N_BUCKETS and sizes[-1] - sizes[0] <= 1
    return shares if ok else None


class Fleet:
    """The vehicles at 100 Hz on a thread, and when each estimate arrived."""

    def __init__(self, session: zenoh.Session) -> None:
        self.seq = dict.fromkeys(VEHICLES, 0)
        self.arrivals: list[tuple[float, str, int]] = []
        self._pubs = {v: session.declare_publisher(f"agv/v1/{bucket_of(v)}/{v}/meas") for v in VEHICLES}
        self._sub = session.declare_subscriber(fleet_selector("estimate"), self._arrived)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._send, daemon=True)
        self._thread.start()

    def _arrived(self, sample: zenoh.Sample) -> None:
        estimate = Estimate.decode(sample.payload.to_bytes())
        self.arrivals.append((time.monotonic(), estimate.vehicle, estimate.seq))

    def _send(self) -> None:
        t0_ns = time.time_ns()
        while not self._stop.is_set():
            for vehicle, pub in self._pubs.items():
                k = self.seq[vehicle]
                pub.put(Measurement(vehicle, k, t0_ns + k * 10_000_000, 10.0, 0.0, 60.0, 0.0).encode())
                self.seq[vehicle] = k + 1
            self._stop.wait(0.01)

    def first_after(self, t0: float, marks: dict[str, int]) -> dict[str, float]:
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


@contextmanager
def _cluster(work: Path) -> Iterator[tuple[zenoh.Session, list[Replica]]]:
    with ExitStack() as stack:
        server = PostgresServer().init()
        stack.callback(server.close)
        url = server.database()
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        session = open_session("router", endpoint)
        stack.callback(session.close)
        replicas = [Replica(name, endpoint, url, work) for name in REPLICAS]
        for replica in replicas:
            stack.callback(replica.stop)
            replica.start()
        _wait(lambda: all(r.ready() for r in replicas), "three ready replicas")
        _wait(lambda: _balanced(replicas), "balanced buckets")
        yield session, replicas


def _one_kill(fleet: Fleet, replicas: list[Replica]) -> dict[str, Any]:
    shares = _wait(lambda: _balanced(replicas), "balanced buckets")
    victim = max(replicas, key=lambda r: (len(shares[r.name]), r.name))
    its = [v for v in VEHICLES if bucket_of(v) in shares[victim.name]]
    killed_at = time.monotonic()
    victim.kill()
    marks = dict(fleet.seq)
    first = _wait(
        lambda: (lambda f: f if set(its) <= set(f) else None)(fleet.first_after(killed_at, marks)), "takeover"
    )
    delays = sorted(first[v] - killed_at for v in its)
    survivors = [r for r in replicas if r is not victim]
    _wait(lambda: _balanced(survivors), "buckets shared by the survivors")
    victim.start()
    _wait(victim.ready, "the restarted replica")
    return {"victim": victim.name, "buckets": len(shares[victim.name]), "vehicles": len(its), "delays_s": delays}


def run(out_dir: Path, kills: int = KILLS) -> Path:
    results = []
    with tempfile.TemporaryDirectory() as work, _cluster(Path(work)) as (session, replicas):
        fleet = Fleet(session)
        try:
            _wait(lambda: set(fleet.first_after(0.0, {})) == set(VEHICLES), "estimates of every vehicle")
            for _ in range(kills):
                results.append(_one_kill(fleet, replicas))
        finally:
            fleet.close()
    return _write(out_dir, results)


def _write(out_dir: Path, results: list[dict[str, Any]]) -> Path:
    every = sorted(d for r in results for d in r["delays_s"])
    lines = [
        report_header("Failover with bucket leases", "failover").rstrip("\n") + "\n",
        (__doc__ or "").split("\n\n", 1)[1].replace("\n", " ").strip() + "\n",
        "| kill | replica | buckets | vehicles | takeover p50 [s] | takeover max [s] |",
        "|---|---|---|---|---|---|",
    ]
    for k, r in enumerate(results, 1):
        d = r["delays_s"]
        lines.append(
            f"| {k} | {r['victim']} | {r['buckets']} | {r['vehicles']} | {statistics.median(d):.2f} | {d[-1]:.2f} |"
        )
    lines.append(
        f"\nOver the {len(results)} kills ({len(every)} vehicles taken over): takeover p50 "
        f"{statistics.median(every):.2f} s, max {every[-1]:.2f} s.\n"
    )
    path = out_dir / "failover.md"
    path.write_text("\n".join(lines))
    (out_dir / "failover.json").write_text(json.dumps(results, indent=1) + "\n")
    return path
