"""Persistence: one storage interface, two databases.

Profiles, gain versions with their certificates, the vehicle registry,
alarms with their event history, and synthesis jobs. Every write is one
transaction. :class:`Storage` is the interface: every query, written once in
SQL that both databases accept; an implementation supplies the connection,
the transaction, the schema and which of its errors are transient.

* :class:`SqliteStorage`, the embedded default: one SQLite file (stdlib
  sqlite3, WAL journal, synchronous=FULL) in the data directory.
* ``service.storage_postgres.PostgresStorage``: a PostgreSQL server shared by
  several replicas (psycopg 3; the schema versioned by Alembic migrations in
  ``service/migrations``, applied at start).

A :class:`Storage` is one connection, used by one thread: the service reads
on the event loop's connection and writes through
:class:`service.storage_writer.StorageWriter`, which owns a second connection
on a thread of its own, so a locked, full or unreachable database never
blocks the event loop's writes.
"""

from __future__ import annotations

import json
import sqlite3
from abc import ABC, abstractmethod
from collections.abc import Iterable, Iterator, Sequence
from contextlib import AbstractContextManager, contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

SCHEMA_VERSION = 1

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS profiles (
    name TEXT PRIMARY KEY,
    spec TEXT NOT NULL,
    active_version TEXT,
    created_t_ns INTEGER NOT NULL,
    updated_t_ns INTEGER NOT NULL
);
CREATE TABLE IF NOT EXISTS gain_versions (
    profile TEXT NOT NULL,
    version TEXT NOT NULL,
    created_t_ns INTEGER NOT NULL,
    gains TEXT NOT NULL,
    PRIMARY KEY (profile, version)
);
CREATE TABLE IF NOT EXISTS vehicles (
    id TEXT PRIMARY KEY,
    profile TEXT NOT NULL,
    registered_t_ns INTEGER NOT NULL
);
CREATE TABLE IF NOT EXISTS vehicle_payloads (
    id TEXT PRIMARY KEY,
    payload_kg REAL NOT NULL,
    updated_t_ns INTEGER NOT NULL
);
CREATE TABLE IF NOT EXISTS alarms (
    id TEXT PRIMARY KEY,
    vehicle TEXT NOT NULL,
    kind TEXT NOT NULL,
    latched INTEGER NOT NULL,
    updated_t_ns INTEGER NOT NULL,
    record TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS alarms_latched ON alarms (latched, vehicle);
CREATE TABLE IF NOT EXISTS alarm_events (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    alarm_id TEXT NOT NULL,
    t_ns INTEGER NOT NULL,
    event TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS alarm_events_by_alarm ON alarm_events (alarm_id, seq);
CREATE TABLE IF NOT EXISTS jobs (
    id TEXT PRIMARY KEY,
    profile TEXT NOT NULL,
    created_t_ns INTEGER NOT NULL,
    record TEXT NOT NULL
);
"""


class StorageError(Exception):
    """The database cannot be opened or has an unexpected schema."""


class StorageUnavailable(StorageError):
    """A read or write could not reach the database (yet): the queue is full, the writer stopped, or the database
    fails."""


@dataclass(frozen=True)
class StoredProfile:
    name: str
    spec: dict[str, Any]
    active_version: str | None
    created_t_ns: int
    updated_t_ns: int
    #: why the stored spec is not even JSON (``spec`` is then empty); None when it parsed
    problem: str | None = None


class Cursor(Protocol):
    """What a transaction hands to the queries: sqlite3's connection and psycopg's cursor both have these."""

    def execute(self, sql: str, params: Sequence[Any] = ..., /) -> Any: ...

    def executemany(self, sql: str, params: Iterable[Sequence[Any]], /) -> Any: ...


class Storage(ABC):
    """The service's database: every query, written once; the connection is the implementation's.

    The SQL uses ``?`` placeholders and only what SQLite and PostgreSQL both accept (``ON CONFLICT ... DO``,
    ``excluded``, ``LIMIT``); an implementation translates the placeholders if its driver wants others.
    """

    #: errors after which the same write may succeed later (a lock, a full disk, a lost connection): the storage
    #: writer retries them; any other error is a write that cannot succeed
    transient_errors: tuple[type[BaseException], ...] = (OSError,)

    #: where the data lives, for messages (a path, or a URL without its password)
    location: str

    @abstractmethod
    def close(self) -> None: ...

    @abstractmethod
    def transaction(self) -> AbstractContextManager[Cursor]:
        """One durable unit of work: committed at the end of the block, rolled back on error."""

    @abstractmethod
    def _rows(self, sql: str, params: Sequence[Any] = ()) -> list[tuple[Any, ...]]:
        """The rows of one read query, outside any transaction."""

    def _profile_changed(self, db: Cursor, name: str) -> None:
        """Called in the transaction that changed a profile or its active gains (PostgreSQL tells the other
        replicas; an embedded database has none)."""
        return None

    def _row(self, sql: str, params: Sequence[Any] = ()) -> tuple[Any, ...] | None:
        rows = self._rows(sql, params)
        return rows[0] if rows else None

    # ------------------------------------------------------------------ profiles and gains

    def profiles(self) -> list[StoredProfile]:
        rows = self._rows("SELECT name, spec, active_version, created_t_ns, updated_t_ns FROM profiles ORDER BY name")
        out = []
        for name, text, active, created, updated in rows:
            try:
                spec = json.loads(text)
            except (json.JSONDecodeError, TypeError) as exc:
                out.append(StoredProfile(name, {}, active, created, updated, f"the stored spec is not JSON: {exc}"))
                continue
            if not isinstance(spec, dict):
                problem = f"the stored spec is JSON {type(spec).__name__}, not an object"
                out.append(StoredProfile(name, {}, active, created, updated, problem))
                continue
            out.append(StoredProfile(name, spec, active, created, updated))
        return out

    def put_profile(self, name: str, spec: dict[str, Any], t_ns: int, active_version: str | None = None) -> None:
        """Create or update a profile's spec (and, if given, its active version)."""
        with self.transaction() as db:
            db.execute(
                "INSERT INTO profiles (name, spec, active_version, created_t_ns, updated_t_ns) VALUES (?, ?, ?, ?, ?) "
                "ON CONFLICT(name) DO UPDATE SET spec = excluded.spec, updated_t_ns = excluded.updated_t_ns, "
                "active_version = COALESCE(excluded.active_version, profiles.active_version)",
                (name, json.dumps(spec), active_version, t_ns, t_ns),
            )
            self._profile_changed(db, name)

    def activate_gains(self, name: str, spec: dict[str, Any], gains: dict[str, Any], t_ns: int) -> None:
        """Store a gain version and make it the profile's active one, with the spec it was designed for."""
        version = gains["version"]
        with self.transaction() as db:
            db.execute(
                "INSERT INTO gain_versions (profile, version, created_t_ns, gains) VALUES (?, ?, ?, ?) "
                "ON CONFLICT (profile, version) DO NOTHING",
                (name, version, t_ns, json.dumps(gains)),
            )
            db.execute(
                "INSERT INTO profiles (name, spec, active_version, created_t_ns, updated_t_ns) VALUES (?, ?, ?, ?, ?) "
                "ON CONFLICT(name) DO UPDATE SET spec = excluded.spec, active_version = excluded.active_version, "
                "updated_t_ns = excluded.updated_t_ns",
                (name, json.dumps(spec), version, t_ns, t_ns),
            )
            self._profile_changed(db, name)

    def gains(self, profile: str, version: str) -> dict[str, Any] | None:
        row = self._row("SELECT gains FROM gain_versions WHERE profile = ? AND version = ?", (profile, version))
        if row is None:
            return None
        try:
            doc = json.loads(row[0])
        except (json.JSONDecodeError, TypeError) as exc:
            raise StorageError(f"{self.location}: gains {version} of profile {profile} are not JSON: {exc}") from exc
        if not isinstance(doc, dict):
            raise StorageError(f"{self.location}: gains {version} of profile {profile} are not a JSON object")
        return doc

    def gain_versions(self, profile: str) -> list[tuple[str, int]]:
        rows = self._rows(
            "SELECT version, created_t_ns FROM gain_versions WHERE profile = ? ORDER BY created_t_ns, version",
            (profile,),
        )
        return [(r[0], r[1]) for r in rows]

    # ------------------------------------------------------------------ vehicles

    def vehicles(self) -> list[tuple[str, str, int]]:
        return [(r[0], r[1], r[2]) for r in self._rows("SELECT id, profile, registered_t_ns FROM vehicles ORDER BY id")]

    def put_vehicles(self, rows: Iterable[tuple[str, str, int]]) -> None:
        with self.transaction() as db:
            db.executemany(
                "INSERT INTO vehicles (id, profile, registered_t_ns) VALUES (?, ?, ?) "
                "ON CONFLICT(id) DO UPDATE SET profile = excluded.profile",
                list(rows),
            )

    def payloads(self) -> dict[str, float]:
        """Each vehicle's last reported payload [kg] (PUT /vehicles/{id}/payload); vehicles never loaded are absent."""
        return {r[0]: float(r[1]) for r in self._rows("SELECT id, payload_kg FROM vehicle_payloads ORDER BY id")}

    def put_payload(self, vehicle_id: str, payload_kg: float, t_ns: int) -> None:
        with self.transaction() as db:
            db.execute(
                "INSERT INTO vehicle_payloads (id, payload_kg, updated_t_ns) VALUES (?, ?, ?) "
                "ON CONFLICT(id) DO UPDATE SET payload_kg = excluded.payload_kg, updated_t_ns = excluded.updated_t_ns",
                (vehicle_id, payload_kg, t_ns),
            )

    # ------------------------------------------------------------------ alarms

    def record_alarm_changes(self, changes: Iterable[tuple[dict[str, Any], dict[str, Any]]]) -> None:
        """Upsert alarm records and append their events, in one transaction: (record dict, event dict) pairs."""
        with self.transaction() as db:
            for record, event in changes:
                latched = not (record["state"] == "cleared" and record["acknowledged"])
                db.execute(
                    "INSERT INTO alarms (id, vehicle, kind, latched, updated_t_ns, record) VALUES (?, ?, ?, ?, ?, ?) "
                    "ON CONFLICT(id) DO UPDATE SET latched = excluded.latched, updated_t_ns = excluded.updated_t_ns, "
                    "record = excluded.record",
                    (
                        record["id"],
                        record["vehicle"],
                        record["kind"],
                        int(latched),
                        record["updated_t_ns"],
                        json.dumps(record),
                    ),
                )
                db.execute(
                    "INSERT INTO alarm_events (alarm_id, t_ns, event) VALUES (?, ?, ?)",
                    (record["id"], event["t_ns"], json.dumps(event)),
                )

    def latched_alarms(self) -> list[dict[str, Any]]:
        rows = self._rows("SELECT record FROM alarms WHERE latched = 1 ORDER BY updated_t_ns, id")
        return [dict(json.loads(r[0])) for r in rows]

    def alarms(self, vehicle: str | None = None, limit: int = 100) -> list[dict[str, Any]]:
        """Latched and closed alarms, newest first."""
        if vehicle is None:
            rows = self._rows("SELECT record FROM alarms ORDER BY updated_t_ns DESC, id LIMIT ?", (limit,))
        else:
            rows = self._rows(
                "SELECT record FROM alarms WHERE vehicle = ? ORDER BY updated_t_ns DESC, id LIMIT ?", (vehicle, limit)
            )
        return [dict(json.loads(r[0])) for r in rows]

    def alarm(self, alarm_id: str) -> dict[str, Any] | None:
        row = self._row("SELECT record FROM alarms WHERE id = ?", (alarm_id,))
        return None if row is None else dict(json.loads(row[0]))

    def alarm_events(self, alarm_id: str) -> list[dict[str, Any]]:
        rows = self._rows("SELECT event FROM alarm_events WHERE alarm_id = ? ORDER BY seq", (alarm_id,))
        return [dict(json.loads(r[0])) for r in rows]

    # ------------------------------------------------------------------ jobs

    def put_job(self, record: dict[str, Any]) -> None:
        with self.transaction() as db:
            db.execute(
                "INSERT INTO jobs (id, profile, created_t_ns, record) VALUES (?, ?, ?, ?) "
                "ON CONFLICT(id) DO UPDATE SET record = excluded.record",
                (record["id"], record["profile"], record["created_t_ns"], json.dumps(record)),
            )

    def job(self, job_id: str) -> dict[str, Any] | None:
        row = self._row("SELECT record FROM jobs WHERE id = ?", (job_id,))
        return None if row is None else dict(json.loads(row[0]))

    def prune_jobs(self, keep: int) -> None:
        """Delete all but the newest ``keep`` jobs."""
        with self.transaction() as db:
            db.execute(
                "DELETE FROM jobs WHERE id NOT IN (SELECT id FROM jobs ORDER BY created_t_ns DESC, id LIMIT ?)", (keep,)
            )

    def jobs(self, limit: int = 100) -> list[dict[str, Any]]:
        rows = self._rows("SELECT record FROM jobs ORDER BY created_t_ns DESC, id LIMIT ?", (limit,))
        return [dict(json.loads(r[0])) for r in rows]


class SqliteStorage(Storage):
    """The embedded default: one SQLite file (WAL journal, synchronous=FULL), its schema version in ``meta``."""

    transient_errors = (sqlite3.OperationalError, OSError)

    def __init__(self, path: Path, busy_timeout_s: float = 5.0) -> None:
        self.path = path
        self.location = str(path)
        try:
            if path.exists() and path.stat().st_size == 0:
                # SQLite would take it for a new database and the service would start with nothing: a truncated
                # copy or a failed restore. A database this service creates has its header before anything else.
                raise StorageError(
                    f"{path}: the database file is empty (0 bytes), so it holds none of the service's profiles, "
                    "gains, vehicles or alarms; restore it, or remove it to start with a new database"
                )
            path.parent.mkdir(parents=True, exist_ok=True)
            self._db = sqlite3.connect(path, timeout=busy_timeout_s, isolation_level=None, check_same_thread=False)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.execute("PRAGMA foreign_keys=ON")
            self._db.executescript(_SCHEMA)
        except (OSError, sqlite3.Error) as exc:
            raise StorageError(f"{path}: cannot open the database: {exc}") from exc
        found = self._db.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
        if found is None:
            self._db.execute("INSERT INTO meta VALUES ('schema_version', ?)", (str(SCHEMA_VERSION),))
        elif str(found[0]).strip() != str(SCHEMA_VERSION):
            self._db.close()
            raise StorageError(f"{path}: schema version {found[0]!r}, this service reads {SCHEMA_VERSION}")

    def close(self) -> None:
        self._db.close()

    @contextmanager
    def transaction(self) -> Iterator[Cursor]:
        """BEGIN IMMEDIATE ... COMMIT (ROLLBACK on error): one durable unit of work."""
        self._db.execute("BEGIN IMMEDIATE")
        try:
            yield self._db
            self._db.execute("COMMIT")
        except BaseException:
            # a failed COMMIT (disk full, busy) may leave the transaction open: end it, or every later BEGIN fails
            if self._db.in_transaction:
                with suppress(sqlite3.Error):
                    self._db.execute("ROLLBACK")
            raise

    def _rows(self, sql: str, params: Sequence[Any] = ()) -> list[tuple[Any, ...]]:
        return [tuple(r) for r in self._db.execute(sql, params).fetchall()]
