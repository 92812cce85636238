"""Bucket ownership without a database: the fair share of the leases, and a fleet engine that adopts and forgets
the vehicles of a bucket taken over or handed over (service/bucket_leases.py, FleetEngine.adopt and forget)."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from service.bucket_leases import fair_share
from service.fleet import AlarmRecord
from service.protocol import N_BUCKETS
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
