"""Vehicles whose bucket has no owner: listed by every replica of a shared database, alarmed by one.

A key-expression bucket that no replica serves (its replica died, a hand-over is under way, a static shard is
missing) leaves its vehicles without estimates and without alarms: the replica that would raise their STALE
alarms is the one that is gone. The database's lock table knows which buckets have an owner
(service/bucket_leases.py: a replica with leases holds one advisory lock per bucket it serves, a static shard
holds shared locks on its buckets, and PostgreSQL releases a session's locks when it ends), and its vehicle
registry knows which vehicles a bucket holds. :class:`OwnershipWatch` joins the two, from the housekeeping loop:

* every replica reads the unowned buckets from its lock thread's latest round (no I/O on the event loop), and
  the registry's vehicles of those buckets when that set changes (off the loop): ``GET /vehicles`` lists them
  with ``served: false`` and level STALE, ``/metrics`` counts them;
* the replica holding the warden's lock (one per database) raises an alarm of kind ``unserved`` (level STALE)
  for each of them once their bucket has had no owner for ``shard.unserved_after_s``, stored and published as
  any alarm, and clears it when the bucket has an owner again. A new warden (the old one died) takes up the
  raised ones from the database. The replica that serves the vehicle again loads the alarm as cleared
  (:meth:`service.fleet.AlarmBook.load`): it is latched there until acknowledged, as a cleared STALE alarm is.

Nothing here runs per sample: one look at the lock thread's state per housekeeping round, and database reads
only when the ownership changes. The housekeeping loop never waits for them: a read runs in a thread, and a later
round takes its result, so a database that hangs delays this module's lists and alarms, not the STALE checks of
the replica's own vehicles.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from agv_protocol.wire import bucket_of
from service.fleet import AlarmChange, AlarmRecord, FleetEngine, FleetEvent
from service.storage import Storage, StorageError

if TYPE_CHECKING:
    from service.bucket_leases import LeaseState

log = logging.getLogger("agv_fe.service.ownership")

#: the lock thread's latest view of the lock table (None: no shared database)
OwnershipView = Callable[[], "LeaseState | None"]


@dataclass(frozen=True)
class _Read:
    """What one read of the database found, for the unowned buckets ``unowned``; None where it was not read or
    failed."""

    unowned: frozenset[str]
    vehicles: list[tuple[str, str, int]] | None
    #: the ``unserved`` alarms still raised (read for a replica that became the warden)
    raised: list[AlarmRecord] | None


@dataclass(frozen=True)
class UnservedVehicle:
    """A registered vehicle of a bucket no replica holds."""

    id: str
    profile: str
    bucket: str


class OwnershipWatch:
    """The fleet's unowned buckets and their vehicles, as the lock table and the registry have them; the warden's
    ``unserved`` alarms. Without a shared database (:meth:`attach` not called) it knows nothing and does nothing."""

    def __init__(
        self,
        engine: FleetEngine,
        unserved_after_s: float,
        clock_ns: Callable[[], int] = time.time_ns,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        self.engine = engine
        self.unserved_after_s = unserved_after_s
        self._clock_ns, self._monotonic = clock_ns, monotonic
        self._view: OwnershipView | None = None
        self._storage: Storage | None = None
        #: the buckets without an owner at the latest check, sorted; None: not known
        self.unowned: list[str] | None = None
        #: the registered vehicles of the unowned buckets, by id (read when the unowned buckets change)
        self.vehicles: dict[str, UnservedVehicle] = {}
        #: when each unowned bucket was first seen without an owner [time.monotonic() s]
        self._since: dict[str, float] = {}
        self._read_for: frozenset[str] = frozenset()
        #: this replica raises the alarms (it holds the warden's lock)
        self.warden = False
        #: the warden's raised ``unserved`` alarms, by vehicle
        self._raised: dict[str, AlarmRecord] = {}
        #: the database read under way (in a thread), if any
        self._reading: asyncio.Future[_Read] | None = None

    def attach(self, view: OwnershipView, storage: Storage) -> None:
        """Watch the lock table through ``view``; ``storage`` (a connection of the watch's own, used off the event
        loop) reads the registry and the alarms."""
        self._view, self._storage = view, storage

    def close(self) -> None:
        if self._storage is not None:
            self._storage.close()
            self._storage = None

    async def check(self) -> list[AlarmChange]:
        """One housekeeping round: follow the lock table; as warden, the alarm changes to store and publish."""
        state = self._view() if self._view is not None else None
        if state is None or state.unowned is None or self._storage is None:
            self.unowned = None  # the lock connection is down: nothing is known, and its warden's lock is gone
            self._resign()
            return []
        unowned = frozenset(state.unowned)
        now = self._monotonic()
        self._since = {bucket: self._since.get(bucket, now) for bucket in unowned}
        self.unowned = sorted(unowned)
        if not state.warden:
            self._resign()
        self._take_read(state.warden)
        if not unowned:  # every bucket has an owner: no vehicle to read
            self.vehicles, self._read_for = {}, unowned
        to_office = state.warden and not self.warden
        if self._reading is None and (unowned != self._read_for or to_office):
            self._reading = asyncio.ensure_future(asyncio.to_thread(self._read, unowned, to_office))
        if not self.warden or unowned != self._read_for:
            return []  # the alarms wait for the registry of these buckets
        changes = self._cleared(unowned) + self._raised_now(now)
        if changes and self.engine.events.wants("alarm"):
            for change in changes:
                self.engine.events.publish(FleetEvent("alarm", change.record.vehicle, change.event))
        return changes

    def statuses(self) -> list[dict[str, Any]]:
        """The unserved vehicles as ``GET /vehicles`` lists them (``served`` false, level STALE), by id."""
        unowned = set(self.unowned or ())
        return [
            {
                "id": v.id,
                "profile": v.profile,
                "level": "STALE",
                "stale": True,
                "alive": None,
                "last_seq": None,
                "last_seen_ns": None,
                "seconds_since_seen": None,
                "gain_version": None,
                "gain_set": None,
                "counters": {},
                "rejected": {},
                "served": False,
            }
            for v in sorted(self.vehicles.values(), key=lambda v: v.id)
            if v.bucket in unowned and v.id not in self.engine.vehicles
        ]

    async def wait_read(self) -> None:
        """Wait for the database read under way, if any (its result is taken at the next :meth:`check`)."""
        if self._reading is not None:
            await asyncio.wait([self._reading])

    # ------------------------------------------------------------------ reading the database (in a thread)

    def _read(self, unowned: frozenset[str], office: bool) -> _Read:
        """The registry (when some bucket has no owner) and, for a new warden, the ``unserved`` alarms raised."""
        try:
            storage = self._require()
            vehicles = storage.vehicles() if unowned else []
            latched = storage.latched_alarms() if office else None
        except Exception as exc:  # a read of a database that failed or closed: tried again at a later round
            log.warning("the vehicles of the buckets without an owner could not be read: %s", exc)
            return _Read(unowned, None, None)
        raised = None
        if latched is not None:
            raised = [AlarmRecord.from_dict(r) for r in latched if r["kind"] == "unserved" and r["state"] == "raised"]
        return _Read(unowned, vehicles, raised)

    def _take_read(self, warden: bool) -> None:
        """Take a finished read: the unowned buckets' vehicles, and the office of warden if still held."""
        if self._reading is None or not self._reading.done():
            return
        read, self._reading = self._reading.result(), None
        if read.vehicles is None:
            return
        self.vehicles = {
            vehicle_id: UnservedVehicle(vehicle_id, profile, bucket_of(vehicle_id))
            for vehicle_id, profile, _ in read.vehicles
            if bucket_of(vehicle_id) in read.unowned
        }
        if read.unowned != self._read_for and read.unowned:
            log.info(
                "buckets without an owner: %s (%d registered vehicles unserved)",
                ",".join(sorted(read.unowned)),
                len(self.vehicles),
            )
        self._read_for = read.unowned
        if read.raised is not None and warden and not self.warden:
            # the alarms an earlier warden raised and nobody cleared: this one clears or keeps them
            self.engine.alarms.load(read.raised, served=False)
            self._raised = {record.vehicle: record for record in read.raised}
            self.warden = True
            log.info("this replica is the warden: it raises the alarms of vehicles whose bucket has no owner")

    def _require(self) -> Storage:
        if self._storage is None:
            raise StorageError("the ownership watch has no database")
        return self._storage

    # ------------------------------------------------------------------ the warden's alarms

    def _raised_now(self, now: float) -> list[AlarmChange]:
        """Raise the alarm of each vehicle whose bucket has had no owner for ``unserved_after_s``."""
        changes = []
        now_ns = self._clock_ns()
        for vehicle in self.vehicles.values():
            since = self._since.get(vehicle.bucket)
            if vehicle.id in self._raised or since is None or now - since < self.unserved_after_s:
                continue
            if vehicle.id in self.engine.vehicles:
                continue  # this replica serves it (its bucket was taken since the registry was read)
            why = f"bucket {vehicle.bucket} has no owner: no replica estimates this vehicle"
            change = self.engine.alarms.raise_level(
                vehicle.id, vehicle.profile, "unserved", "STALE", now_ns, None, None, why
            )
            record = change.record if change is not None else self.engine.alarms.current(vehicle.id, "unserved")
            if record is not None:
                self._raised[vehicle.id] = record
            if change is not None:
                changes.append(change)
        return changes

    def _cleared(self, unowned: frozenset[str]) -> list[AlarmChange]:
        """Clear the alarm of each vehicle whose bucket has an owner again."""
        changes = []
        now_ns = self._clock_ns()
        for vehicle_id in [v for v in self._raised if bucket_of(v) not in unowned]:
            raised = self._raised.pop(vehicle_id)
            message = f"bucket {bucket_of(vehicle_id)} has an owner again"
            current = self.engine.alarms.current(vehicle_id, "unserved")
            if current is not None and current.state == "raised":
                change = self.engine.alarms.clear(vehicle_id, "unserved", now_ns, message)
            else:
                # this replica took the vehicle over and loaded the alarm as cleared (AlarmBook.load), or no longer
                # holds it: the clear is stored from here all the same, once
                record = current if current is not None else raised
                if record.state == "raised":
                    record.state, record.cleared_t_ns, record.message = "cleared", now_ns, message
                record.updated_t_ns = now_ns
                change = AlarmChange(record, record.event("cleared", now_ns))
            if change is not None:
                changes.append(change)
            self._forget_unless_served(vehicle_id)
        return changes

    def _resign(self) -> None:
        """No longer the warden: its alarms of vehicles it does not serve leave its memory (the next warden reads
        them from the database)."""
        if not self.warden:
            return
        for vehicle_id in self._raised:
            self._forget_unless_served(vehicle_id)
        self._raised = {}
        self.warden = False
        log.info("this replica is no longer the warden of buckets without an owner")

    def _forget_unless_served(self, vehicle_id: str) -> None:
        if vehicle_id not in self.engine.vehicles and vehicle_id not in self.engine.held:
            self.engine.alarms.forget({vehicle_id})
