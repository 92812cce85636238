"""The storage on a PostgreSQL server, shared by the replicas of a scaled-out deployment (psycopg 3).

The queries are :class:`service.storage.Storage`'s, the same as SQLite's; this module supplies the
connection, the transaction and the schema. The schema is versioned by Alembic (``service/migrations``): every
start upgrades the database to the newest revision under a lock, so that replicas starting together migrate it
once, and a database migrated by a newer version than this one is refused with its revision named.

A connection that breaks (the server restarts, the network fails) is opened again at the next use; while it
cannot be, reads raise :class:`service.storage.StorageUnavailable` (the API answers 503) and writes raise
a transient error, which the storage writer retries with backoff.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from functools import cache
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit, urlunsplit

import psycopg

from service.storage import Cursor, Storage, StorageError, StorageUnavailable

log = logging.getLogger("agv_fe.service.storage")

MIGRATIONS_DIR = Path(__file__).with_name("migrations")
#: the advisory lock key held while the schema is migrated (any constant other locks of the service do not use)
MIGRATION_LOCK = 0x41_47_56_00
#: after a failed connection attempt, reads fail at once for this long instead of waiting for the server again
RECONNECT_INTERVAL_S = 1.0
#: libpq's connect_timeout is whole seconds, at least 2
CONNECT_TIMEOUT_S = 5
#: the NOTIFY channel of profile changes: the payload is the profile's name (service/shared_config.py)
PROFILE_CHANNEL = "agv_fe_profiles"


def redacted(url: str) -> str:
    """The URL without its password, for messages and logs."""
    parts = urlsplit(url)
    if parts.password is None:
        return url
    netloc = parts.netloc.replace(f":{parts.password}@", ":***@", 1)
    return urlunsplit(parts._replace(netloc=netloc))


@cache
def _placeholders(sql: str) -> str:
    """The interface's ``?`` placeholders as psycopg's ``%s`` (the queries hold no other ``?`` or ``%``)."""
    return sql.replace("?", "%s")


class _PgCursor:
    """A psycopg cursor that takes the interface's SQL."""

    def __init__(self, cursor: psycopg.Cursor[Any]) -> None:
        self._cursor = cursor

    def execute(self, sql: str, params: Sequence[Any] = (), /) -> Any:
        return self._cursor.execute(_placeholders(sql), params)

    def executemany(self, sql: str, params: Iterable[Sequence[Any]], /) -> Any:
        return self._cursor.executemany(_placeholders(sql), params)


class PostgresStorage(Storage):
    """The service's database on a PostgreSQL server: one connection, used by one thread."""

    transient_errors = (psycopg.OperationalError, StorageUnavailable, OSError)

    def __init__(self, url: str, busy_timeout_s: float = 5.0, migrate_schema: bool = True) -> None:
        if not url.startswith(("postgresql://", "postgres://")):
            raise StorageError(f"database URL {redacted(url)!r}: expected postgresql://USER@HOST:PORT/DATABASE")
        self.url = url
        self.location = redacted(url)
        self._lock_timeout_ms = max(1, round(busy_timeout_s * 1000))
        self._conn: psycopg.Connection[Any] | None = None
        self._retry_at = 0.0
        self._last_failure = ""
        try:
            self._conn = self._connect()
        except psycopg.Error as exc:
            raise StorageError(f"{self.location}: cannot open the database: {exc}") from exc
        if migrate_schema:
            migrate(url)

    def _connect(self) -> psycopg.Connection[Any]:
        return psycopg.connect(
            self.url,
            autocommit=True,
            connect_timeout=CONNECT_TIMEOUT_S,
            # a write waits this long for another replica's row lock, then fails and is retried (busy_timeout_s)
            options=f"-c lock_timeout={self._lock_timeout_ms}",
            application_name="agv-fe",
        )

    def _connection(self) -> psycopg.Connection[Any]:
        """The open connection, opened again if it broke; StorageUnavailable while the server cannot be reached."""
        conn = self._conn
        if conn is not None and not conn.closed and not conn.broken:
            return conn
        if conn is not None:
            conn.close()
            self._conn = None
        if time.monotonic() < self._retry_at:
            raise StorageUnavailable(f"{self.location}: the database cannot be reached: {self._last_failure}")
        try:
            self._conn = self._connect()
        except psycopg.OperationalError as exc:
            self._retry_at = time.monotonic() + RECONNECT_INTERVAL_S
            self._last_failure = str(exc).strip()
            raise StorageUnavailable(f"{self.location}: the database cannot be reached: {self._last_failure}") from exc
        log.warning("storage: connected to %s again", self.location)
        return self._conn

    def close(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None

    @contextmanager
    def transaction(self) -> Iterator[Cursor]:
        """BEGIN ... COMMIT (ROLLBACK on error), on a connection opened again if it broke."""
        conn = self._connection()
        with conn.transaction(), conn.cursor() as cursor:
            yield _PgCursor(cursor)

    def _profile_changed(self, db: Cursor, name: str) -> None:
        """Tell the other replicas, when the transaction commits (NOTIFY is transactional)."""
        db.execute("SELECT pg_notify(?, ?)", (PROFILE_CHANNEL, name))

    def _rows(self, sql: str, params: Sequence[Any] = ()) -> list[tuple[Any, ...]]:
        conn = self._connection()
        try:
            with conn.cursor() as cursor:
                cursor.execute(_placeholders(sql), params)
                return [tuple(r) for r in cursor.fetchall()]
        except psycopg.OperationalError as exc:
            raise StorageUnavailable(f"{self.location}: the database cannot be reached: {str(exc).strip()}") from exc


def migrate(url: str) -> str:
    """Upgrade the database's schema to the newest Alembic revision; returns it.

    Replicas starting together take turns on an advisory lock, so each revision runs once. A database at a
    revision this version does not know (a newer version migrated it) is a StorageError naming the revision.
    """
    from alembic import command
    from alembic.config import Config
    from alembic.runtime.migration import MigrationContext
    from alembic.script import ScriptDirectory
    from alembic.util.exc import CommandError
    from sqlalchemy import create_engine, pool, text
    from sqlalchemy.exc import SQLAlchemyError

    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    head = ScriptDirectory.from_config(config).get_current_head()
    current: str | None = None
    engine = create_engine(
        url.replace("postgres://", "postgresql://", 1).replace("postgresql://", "postgresql+psycopg://", 1),
        poolclass=pool.NullPool,
    )
    try:
        with engine.connect() as connection:
            connection.execute(text("SELECT pg_advisory_lock(:key)"), {"key": MIGRATION_LOCK})
            try:
                current = MigrationContext.configure(connection).get_current_revision()
                connection.commit()
                if current != head:
                    config.attributes["connection"] = connection
                    command.upgrade(config, "head")
                    connection.commit()
                    log.info("storage: schema of %s migrated from revision %s to %s", redacted(url), current, head)
            finally:
                connection.execute(text("SELECT pg_advisory_unlock(:key)"), {"key": MIGRATION_LOCK})
                connection.commit()
    except CommandError as exc:
        raise StorageError(
            f"{redacted(url)}: the schema is at revision {current!r}, which this version does not know (its newest "
            f"is {head!r}): a newer version of the service migrated it ({exc})"
        ) from exc
    except (SQLAlchemyError, psycopg.Error) as exc:
        raise StorageError(f"{redacted(url)}: cannot migrate the schema: {exc}") from exc
    finally:
        engine.dispose()
    return str(head)
