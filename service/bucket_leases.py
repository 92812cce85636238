"""Bucket ownership by leases in the shared PostgreSQL database: session advisory locks, one per bucket.

Replicas started without a static shard share the key-expression buckets among the live ones. Each replica
holds, on a connection of its own, one *member* lock (keyed by its backend pid, so two replicas never share
one) and one lock per bucket it serves. PostgreSQL releases a session's locks when the session ends, so when a
replica dies its buckets become free as soon as the server sees its connection close, and the survivors take
them at their next round.

Every ``lease_interval_s`` a replica counts the live members (``pg_locks``), computes its fair share of the
buckets (16 // n, one more for the first 16 % n by pid), then

* gives up what it holds beyond its share: the service stops serving the bucket and flushes its writes
  first (``on_lose`` completes), and only then is the lock released, so no bucket ever has two owners;
* takes free buckets up to its share with ``pg_try_advisory_lock``: the lock is held before the service is
  told to serve it (``on_gain``).

When the lease connection fails (the database is unreachable) the replica keeps serving what it holds, since
no other replica can take a lock meanwhile, and tries again each interval; once connected it locks its buckets
again and gives up at once any it cannot lock (another replica took it first).

The lock table is also the fleet's view of ownership: a bucket whose lock nobody holds has no owner, and its
vehicles nobody estimates. Each round reads which buckets are unowned (:attr:`LeaseState.unowned`), and tries
the *warden* lock, held by one replica of the database at a time: that replica raises the alarms of the
unowned buckets' vehicles (service/ownership.py). A static shard (``--shard I/N``) on a shared database holds
its buckets as shared locks (:class:`StaticBucketLocks`), so that its death shows in the same table.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass, field, replace
from typing import Any

import psycopg

from agv_protocol.wire import all_buckets
from service.pg_session import SessionThread
from service.storage_postgres import CONNECT_TIMEOUT_S

log = logging.getLogger("agv_fe.service.leases")

#: first key of the advisory locks of buckets and of members (the second is the bucket's index or the pid)
BUCKET_LOCKS = 0x41475601
MEMBER_LOCKS = 0x41475602
#: the warden's lock (second key 0): the replica holding it raises the alarms of buckets without an owner
WARDEN_LOCK = 0x41475603
#: how long a replica waits for the service to stop serving a bucket (and flush its writes) before releasing it
HANDOVER_TIMEOUT_S = 30.0

#: called on the service's side with the buckets gained or lost; the future completes once it is done
Handover = Callable[[list[str]], "Future[None]"]

_LOCKS_HELD = """
SELECT objid::bigint, pid FROM pg_locks
WHERE locktype = 'advisory' AND classid = %s AND objsubid = 2 AND granted
  AND database = (SELECT oid FROM pg_database WHERE datname = current_database())
"""


def unowned_buckets(conn: psycopg.Connection[Any], index: dict[str, int]) -> list[str]:
    """The buckets of ``index`` (name -> lock key) whose lock no session holds, exclusive or shared."""
    held = {int(objid) for objid, _ in conn.execute(_LOCKS_HELD, (BUCKET_LOCKS,)).fetchall()}
    return [bucket for bucket, key in index.items() if key not in held]


def try_warden(conn: psycopg.Connection[Any]) -> bool:
    """Take the warden's lock if no other session holds it (call once per session: the lock is re-entrant)."""
    row = conn.execute("SELECT pg_try_advisory_lock(%s, 0)", (WARDEN_LOCK,)).fetchone()
    return bool(row and row[0])


def fair_share(rank: int, members: int, n_buckets: int) -> int:
    """Buckets the member of rank ``rank`` (0-based, of ``members``) should hold: balanced within one."""
    base, extra = divmod(n_buckets, max(1, members))
    return base + (1 if rank < extra else 0)


@dataclass
class LeaseState:
    """What /metrics and the status endpoint show about the leases."""

    owned: list[str] = field(default_factory=list)
    members: int = 0
    connected: bool = False
    gained: int = 0
    lost: int = 0
    #: rounds completed (taking and giving buckets); 0: the replica does not know its share yet
    rounds: int = 0
    #: why the lease connection failed, while it does
    problem: str | None = None
    #: buckets no replica holds, as the latest round saw the lock table; None: not known (no round, no connection)
    unowned: list[str] | None = None
    #: this replica holds the warden's lock: it raises the alarms of the unowned buckets' vehicles
    warden: bool = False


class _LockThread(SessionThread):
    """Bucket locks held on a session of its own by a thread that runs a round every ``interval_s``: a failed
    session is recorded in the state (and logged once) and opened again at the next round; the state is read and
    written under a lock. Subclasses say what a round does (``_round``) and which buckets they hold."""

    #: True: :meth:`start` runs the first round itself, and the thread waits an interval before its first one
    round_at_start = False

    def __init__(
        self,
        url: str,
        interval_s: float,
        index: dict[str, int],
        *,
        purpose: str,
        application_name: str,
        thread_name: str,
        join_timeout_s: float,
    ) -> None:
        super().__init__(
            url,
            purpose=purpose,
            application_name=application_name,
            thread_name=thread_name,
            join_timeout_s=join_timeout_s,
        )
        self.interval_s = interval_s
        #: bucket name -> the second key of its lock
        self._index = index
        self._lock = threading.Lock()
        self.state = LeaseState()

    # ------------------------------------------------------------------ what the subclasses say

    def _connect(self) -> None:
        """Open the session (the first one, at start)."""
        raise NotImplementedError

    def _reconnect(self) -> None:
        """Open a new session after a failed one (in the thread)."""
        self._connect()

    def _round(self) -> None:
        raise NotImplementedError

    def _holding(self) -> set[str]:
        """The buckets shown as owned."""
        raise NotImplementedError

    def _log_failure(self, exc: psycopg.Error, problem: str) -> None:
        raise NotImplementedError

    # ------------------------------------------------------------------ the lifecycle

    def _begin(self) -> None:
        self._connect()
        if self.round_at_start:
            self._round()

    def _run(self) -> None:
        if not self.round_at_start and not self._stop.is_set():
            self._attempt()
        while not self._stop.wait(self.interval_s):
            self._attempt()

    def _attempt(self) -> None:
        try:
            if self._live_session() is None:
                self._reconnect()
            self._round()
        except psycopg.Error as exc:
            self._connection_failed(exc)

    def _connection_failed(self, exc: psycopg.Error) -> None:
        problem = f"{type(exc).__name__}: {str(exc).strip()}"
        if self.state.problem is None:
            self._log_failure(exc, problem)
        self._set(connected=False, problem=problem, unowned=None, warden=False)
        self._end_session()

    def _require(self) -> psycopg.Connection[Any]:
        if self._conn is None:
            raise psycopg.OperationalError(f"the {self._purpose} connection is closed")
        return self._conn

    def _set(self, **changes: Any) -> None:
        with self._lock:
            for name, value in changes.items():
                setattr(self.state, name, value)
            self.state.owned = sorted(self._holding(), key=self._index.__getitem__)

    def snapshot(self) -> LeaseState:
        with self._lock:
            s = self.state
            return replace(s, owned=list(s.owned), unowned=None if s.unowned is None else list(s.unowned))


class BucketLeases(_LockThread):
    """This replica's share of the buckets, held as session advisory locks on a connection of its own."""

    def __init__(
        self, url: str, interval_s: float, on_gain: Handover, on_lose: Handover, buckets: list[str] | None = None
    ) -> None:
        self.buckets = buckets if buckets is not None else all_buckets()
        super().__init__(
            url,
            interval_s,
            {b: int(b[1:], 16) for b in self.buckets},
            purpose="lease",
            application_name="agv-fe-leases",
            thread_name="bucket-leases",
            join_timeout_s=HANDOVER_TIMEOUT_S + interval_s + 10,
        )
        self._on_gain, self._on_lose = on_gain, on_lose
        self._owned: set[str] = set()
        #: buckets locked whose serving failed: tried again each round
        self._unserved: set[str] = set()

    # ------------------------------------------------------------------ the lease thread

    def _connect(self) -> None:
        conn = self._new_session()
        conn.execute("SELECT pg_advisory_lock(%s, pg_backend_pid())", (MEMBER_LOCKS,))
        self._conn = conn
        self._set(connected=True, problem=None, warden=False)  # a new session holds no warden's lock yet

    def _reconnect(self) -> None:
        """A new session: lock the buckets served until now again; give up at once those another replica took."""
        self._end_session()
        self._connect()
        conn = self._require()
        kept = {b for b in sorted(self._owned) if self._try_lock(conn, b)}
        taken = sorted(self._owned - kept)
        if taken:
            log.warning("leases: buckets %s were taken by another replica while the database was away", taken)
            self._give_up(taken, wait=False)
        log.warning("leases: connected to %s again, serving %d buckets", self.location, len(self._owned))

    def _log_failure(self, exc: psycopg.Error, problem: str) -> None:
        log.error(
            "leases: the lease connection to %s failed (%s); serving the %d buckets held until it is back",
            self.location,
            problem,
            len(self._owned),
        )

    def _holding(self) -> set[str]:
        return self._owned

    def _round(self) -> None:
        conn = self._require()
        retry = sorted(self._unserved & self._owned, key=self._index.__getitem__)
        members = sorted(pid for _, pid in conn.execute(_LOCKS_HELD, (MEMBER_LOCKS,)).fetchall())
        me = conn.execute("SELECT pg_backend_pid()").fetchone()
        rank = members.index(me[0]) if me is not None and me[0] in members else len(members)
        share = fair_share(rank, len(members), len(self.buckets))
        self._set(members=len(members))
        if len(self._owned) > share:
            # the highest buckets go, so that shares settle the same way on every replica
            extra = sorted(self._owned, key=self._index.__getitem__)[share:]
            self._give_up(extra, wait=True)
        elif len(self._owned) < share:
            held = {int(objid) for objid, _ in conn.execute(_LOCKS_HELD, (BUCKET_LOCKS,)).fetchall()}
            free = [b for b in self.buckets if self._index[b] not in held and b not in self._owned]
            gained = []
            for bucket in free[: share - len(self._owned)]:
                if self._try_lock(conn, bucket):
                    gained.append(bucket)
            if gained:
                self._owned.update(gained)
                self._set(gained=self.state.gained + len(gained))
                log.info("leases: gained buckets %s (%d of %d live replicas)", gained, rank + 1, len(members))
                self._serve(gained)
        self._serve([b for b in retry if b in self._owned])
        self._observe(conn)
        self._set(connected=True, problem=None, rounds=self.state.rounds + 1)

    def _observe(self, conn: psycopg.Connection[Any]) -> None:
        """The fleet's ownership after this round: the buckets nobody holds, and whether this replica is warden."""
        warden = self.state.warden or try_warden(conn)
        self._set(unowned=unowned_buckets(conn, self._index), warden=warden)

    def _serve(self, buckets: list[str]) -> None:
        """Have the service serve buckets whose locks this replica holds; those it could not (the database failed
        while it read their vehicles) are tried again next round."""
        if not buckets:
            return
        if self._wait(self._on_gain(buckets), "serving", buckets):
            self._unserved.difference_update(buckets)
        else:
            self._unserved.update(buckets)

    def _try_lock(self, conn: psycopg.Connection[Any], bucket: str) -> bool:
        row = conn.execute("SELECT pg_try_advisory_lock(%s, %s)", (BUCKET_LOCKS, self._index[bucket])).fetchone()
        return bool(row and row[0])

    def _give_up(self, buckets: list[str], wait: bool) -> None:
        """Stop serving ``buckets`` (their writes flushed), then release their locks; ``wait=False``: the locks
        are gone already (a new session), only the service has to stop."""
        done = self._on_lose(buckets)
        if wait and not self._wait(done, "giving up", buckets):
            return  # still served: keep the locks, and try again next round
        if wait:
            conn = self._require()
            for bucket in buckets:
                conn.execute("SELECT pg_advisory_unlock(%s, %s)", (BUCKET_LOCKS, self._index[bucket]))
        self._owned.difference_update(buckets)
        self._unserved.difference_update(buckets)
        self._set(lost=self.state.lost + len(buckets))
        log.info("leases: gave up buckets %s", buckets)

    def _wait(self, done: Future[None], what: str, buckets: list[str]) -> bool:
        try:
            done.result(HANDOVER_TIMEOUT_S)
        except FutureTimeout:
            log.error("leases: %s buckets %s took over %g s", what, buckets, HANDOVER_TIMEOUT_S)
            return False
        except Exception:
            log.exception("leases: %s buckets %s failed", what, buckets)
            return False
        return True


class StaticBucketLocks(_LockThread):
    """A static shard's buckets (``--shard I/N``) on a shared database: shared advisory locks, and the fleet's view.

    The replica serves its buckets whatever happens here; the locks only say so in the lock table, so that every
    replica of the database sees a static replica's buckets lose their owner when its session ends (it died) and
    gain one when it is back. Shared locks: two static replicas configured with overlapping shards both hold
    theirs, while a replica with leases cannot take such a bucket. Every ``interval_s`` the thread locks what it
    does not hold yet (after a new session, or a bucket a replica with leases held), reads the unowned buckets and
    tries the warden's lock, as :class:`BucketLeases` does each round.
    """

    round_at_start = True

    def __init__(self, url: str, buckets: list[str], interval_s: float) -> None:
        super().__init__(
            url,
            interval_s,
            {b: int(b[1:], 16) for b in all_buckets()},
            purpose="bucket-lock",
            application_name="agv-fe-bucket-locks",
            thread_name="bucket-locks",
            join_timeout_s=interval_s + CONNECT_TIMEOUT_S + 10,
        )
        self.buckets = list(buckets)
        self._held: set[str] = set()
        #: buckets of this shard a replica with leases held exclusively (logged once)
        self._contested: set[str] = set()

    def _connect(self) -> None:
        self._end_session()
        self._held = set()
        self._conn = self._new_session()
        self._set(warden=False)

    def _log_failure(self, exc: psycopg.Error, problem: str) -> None:
        log.error("bucket locks: the connection to %s failed: %s", self.location, exc)

    def _holding(self) -> set[str]:
        return self._held

    def _round(self) -> None:
        conn = self._require()
        for bucket in [b for b in self.buckets if b not in self._held]:
            row = conn.execute("SELECT pg_try_advisory_lock_shared(%s, %s)", (BUCKET_LOCKS, self._index[bucket]))
            if (got := row.fetchone()) and got[0]:
                self._held.add(bucket)
            elif bucket not in self._contested:
                self._contested.add(bucket)
                log.warning(
                    "bucket locks: a replica with leases holds %s, which this static replica serves too", bucket
                )
        warden = self.state.warden or try_warden(conn)
        unowned = unowned_buckets(conn, self._index)
        self._set(connected=True, problem=None, rounds=self.state.rounds + 1, unowned=unowned, warden=warden)
