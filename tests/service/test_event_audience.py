"""The event hook's per-vehicle audience: only followed vehicles' estimate events are built and delivered."""

from __future__ import annotations

import asyncio

from agv_protocol.wire import Measurement, vehicle_key
from service.fleet import EngineConfig, EventBus, FleetEngine
from service.profiles import ProfileSpec
from tests.service.helpers import FAST_DESIGN, constant_measurement


def make_engine(gains) -> FleetEngine:
    engine = FleetEngine(EngineConfig())
    engine.add_profile("default", ProfileSpec.model_validate({"design": FAST_DESIGN}))
    engine.activate("default", gains)
    return engine


def pairs(measurements: list[Measurement]) -> list[tuple[str, bytes]]:
    return [(vehicle_key(m.vehicle_id, "meas"), m.encode()) for m in measurements]


def drain(subscription) -> list:
    out = []
    while (event := subscription.get_nowait()) is not None:
        out.append(event)
    return out


def test_audience_is_the_union_of_followed_vehicles_or_none_for_everyone():
    bus = EventBus()
    assert bus.audience("estimate") == frozenset()
    a = bus.subscribe(kinds=("estimate",), vehicles=frozenset({"a"}))
    b = bus.subscribe(kinds=("estimate",), vehicles=frozenset({"b", "c"}))
    bus.subscribe(kinds=("alarm",))  # every vehicle, but not estimates
    assert bus.audience("estimate") == {"a", "b", "c"}
    assert bus.audience("alarm") is None
    b.follow(frozenset())
    assert bus.audience("estimate") == {"a"}
    a.follow(None)
    assert bus.audience("estimate") is None


def test_a_filtered_subscription_gets_only_its_vehicles_with_the_measurement(fast_gains):
    async def scenario():
        engine = make_engine(fast_gains)
        with (
            engine.events.subscribe(kinds=("estimate",), vehicles=frozenset({"b"})) as only_b,
            engine.events.subscribe(kinds=("estimate",)) as everyone,
        ):
            engine.process(pairs([constant_measurement(v, 0, vx=12.5, r=0.01, torque=70.0) for v in "abc"]))
            followed, all_events = drain(only_b), drain(everyone)
            only_b.follow(frozenset())
            engine.process(pairs([constant_measurement(v, 1) for v in "abc"]))
            after_unfollow = drain(only_b)
        return followed, all_events, after_unfollow

    followed, all_events, after_unfollow = asyncio.run(scenario())
    assert [e.vehicle for e in followed] == ["b"]
    assert followed[0].measured == (12.5, 0.01, 70.0, 0.0)  # the measurement the estimate answers
    assert sorted(e.vehicle for e in all_events) == ["a", "b", "c"]
    assert after_unfollow == []


def test_no_estimate_event_is_built_for_vehicles_nobody_follows(fast_gains, monkeypatch):
    built: list[str] = []
    engine = make_engine(fast_gains)
    publish = engine.events.publish

    def spy(event):
        built.append(event.vehicle)
        publish(event)

    monkeypatch.setattr(engine.events, "publish", spy)

    async def scenario():
        with engine.events.subscribe(kinds=("estimate",), vehicles=frozenset({"a"})):
            engine.process(pairs([constant_measurement(v, 0) for v in "abc"]))

    asyncio.run(scenario())
    assert built == ["a"]
