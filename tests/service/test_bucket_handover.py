"""The bucket hand-over on its own (service/bucket_handover.py): a bucket gained is served from the registry (its
vehicles and latched alarms adopted, its measurements subscribed to), a bucket lost is dropped (subscriptions,
vehicles and their alarms) and its queued writes stored before the hand-over completes, and each change is announced
on Zenoh. Real parts: a SQLite registry and the storage writer, a fleet engine, the service's transport as a router
on loopback and a Zenoh client putting measurements."""

from __future__ import annotations

import asyncio
import time
from functools import partial
from pathlib import Path

import pytest

from agv_protocol.wire import OwnershipChange, shard_buckets, vehicle_key
from service.bucket_handover import BucketHandover
from service.settings import StorageSettings
from service.storage import SqliteStorage, Storage
from service.storage_writer import StorageWriter
from service.transport import Transport, open_session
from tests.faults.helpers import exclusive_lock, stored_vehicles
from tests.service.helpers import constant_measurement, make_settings, wait_for
from tests.service.test_bucket_ownership import ids_in, stale_record
from tests.service.test_fleet_engine import make_engine

pytestmark = pytest.mark.network

#: how long the test holds the database locked while a bucket is handed over [s]
LOCKED_S = 0.5


class Database:
    """The service's side of the database, as the hand-over uses it: a connection for reads and the storage
    writer (a connection of its own), whose queue :meth:`stored` waits for."""

    def __init__(self, path: Path) -> None:
        self.db = SqliteStorage(path)
        self.writer: StorageWriter | None = StorageWriter(SqliteStorage(path), StorageSettings())

    async def stored(self, what: str) -> None:
        assert self.writer is not None
        await asyncio.wrap_future(self.writer.barrier())

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
        self.db.close()


def test_a_bucket_gained_is_served_from_the_registry_and_a_bucket_lost_is_dropped_once_its_writes_are_stored(
    fast_gains, tmp_path: Path
):
    settings = make_settings(tmp_path, shard={"index": 0, "replicas": 2})
    mine, bucket = shard_buckets(0, 2), shard_buckets(1, 2)[0]
    taken, elsewhere = ids_in(bucket, 2), ids_in(shard_buckets(1, 2)[1], 1)
    path = tmp_path / "fleet.sqlite3"
    database = Database(path)
    database.db.put_vehicles([(v, "default", 1) for v in taken + elsewhere])
    database.db.put_payload(taken[1], 70.0, 2)  # its payload is adopted with it
    database.db.put_payload(elsewhere[0], 50.0, 2)
    latched = stale_record(taken[0], 8)
    database.db.record_alarm_changes([(latched.to_dict(), latched.event("raised", 8).model_dump())])
    engine = make_engine(fast_gains)
    handover = BucketHandover(settings, "replica-test", engine)
    assert handover.buckets == mine
    transport = Transport(settings.zenoh, handover.buckets, "replica-test", dynamic=True)
    transport.open()
    client = open_session("client", settings.zenoh.endpoint)
    announced: list[OwnershipChange] = []

    def announcements(n: int) -> list[OwnershipChange]:
        announced.extend(OwnershipChange.decode(p) for p in transport.drain_ownership())
        return announced if len(announced) >= n else []

    def measured(vehicle_id: str, seq: int) -> list[tuple[str, bytes]]:
        """Put one measurement of ``vehicle_id`` and return what the transport received within a second."""
        client.put(vehicle_key(vehicle_id, "meas"), constant_measurement(vehicle_id, seq).encode())
        deadline, received = time.monotonic() + 1.0, []
        while time.monotonic() < deadline and not received:
            received = transport.drain(100)
            time.sleep(0.02)
        return received

    async def hand_over() -> None:
        await handover.start(transport, database)  # no shared database: no locks, no leases
        assert handover.lease_state() is None and handover.serving() == ",".join(mine)
        await handover.gain([bucket])
        assert handover.buckets == sorted([*mine, bucket]) == transport.buckets
        assert sorted(engine.vehicles) == sorted(taken)  # not the vehicle of the bucket still elsewhere
        assert [engine.vehicles[v].payload_kg for v in taken] == [0.0, 70.0]
        assert [(a.vehicle, a.kind) for a in engine.alarms.latched()] == [(taken[0], "stale")]
        assert [key for key, _ in measured(taken[1], 1)] == [vehicle_key(taken[1], "meas")]
        gained = wait_for(lambda: announcements(1), what="the announcement of the bucket gained")
        assert [(c.replica, c.gained, c.lost, c.buckets, c.vehicles) for c in gained] == [
            ("replica-test", [bucket], [], handover.buckets, 2)
        ]
        with exclusive_lock(path):  # the database takes no write: the hand-over waits for the one queued
            registered = database.writer.submit(  # type: ignore[union-attr]
                "a registration", partial(Storage.put_vehicles, rows=[("late-1", "default", 9)])
            )
            losing = asyncio.ensure_future(handover.lose([bucket]))
            await asyncio.sleep(LOCKED_S)
            assert not losing.done() and not registered.done()
            assert handover.buckets == mine and engine.vehicles == {} and engine.alarms.latched() == []
            assert len(announcements(1)) == 1  # not announced before the writes are stored
        await losing
        assert registered.done() and "late-1" in stored_vehicles(path)
        lost = wait_for(lambda: announcements(2), what="the announcement of the bucket lost")[1]
        assert (lost.gained, lost.lost, lost.buckets, lost.vehicles) == ([], [bucket], mine, 2)
        assert measured(taken[1], 2) == []  # no longer subscribed

    try:
        asyncio.run(hand_over())
    finally:
        handover.close()
        client.close()
        transport.close()
        database.close()
