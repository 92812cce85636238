"""A thread on a PostgreSQL session of its own: the lifecycle that the bucket leases, a static shard's bucket
locks (service/bucket_leases.py) and the shared configuration (service/shared_config.py) have in common.

Each keeps a session beside the storage's, because its advisory locks live exactly as long as that session:
ending it releases them all at once. :class:`SessionThread` holds what they do alike: the session (autocommit,
the connect timeout, an application name that tells the sessions apart in ``pg_stat_activity``), opening it with
a database error translated into :class:`StorageError` that names the connection, the thread and its stop event,
and the order of closing: stop the thread, wait for it (at most ``join_timeout_s``), then end the session.
What a session is for, what the thread does and how it recovers stay with each subclass.
"""

from __future__ import annotations

import threading
from typing import Any

import psycopg

from service.storage import StorageError
from service.storage_postgres import CONNECT_TIMEOUT_S, redacted


class SessionThread:
    """A session of its own (``_conn``, opened by :meth:`open`) and a thread (``_run``) that ends once ``_stop`` is
    set; ``purpose`` names the connection in errors ("lease" -> "cannot open the lease connection")."""

    def __init__(
        self, url: str, *, purpose: str, application_name: str, thread_name: str, join_timeout_s: float
    ) -> None:
        self.url = url
        self.location = redacted(url)
        self._purpose = purpose
        self._application_name = application_name
        self._join_timeout_s = join_timeout_s
        self._conn: psycopg.Connection[Any] | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=thread_name, daemon=True)

    def open(self) -> None:
        """Run :meth:`_begin` (open the session and do what must be done before the service goes on); a database
        error becomes :class:`StorageError`."""
        try:
            self._begin()
        except psycopg.Error as exc:
            raise StorageError(f"{self.location}: cannot open the {self._purpose} connection: {exc}") from exc

    def start(self) -> None:
        """:meth:`open`, then the thread."""
        self.open()
        self._thread.start()

    def halt(self) -> None:
        """Stop the thread and wait for it; the session, and its locks, stay."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(self._join_timeout_s)

    def close(self) -> None:
        """Halt, then end the session: PostgreSQL releases every lock it held at once."""
        self.halt()
        self._end_session()

    def _begin(self) -> None:
        self._conn = self._new_session()

    def _run(self) -> None:
        raise NotImplementedError

    def _new_session(self, application_name: str | None = None) -> psycopg.Connection[Any]:
        """A new autocommit session, named ``application_name`` (by default this object's)."""
        return psycopg.connect(
            self.url,
            autocommit=True,
            connect_timeout=CONNECT_TIMEOUT_S,
            application_name=application_name or self._application_name,
        )

    def _live_session(self) -> psycopg.Connection[Any] | None:
        """The session if it is open and not broken; None: it must be opened again."""
        conn = self._conn
        return conn if conn is not None and not conn.closed and not conn.broken else None

    def _end_session(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None
