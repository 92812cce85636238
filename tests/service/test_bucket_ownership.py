"""Bucket ownership without a shared database: the fair share of the leases, a fleet engine that adopts and forgets
the vehicles of a bucket taken over or handed over (service/bucket_leases.py, FleetEngine.adopt and forget), and
the vehicles of a bucket without owner (service/ownership.py) on a real SQLite registry, the lock table's state
given by the test."""

from __future__ import annotations

import asyncio
from pathlib import Path

from hypothesis import given
from hypothesis import strategies as st

from agv_protocol.wire import N_BUCKETS, bucket_of
from service.bucket_leases import LeaseState, fair_share
from service.fleet import AlarmChange, AlarmRecord
from service.ownership import OwnershipWatch
from service.storage import SqliteStorage
from tests.service.helpers import constant_measurement
from tests.service.test_fleet_engine import FakeClock, make_engine, pairs


@given(st.integers(min_value=1, max_value=40))
def test_the_fair_shares_cover_every_bucket_once_balanced_within_one(members):
    shares = [fair_share(rank, members, N_BUCKETS) for rank in range(members)]
    assert sum(shares) == N_BUCKETS and max(shares) - min(shares) <= 1
    assert shares == sorted(shares, reverse=True)  # the first ranks take the remainder


def stale_record(vehicle: str, t_ns: int) -> AlarmRecord:
    return AlarmRecord.from_dict(
        {
            "id": f"al-{vehicle}",
            "vehicle": vehicle,
            "profile": "default",
            "kind": "stale",
            "level": "STALE",
            "peak_level": "STALE",
            "state": "raised",
            "acknowledged": False,
            "raised_t_ns": t_ns,
            "updated_t_ns": t_ns,
            "value": None,
            "threshold": None,
            "message": "no measurement for 1.0 s",
        }
    )


def test_an_adopted_vehicle_starts_fresh_keeps_its_latched_alarm_and_clears_it_when_it_speaks(fast_gains):
    clock = FakeClock()
    engine = make_engine(fast_gains, clock=clock, alarms={"stale_after_s": 1.0})
    adopted = engine.adopt([("v1", "default", 5), ("v2", "default", 6), ("v3", "gone", 7)], [stale_record("v1", 8)])
    assert adopted == ["v1", "v2"] and "v3" in engine.held  # a profile this replica does not run: held
    assert engine.level_of(engine.vehicle("v1")) == "STALE" and engine.level_of(engine.vehicle("v2")) == "OK"
    assert [a.kind for a in engine.alarms.for_vehicle("v1")] == ["stale"]
    engine.process(pairs([constant_measurement("v1", 1000), constant_measurement("v2", 7)]))
    assert engine.stats["accepted"] == 2  # any sequence number starts a taken-over vehicle's observer
    assert engine.level_of(engine.vehicle("v1")) == "OK"  # its next measurement cleared the STALE alarm
    assert engine.alarms.current("v1", "stale").state == "cleared"
    clock.mono += 0.5
    assert engine.housekeeping() == []  # silence is counted from the takeover, not from the engine's start
    clock.mono += 1.0
    assert {c.record.vehicle for c in engine.housekeeping()} == {"v1", "v2"}


def test_a_forgotten_vehicle_leaves_memory_and_its_alarms_with_it(fast_gains):
    engine = make_engine(fast_gains)
    engine.adopt([("v1", "default", 5), ("v2", "default", 6)], [stale_record("v1", 8)])
    engine.forget(["v1", "nobody"])
    assert set(engine.vehicles) == {"v2"} and engine.alarms.latched() == []
    engine.process(pairs([constant_measurement("v1", 0)]))  # back later: registered anew
    assert engine.vehicle("v1").profile == "default"


# ---------------------------------------------------------------------- vehicles whose bucket has no owner


#: shard.unserved_after_s in these tests [s]
UNSERVED_AFTER_S = 2.0


class LockTable:
    """What a replica's lock thread last saw (service/bucket_leases.py): the unowned buckets, the warden's lock."""

    def __init__(self) -> None:
        self.state = LeaseState(connected=True, rounds=1, unowned=[], warden=True)

    def __call__(self) -> LeaseState:
        return self.state


def ids_in(bucket: str, n: int) -> list[str]:
    """The first ``n`` vehicle ids of the form v-K that fall into ``bucket``."""
    found = (f"v-{k}" for k in range(10_000) if bucket_of(f"v-{k}") == bucket)
    return [next(found) for _ in range(n)]


def watch_of(engine, tmp_path: Path, clock: FakeClock, registry: list[str]) -> tuple[OwnershipWatch, LockTable]:
    storage = SqliteStorage(tmp_path / "fleet.sqlite3")
    storage.put_vehicles([(v, "default", 1) for v in registry])
    watch = OwnershipWatch(engine, UNSERVED_AFTER_S, clock_ns=clock.ns, monotonic=clock.monotonic)
    table = LockTable()
    watch.attach(table, storage)
    return watch, table


def unserved_kinds(changes: list[AlarmChange]) -> list[tuple[str, str]]:
    assert all(c.record.kind == "unserved" for c in changes)
    return sorted((c.record.vehicle, c.event.state) for c in changes)


async def settle(watch: OwnershipWatch) -> list[AlarmChange]:
    """One housekeeping round, and another once the database read it started (in a thread) is done."""
    changes = await watch.check()
    await watch.wait_read()
    return changes + await watch.check()


def test_the_warden_alarms_the_vehicles_of_a_bucket_without_owner_after_the_delay_and_clears_them(
    fast_gains, tmp_path: Path
):
    clock = FakeClock()
    engine = make_engine(fast_gains, clock=clock)
    orphans, others = ids_in("b03", 2), ids_in("b04", 1)
    watch, table = watch_of(engine, tmp_path, clock, orphans + others)

    async def rounds() -> None:
        assert await settle(watch) == [] and watch.statuses() == [] and watch.unowned == [] and watch.warden
        table.state.unowned = ["b03"]  # its replica died: the lock is free
        assert await settle(watch) == []  # listed at once, alarmed only after unserved_after_s
        assert [(s["id"], s["served"], s["level"]) for s in watch.statuses()] == [(v, False, "STALE") for v in orphans]
        clock.mono += UNSERVED_AFTER_S
        raised = await watch.check()
        assert unserved_kinds(raised) == [(v, "raised") for v in orphans]
        assert {r.vehicle for r in engine.alarms.latched()} == set(orphans)  # GET /alarms of the warden lists them
        assert await settle(watch) == []  # raised once
        table.state.unowned = []  # an owner again
        cleared = await watch.check()
        assert unserved_kinds(cleared) == [(v, "cleared") for v in orphans]
        assert watch.statuses() == [] and engine.alarms.latched() == []  # the owner holds them now, not the warden

    asyncio.run(rounds())


def test_only_the_warden_raises_and_a_new_warden_takes_up_the_raised_alarms_from_the_database(
    fast_gains, tmp_path: Path
):
    clock = FakeClock()
    engine = make_engine(fast_gains, clock=clock)
    orphans = ids_in("b07", 2)
    watch, table = watch_of(engine, tmp_path, clock, orphans)
    table.state.unowned, table.state.warden = ["b07"], False
    # an earlier warden raised one of them and died: its alarm is in the database, raised
    earlier = AlarmRecord.from_dict({**stale_record(orphans[0], 5).to_dict(), "id": "al-earlier", "kind": "unserved"})
    storage = SqliteStorage(tmp_path / "fleet.sqlite3")
    storage.record_alarm_changes([(earlier.to_dict(), earlier.event("raised", 5).model_dump())])

    async def rounds() -> None:
        await settle(watch)
        clock.mono += UNSERVED_AFTER_S
        assert await settle(watch) == [] and len(watch.statuses()) == 2  # listed, not alarmed: not the warden
        table.state.warden = True
        raised = await settle(watch)
        assert unserved_kinds(raised) == [(orphans[1], "raised")]  # the other one's alarm is the earlier warden's
        assert engine.alarms.current(orphans[0], "unserved").id == "al-earlier"
        table.state.unowned = None  # the lock connection failed: nothing is known, and the warden's lock with it
        assert await settle(watch) == [] and not watch.warden and engine.alarms.latched() == []

    asyncio.run(rounds())


def test_the_replica_that_serves_an_unserved_vehicle_again_loads_its_alarm_as_cleared(fast_gains):
    engine = make_engine(fast_gains)
    unserved = AlarmRecord.from_dict({**stale_record("v1", 5).to_dict(), "id": "al-u", "kind": "unserved"})
    engine.adopt([("v1", "default", 5)], [unserved])
    record = engine.alarms.current("v1", "unserved")
    assert record.state == "cleared" and not record.acknowledged  # latched until acknowledged, as a cleared STALE
    assert engine.level_of(engine.vehicle("v1")) == "OK"
