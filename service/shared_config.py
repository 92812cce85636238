"""One configuration for the replicas of a shared PostgreSQL database: profile changes announced with
LISTEN/NOTIFY, designs claimed with advisory locks.

* **Announcements.** ``PostgresStorage`` sends ``NOTIFY agv_fe_profiles, 'NAME'`` in the transaction that stores
  a profile or activates a gain version, so the notification goes out exactly when the change is committed. Each
  replica listens on a connection of its own and reloads the profile from the database: the same gain version
  becomes active everywhere (verified again by each replica, never designed again), thresholds apply everywhere.
  Every ``resync_s`` without a notification, and after a lost connection (notifications sent meanwhile are not
  kept for it), the replica compares every profile with the database.
* **Claims.** A design runs on the replica that holds the profile's design lock (a session advisory lock on the
  claims connection) until the job ends: replicas starting together on a database without gains design each
  profile once, a replica starting while another designs does not resume or repeat that design, and when the
  designer dies its lock goes with its session, so that another replica designs the profile (at its next resync).
"""

from __future__ import annotations

import logging
import threading
import zlib
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

import psycopg

from service.storage import StorageError
from service.storage_postgres import CONNECT_TIMEOUT_S, PROFILE_CHANNEL, redacted

log = logging.getLogger("agv_fe.service.config")

#: first key of the design locks (the second is a hash of the profile's name)
DESIGN_LOCKS = 0x41475603

#: called with the profile that changed, or None for "compare every profile"; runs on the service's loop
Changed = Callable[[str | None], "Future[None]"]


def design_key(profile: str) -> int:
    """The second key of a profile's design lock (a signed 32-bit number, as PostgreSQL's int4)."""
    return zlib.crc32(profile.encode()) - (1 << 31)


class SharedConfig:
    """This replica's side of the shared configuration: its design claims and its listener."""

    def __init__(self, url: str, on_change: Changed, resync_s: float = 2.0) -> None:
        self.url = url
        self.location = redacted(url)
        self.resync_s = resync_s
        self._on_change = on_change
        self._claims: psycopg.Connection[Any] | None = None
        self._held: set[str] = set()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._listen, name="config-listener", daemon=True)
        #: notifications received (for /metrics and tests)
        self.notifications = 0

    def _connect(self, name: str) -> psycopg.Connection[Any]:
        return psycopg.connect(self.url, autocommit=True, connect_timeout=CONNECT_TIMEOUT_S, application_name=name)

    def open(self) -> None:
        """The claims connection (used on the event loop, short queries only)."""
        try:
            self._claims = self._connect("agv-fe-claims")
        except psycopg.Error as exc:
            raise StorageError(f"{self.location}: cannot open the claims connection: {exc}") from exc

    def start_listening(self) -> None:
        self._thread.start()

    def claim(self, profile: str) -> bool:
        """Take the profile's design lock; False when another replica holds it (or the database is away)."""
        if profile in self._held:
            return True
        try:
            conn = self._claims if self._claims is not None and not self._claims.broken else self._reopen()
            row = conn.execute("SELECT pg_try_advisory_lock(%s, %s)", (DESIGN_LOCKS, design_key(profile))).fetchone()
        except psycopg.Error as exc:
            log.warning("config: cannot claim the design of profile %s: %s", profile, exc)
            return False
        if row and row[0]:
            self._held.add(profile)
            return True
        return False

    def release(self, profile: str) -> None:
        if profile not in self._held:
            return
        self._held.discard(profile)
        try:
            if self._claims is not None and not self._claims.broken:
                self._claims.execute("SELECT pg_advisory_unlock(%s, %s)", (DESIGN_LOCKS, design_key(profile)))
        except psycopg.Error as exc:  # the session is gone, and its locks with it
            log.warning("config: releasing the design claim of %s: %s", profile, exc)

    def _reopen(self) -> psycopg.Connection[Any]:
        """A new claims session: the claims of the old one went with it."""
        if self._claims is not None:
            self._claims.close()
        self._held.clear()
        self._claims = self._connect("agv-fe-claims")
        return self._claims

    def _listen(self) -> None:
        conn: psycopg.Connection[Any] | None = None
        while not self._stop.is_set():
            try:
                if conn is None or conn.broken:
                    conn = self._connect("agv-fe-listener")
                    conn.execute(f"LISTEN {PROFILE_CHANNEL}")
                    self._on_change(None)  # what changed while nobody listened
                for notify in conn.notifies(timeout=self.resync_s, stop_after=64):
                    self.notifications += 1
                    self._on_change(notify.payload)
                if not self._stop.is_set():
                    self._on_change(None)
            except psycopg.Error as exc:
                log.warning("config: the listener lost %s (%s); listening again", self.location, exc)
                if conn is not None:
                    conn.close()
                conn = None
                self._stop.wait(self.resync_s)
        if conn is not None:
            conn.close()

    def close(self) -> None:
        """Stop listening; ending the claims session releases every design claim."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(self.resync_s + CONNECT_TIMEOUT_S + 5)
        if self._claims is not None:
            self._claims.close()
            self._claims = None
