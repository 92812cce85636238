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
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import httpx
import zenoh

from agv_fe.benchmarks import report_header
from agv_fe.benchmarks.harness import SteadyFleet
from agv_fe.pg_cluster import PostgresServer, free_port
from agv_protocol.wire import N_BUCKETS, bucket_of
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


def _one_kill(fleet: SteadyFleet, replicas: list[Replica]) -> dict[str, Any]:
    shares = _wait(lambda: _balanced(replicas), "balanced buckets")
    victim = max(replicas, key=lambda r: (len(shares[r.name]), r.name))
    its = [v for v in VEHICLES if bucket_of(v) in shares[victim.name]]
    killed_at = time.monotonic()
    victim.kill()
    marks = dict(fleet.seq)
    first = _wait(
        lambda: (lambda f: f if set(its) <= set(f) else None)(fleet.estimated_since(killed_at, marks)), "takeover"
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
        fleet = SteadyFleet(session, VEHICLES, max_s=3600.0).start()
        try:
            _wait(lambda: set(fleet.estimated_since(0.0, {})) == set(VEHICLES), "estimates of every vehicle")
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
