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
import zlib
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

import psycopg

from service.pg_session import SessionThread
from service.storage_postgres import CONNECT_TIMEOUT_S, PROFILE_CHANNEL

log = logging.getLogger("agv_fe.service.config")

#: first key of the design locks (the second is a hash of the profile's name)
DESIGN_LOCKS = 0x41475603

#: called with the profile that changed, or None for "compare every profile"; runs on the service's loop
Changed = Callable[[str | None], "Future[None]"]


def design_key(profile: str) -> int:
    """The second key of a profile's design lock (a signed 32-bit number, as PostgreSQL's int4)."""
    return zlib.crc32(profile.encode()) - (1 << 31)


class SharedConfig(SessionThread):
    """This replica's side of the shared configuration: its design claims (on its session, used on the event loop,
    short queries only) and its listener (a thread on a session of its own)."""

    def __init__(self, url: str, on_change: Changed, resync_s: float = 2.0) -> None:
        super().__init__(
            url,
            purpose="claims",
            application_name="agv-fe-claims",
            thread_name="config-listener",
            join_timeout_s=resync_s + CONNECT_TIMEOUT_S + 5,
        )
        self.resync_s = resync_s
        self._on_change = on_change
        self._held: set[str] = set()
        #: notifications received (for /metrics and tests)
        self.notifications = 0

    def start_listening(self) -> None:
        """The listener thread (the claims session is opened before, by :meth:`open`)."""
        self._thread.start()

    def claim(self, profile: str) -> bool:
        """Take the profile's design lock; False when another replica holds it (or the database is away)."""
        if profile in self._held:
            return True
        try:
            conn = self._live_session() or self._reopen()
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
            if (conn := self._live_session()) is not None:
                conn.execute("SELECT pg_advisory_unlock(%s, %s)", (DESIGN_LOCKS, design_key(profile)))
        except psycopg.Error as exc:  # the session is gone, and its locks with it
            log.warning("config: releasing the design claim of %s: %s", profile, exc)

    def _reopen(self) -> psycopg.Connection[Any]:
        """A new claims session: the claims of the old one went with it."""
        self._end_session()
        self._held.clear()
        self._conn = self._new_session()
        return self._conn

    def _run(self) -> None:
        """Listen for the profile changes; compare every profile after each ``resync_s`` without one."""
        conn: psycopg.Connection[Any] | None = None
        while not self._stop.is_set():
            try:
                if conn is None or conn.broken:
                    conn = self._new_session("agv-fe-listener")
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
