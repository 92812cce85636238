"""The buckets a replica serves, and their hand-over between replicas of a shared database.

A replica serves a share of the 16 key-expression buckets: all of them, a static shard (``--shard I/N``), or,
with bucket leases (service/bucket_leases.py), those whose locks it holds in the shared PostgreSQL database,
which change while it runs. :class:`BucketHandover` keeps that set and carries out the lease thread's decisions
on the service's event loop, between two ingest ticks:

* a bucket gained (its lock is held now): its vehicles' registry and latched alarms are read from the shared
  database and adopted by the fleet engine, then its measurements and liveliness are subscribed to; each
  observer starts at the vehicle's next measurement;
* a bucket lost: its subscriptions stop, its vehicles leave the engine and the writes queued so far are stored,
  and only then does the lease thread release its lock, so that no bucket ever has two owners.

Each change is logged, counted by the leases (``/metrics``) and announced on Zenoh
(:func:`agv_protocol.wire.ownership_key`). With a shared database a static shard holds its buckets as shared
locks, and either kind of replica watches the lock table for buckets without an owner
(:class:`~service.ownership.OwnershipWatch`, fed by the lock thread started here).
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import TYPE_CHECKING, Protocol

from agv_protocol.wire import OwnershipChange, all_buckets, bucket_of, shard_buckets
from service.databases import open_storage
from service.fleet import AlarmRecord, FleetEngine
from service.ownership import OwnershipWatch
from service.settings import Settings
from service.storage import Storage
from service.storage_writer import StorageWriter

if TYPE_CHECKING:  # psycopg is imported only by a replica that uses PostgreSQL
    from service.bucket_leases import BucketLeases, LeaseState, StaticBucketLocks

log = logging.getLogger("agv_fe.service")


class HandoverError(Exception):
    """A hand-over asked of a replica whose bucket hand-over is not started, or closed."""


class BucketTransport(Protocol):
    """The Zenoh transport as the hand-over uses it (service.transport.Transport)."""

    #: the buckets subscribed to now
    buckets: list[str]

    def add_buckets(self, buckets: list[str]) -> None: ...

    def remove_buckets(self, buckets: list[str]) -> None: ...

    def publish_ownership(self, payload: bytes) -> None: ...


class HandoverDatabase(Protocol):
    """The service's database as the hand-over uses it: its connection for reads (on the event loop), and the
    wait until the writes queued so far are stored."""

    @property
    def writer(self) -> StorageWriter | None: ...

    @property
    def db(self) -> Storage: ...

    async def stored(self, what: str) -> None: ...


def _configured_buckets(settings: Settings) -> list[str]:
    """The buckets served from the start: static (``--shard``), or none with bucket leases (before their first
    round)."""
    if settings.bucket_leases:
        return []
    if settings.shard.replicas == 1:
        return all_buckets()
    return shard_buckets(settings.shard.index, settings.shard.replicas)


class BucketHandover:
    """The buckets one replica serves; with a shared database, the locks that say so and the hand-over of buckets.

    Parameters
    ----------
    settings : Settings
        the service's settings (shard, bucket_leases, database_url, storage.busy_timeout_s)
    replica_id : str
        this replica's name, in the logs and the announcements
    engine : FleetEngine
        the fleet that adopts the vehicles of a bucket gained and forgets those of a bucket lost
    """

    def __init__(self, settings: Settings, replica_id: str, engine: FleetEngine) -> None:
        self._settings = settings
        self.replica_id = replica_id
        self.engine = engine
        #: the buckets this replica serves now: static (--shard), or those its leases hold (none before start)
        self.buckets: list[str] = _configured_buckets(settings)
        self.leases: BucketLeases | None = None
        #: a static shard on a shared database: its buckets' locks, for the other replicas to see them owned
        self.static_locks: StaticBucketLocks | None = None
        #: with a shared database: the buckets without an owner, their vehicles and (as warden) their alarms
        self.ownership = OwnershipWatch(engine, settings.shard.unserved_after_s)
        self._transport: BucketTransport | None = None
        self._database: HandoverDatabase | None = None

    # ------------------------------------------------------------------ life cycle

    async def start(self, transport: BucketTransport, database: HandoverDatabase) -> None:
        """With a shared database: take buckets by leases (or hold a static shard's locks) and watch the lock table.

        Called on the service's event loop once ``transport`` is open and the state loaded; the hand-overs run on
        that loop."""
        self._transport, self._database = transport, database
        settings = self._settings
        if settings.bucket_leases and settings.database_url is not None:
            from service.bucket_leases import BucketLeases

            loop = asyncio.get_running_loop()
            self.leases = BucketLeases(
                settings.database_url,
                settings.shard.lease_interval_s,
                on_gain=lambda buckets: asyncio.run_coroutine_threadsafe(self.gain(buckets), loop),
                on_lose=lambda buckets: asyncio.run_coroutine_threadsafe(self.lose(buckets), loop),
            )
            await asyncio.to_thread(self.leases.start)
        await self._watch_ownership()

    async def halt(self) -> None:
        """No more buckets taken or given; the locks stay until the writes are stored (:meth:`close`)."""
        if self.leases is not None:
            await asyncio.to_thread(self.leases.halt)

    def close(self) -> None:
        """End the lock sessions: every bucket lock is released for the other replicas."""
        if self.leases is not None:
            self.leases.close()
            self.leases = None
        if self.static_locks is not None:
            self.static_locks.close()
            self.static_locks = None
        self.ownership.close()
        self._transport, self._database = None, None

    async def _watch_ownership(self) -> None:
        """With a shared database: a static shard holds its buckets' locks, and every replica watches the lock
        table for buckets without an owner (service/ownership.py)."""
        settings = self._settings
        url = settings.database_url
        if url is None:
            return
        if self.leases is None:
            from service.bucket_leases import StaticBucketLocks

            self.static_locks = StaticBucketLocks(url, self.buckets, settings.shard.lease_interval_s)
            await asyncio.to_thread(self.static_locks.start)
        locks = self.leases or self.static_locks
        if locks is not None:
            storage = await asyncio.to_thread(
                open_storage, url, settings.database_path, settings.storage.busy_timeout_s
            )
            self.ownership.attach(locks.snapshot, storage)

    # ------------------------------------------------------------------ what /health, /metrics and the logs show

    def lease_state(self) -> LeaseState | None:
        """The leases' view (owned buckets, live replicas, hand-overs), None with a static shard."""
        return None if self.leases is None else self.leases.snapshot()

    def serving(self) -> str:
        """What this replica serves, for the start-up log."""
        return "by leases in the shared database" if self.leases is not None else ",".join(self.buckets)

    # ------------------------------------------------------------------ the hand-over

    async def gain(self, buckets: list[str]) -> None:
        """Serve ``buckets``, whose locks this replica holds now: their vehicles' registry and latched alarms from
        the shared database, then their subscriptions; each observer starts at the vehicle's next measurement."""
        database, transport = self._require()
        wanted = set(buckets)
        rows = [row for row in database.db.vehicles() if bucket_of(row[0]) in wanted]
        latched = [AlarmRecord.from_dict(r) for r in database.db.latched_alarms() if bucket_of(r["vehicle"]) in wanted]
        adopted = self.engine.adopt(rows, latched)
        loads = database.db.payloads()
        for problem in self.engine.load_payloads({v: loads[v] for v in adopted if v in loads}):
            log.warning(problem)
        transport.add_buckets(buckets)
        self.buckets = list(transport.buckets)
        self._announce(buckets, [], len(adopted), len(latched))

    async def lose(self, buckets: list[str]) -> None:
        """Stop serving ``buckets`` and store what is queued, before their locks go to another replica."""
        gone = set(buckets)
        if self._transport is not None:
            self._transport.remove_buckets(buckets)
            self.buckets = list(self._transport.buckets)
        ids = [v for v in [*self.engine.vehicles, *self.engine.held] if bucket_of(v) in gone]
        self.engine.forget(ids)
        if self._database is not None and self._database.writer is not None:
            await self._database.stored(f"the hand-over of buckets {', '.join(buckets)}")
        self._announce([], buckets, len(ids), 0)

    def _require(self) -> tuple[HandoverDatabase, BucketTransport]:
        if self._database is None or self._transport is None:
            raise HandoverError("the bucket hand-over is not started: the transport is not open")
        return self._database, self._transport

    def _announce(self, gained: list[str], lost: list[str], vehicles: int, alarms: int) -> None:
        """An ownership change: logged, counted (/metrics) and published on Zenoh (agv_protocol.wire.ownership_key)."""
        verb, which = ("took", gained) if gained else ("handed over", lost)
        log.warning(
            "replica %s %s buckets %s (%d vehicles, %d latched alarms); it serves %s now",
            self.replica_id,
            verb,
            ",".join(which),
            vehicles,
            alarms,
            ",".join(self.buckets) or "no bucket",
        )
        change = OwnershipChange(
            replica=self.replica_id,
            gained=gained,
            lost=lost,
            buckets=self.buckets,
            vehicles=vehicles,
            t_ns=time.time_ns(),
        )
        if self._transport is not None:
            try:
                self._transport.publish_ownership(change.encode())
            except Exception:  # the change stands; only its announcement failed
                log.exception("the ownership change could not be published on Zenoh")
