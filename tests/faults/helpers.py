"""Fault injection on real parts: a database another process locks, a data directory on a small tmpfs that fills,
a Zenoh router process that is killed and restarted, and a measurement stream that keeps going meanwhile."""

from __future__ import annotations

import errno
import os
import sqlite3
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

from tests.service.helpers import Probe, constant_measurement

ROUTER_SCRIPT = Path(__file__).resolve().parents[1] / "edge_client" / "zenoh_router.py"


class Stream:
    """Vehicles sending one constant sample per round, each with its own rising sequence number."""

    def __init__(self, probe: Probe, vehicle_ids: list[str]) -> None:
        self.probe = probe
        self.vehicle_ids: list[str] = []
        self.seq: dict[str, int] = {}
        self.add(vehicle_ids)

    def add(self, vehicle_ids: list[str]) -> None:
        """More vehicles, from the next round on."""
        self.vehicle_ids += vehicle_ids
        self.seq.update(dict.fromkeys(vehicle_ids, 0))

    def round(self) -> None:
        for vehicle_id in self.vehicle_ids:
            self.probe.put(constant_measurement(vehicle_id, self.seq[vehicle_id]))
            self.seq[vehicle_id] += 1
        time.sleep(0.01)  # 100 Hz

    def latest_estimate(self, vehicle_id: str) -> int:
        """The sequence number of the vehicle's latest estimate, -1 if none came."""
        return max((e.seq for e in self.probe.estimates_of(vehicle_id)), default=-1)

    def estimated_beyond(self, marks: dict[str, int]) -> bool:
        """Send a round; true once every vehicle has an estimate newer than its mark."""
        self.round()
        return all(self.latest_estimate(v) > marks.get(v, -1) for v in self.vehicle_ids)


@contextmanager
def exclusive_lock(database: Path) -> Iterator[sqlite3.Connection]:
    """Another process's connection holding the database's write lock (BEGIN EXCLUSIVE) until the block ends."""
    lock = sqlite3.connect(database, timeout=10.0, isolation_level=None)
    try:
        lock.execute("BEGIN EXCLUSIVE")
        yield lock
        lock.execute("ROLLBACK")
    finally:
        lock.close()


def stored_vehicles(database: Path) -> set[str]:
    """The vehicle ids in the database, read by a connection of the test's own (WAL: readers never wait)."""
    with sqlite3.connect(database, timeout=10.0) as db:
        return {row[0] for row in db.execute("SELECT id FROM vehicles")}


def truncate_journal(database: Path) -> None:
    """Checkpoint the write-ahead log into the database and truncate it to zero bytes."""
    db = sqlite3.connect(database, timeout=10.0, isolation_level=None)
    try:
        busy, _, _ = db.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchone()
    finally:
        db.close()
    if busy:
        raise AssertionError(f"{database}: the checkpoint could not truncate the journal")


@contextmanager
def small_filesystem(directory: Path, size: str) -> Iterator[Path]:
    """A tmpfs of ``size`` mounted on ``directory`` (needs root and CAP_SYS_ADMIN; the test is skipped without)."""
    directory.mkdir(parents=True, exist_ok=True)
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(directory)], capture_output=True, text=True
    )
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root and CAP_SYS_ADMIN): {mounted.stderr.strip()}")
    try:
        yield directory
    finally:
        subprocess.run(["umount", "-l", str(directory)], check=True)


def fill(path: Path) -> int:
    """Write ``path`` until its file system has no byte left (ENOSPC); returns the bytes written."""
    written = 0
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
    try:
        for chunk in (1 << 20, 1 << 16, 1 << 12, 1):
            block = b"\0" * chunk
            while True:  # bounded by the file system's size
                try:
                    written += os.write(fd, block)
                except OSError as exc:
                    if exc.errno != errno.ENOSPC:
                        raise
                    break
    finally:
        os.close(fd)
    return written


class RouterProcess:
    """A Zenoh router in a child process on a fixed loopback port (tests/edge_client/zenoh_router.py)."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.endpoint = f"tcp/127.0.0.1:{port}"
        self.process: subprocess.Popen[str] | None = None

    def start(self) -> RouterProcess:
        self.process = subprocess.Popen(
            [sys.executable, str(ROUTER_SCRIPT), str(self.port)], stdout=subprocess.PIPE, text=True
        )
        assert self.process.stdout is not None
        line = self.process.stdout.readline().strip()  # the script prints "ready" once it listens
        if line != "ready":
            self.stop()
            raise AssertionError(f"the router on port {self.port} did not start: {line!r}")
        return self

    def kill(self) -> None:
        """SIGKILL: a crash, no goodbye to the clients."""
        if self.process is not None:
            self.process.kill()
            self.process.wait(timeout=30)
            self.process = None

    def stop(self) -> None:
        if self.process is not None:
            self.process.terminate()
            try:
                self.process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout=30)
            self.process = None


def ready_body(server: Any) -> tuple[int, dict[str, Any]]:
    answer = server.get("/ready")
    return answer.status_code, dict(answer.json())
