"""The dashboard hub on a real fleet engine, without a server: frames, deltas, decimation, following, back-pressure."""

from __future__ import annotations

import asyncio
import itertools
import json
import threading

import pytest

from agv_protocol.wire import EstimateRow, Measurement, OwnershipChange, all_buckets, vehicle_key
from edge_client.library import paper_1
from service.fleet import EngineConfig, FleetEngine, FleetEvent, UnknownVehicle
from service.profiles import ProfileSpec
from service.settings import DashboardSettings
from service.web.hub import CLIENT_QUEUE_FRAMES, FLEET_COLUMNS, OWNERSHIP_KEPT, POINT_COLUMNS, Client, DashboardHub
from tests.service.helpers import FAST_DESIGN, constant_measurement, plant_measurements
from tests.web.helpers import cruise

ALARMS = {"torque_warn_nm": 10.0, "torque_fault_nm": 20.0, "raise_after_s": 0.2, "warmup_s": 1.0}


def make_engine(gains) -> FleetEngine:
    engine = FleetEngine(EngineConfig())
    engine.add_profile("default", ProfileSpec.model_validate({"design": FAST_DESIGN, "alarms": ALARMS}))
    engine.activate("default", gains)
    return engine


def make_hub(engine: FleetEngine, **settings) -> DashboardHub:
    hub = DashboardHub(engine, DashboardSettings(**settings))
    hub.attach()
    return hub


def feed(engine: FleetEngine, measurements: list[Measurement]) -> None:
    engine.process([(vehicle_key(m.vehicle_id, "meas"), m.encode()) for m in measurements])


def frames(client: Client) -> list[tuple[str, dict]]:
    """The (event, data) pairs waiting in a client's queue."""
    out = []
    while not client.queue.empty():
        raw = client.queue.get_nowait()
        if raw is None:
            out.append(("<end>", {}))
            continue
        event, data = raw.decode().split("\n", 1)
        assert event.startswith("event: ") and data.startswith("data: ") and data.endswith("\n\n")
        out.append((event[7:], json.loads(data[6:])))
    return out


def rows_by_id(rows: list[list]) -> dict[str, dict]:
    return {row[0]: dict(zip(FLEET_COLUMNS, row, strict=True)) for row in rows}


def test_a_fleet_stream_starts_with_every_row_then_sends_only_changed_rows(fast_gains):
    engine = make_engine(fast_gains)
    hub = make_hub(engine)
    feed(engine, [constant_measurement(v, 0) for v in ("a", "b", "c")])
    client = hub.connect("fleet")
    first = frames(client)
    assert [name for name, _ in first] == ["hello", "alarms", "fleet", "ownership"]
    hello, alarms, fleet, ownership = (data for _, data in first)
    assert hello["fleet_columns"] == list(FLEET_COLUMNS) and hello["point_columns"] == list(POINT_COLUMNS)
    assert alarms == {"full": True, "upsert": [], "remove": []}
    assert ownership == {"full": True, "changes": []}  # no replica announced a change of buckets
    rows = rows_by_id(fleet["rows"])
    assert fleet["full"] and sorted(rows) == ["a", "b", "c"]
    assert rows["a"]["level"] == "OK" and rows["a"]["profile"] == "default" and rows["a"]["vx"] == pytest.approx(10.0)
    hub.tick(now=100.0)
    assert frames(client) == []  # nothing changed: nothing sent
    feed(engine, [constant_measurement("b", 1, vx=12.0)])
    hub.tick(now=101.0)
    (name, delta), *_ = frames(client)
    assert name == "fleet" and not delta["full"] and [row[0] for row in delta["rows"]] == ["b"]
    feed(engine, [constant_measurement("c", 2, vx=11.0)])
    hub.tick(now=101.1)  # before the next fleet tick is due (fleet_hz = 2)
    assert frames(client) == []


def test_a_fleet_row_carries_the_payload_the_vehicle_reported(fast_gains):
    """payload_kg: what the vehicle reported (0: none), in the full frame and in the delta after a new report."""
    engine = make_engine(fast_gains)
    hub = make_hub(engine)
    feed(engine, [constant_measurement(v, 0) for v in ("a", "b")])
    engine.set_payload("b", 246.04)
    client = hub.connect("fleet")
    rows = rows_by_id(next(data for name, data in frames(client) if name == "fleet")["rows"])
    assert (rows["a"]["payload_kg"], rows["b"]["payload_kg"]) == (0.0, 246.0)
    engine.set_payload("a", 80.0)  # nothing else changed: the new payload alone makes the delta
    hub.tick(now=100.0)
    (name, delta), *_ = frames(client)
    assert name == "fleet" and [row[0] for row in delta["rows"]] == ["a"]
    assert rows_by_id(delta["rows"])["a"]["payload_kg"] == 80.0


class Announced:
    """Ownership announcements as the transport hands them over (service.web.hub.OwnershipSource)."""

    def __init__(self) -> None:
        self.payloads: list[bytes] = []

    def drain_ownership(self) -> list[bytes]:
        drained, self.payloads = self.payloads, []
        return drained


def ownership_change(replica: str, gained: list[str], lost: list[str], k: int) -> OwnershipChange:
    kept = sorted(set(all_buckets()[:8]) | set(gained) - set(lost))
    return OwnershipChange(replica=replica, gained=gained, lost=lost, buckets=kept, vehicles=k, t_ns=k)


def test_ownership_changes_go_to_the_fleet_streams_and_a_new_one_gets_the_newest(fast_gains):
    source = Announced()
    hub = DashboardHub(make_engine(fast_gains), DashboardSettings(), "ra")
    hub.attach(ownership=source)
    fleet, profiles = hub.connect("fleet"), hub.connect("profiles")
    frames(fleet)
    frames(profiles)
    handed = ownership_change("ra", [], all_buckets()[8:], 1)
    taken = ownership_change("rb", all_buckets()[8:], [], 2)
    source.payloads += [handed.encode(), b'{"replica": "rc"}', taken.encode()]  # one not an OwnershipChange
    hub.tick(now=100.0)
    pushed = [data for name, data in frames(fleet) if name == "ownership"]
    assert pushed == [{"full": False, "changes": [handed.model_dump(mode="json"), taken.model_dump(mode="json")]}]
    assert [name for name, _ in frames(profiles)] == []  # a fleet-level event: the fleet view shows it
    later = [ownership_change("ra", [f"b{k % 16:02x}"], [], 3 + k) for k in range(OWNERSHIP_KEPT)]
    source.payloads += [c.encode() for c in later]
    hub.tick(now=101.0)
    first = dict(frames(hub.connect("fleet")))["ownership"]
    assert first == {"full": True, "changes": [c.model_dump(mode="json") for c in later]}  # the newest kept


def test_a_vehicle_stream_gets_decimated_points_with_the_measurement_and_only_its_vehicle_is_followed(fast_gains):
    engine = make_engine(fast_gains)
    hub = make_hub(engine, plot_hz=20.0, history_s=5.0)
    feed(engine, [constant_measurement(v, 0) for v in ("a", "b")])
    client = hub.connect("vehicle", "a")
    names = [name for name, _ in frames(client)]
    assert names == ["hello", "alarms", "status", "trace"]
    assert engine.events.audience("estimate") == {"a"} and set(hub.traces) == {"a"}
    points = []
    for k in range(1, 201):  # 2 s at 100 Hz, ticks every 100 ms
        feed(engine, [constant_measurement(v, k, vx=10.0 + k / 100) for v in ("a", "b")])
        if k % 10 == 0:
            hub.tick(now=float(k))
            points += [p for name, data in frames(client) if name == "trace" for p in data["points"]]
    assert len(points) == 40  # 2 s at 20 Hz
    t = [p[0] for p in points]
    assert all(abs((t2 - t1) - 0.05) < 1e-6 for t1, t2 in itertools.pairwise(t))
    column = {name: i for i, name in enumerate(POINT_COLUMNS)}
    assert points[-1][column["vx_meas"]] == pytest.approx(10.0 + 200 / 100)  # samples 5, 10, ..., 200 were kept
    assert points[-1][column["r_meas"]] == 0.0
    for k in range(201, 1001):  # 8 s more: the history keeps history_s
        feed(engine, [constant_measurement("a", k)])
    hub.tick(now=2000.0)
    assert len(hub.traces["a"].points) == 100  # 5 s at 20 Hz
    hub.disconnect(client)
    assert client.closed


def test_the_hub_follows_viewed_then_alarmed_then_recent_vehicles_up_to_follow_max(fast_gains):
    engine = make_engine(fast_gains)
    hub = make_hub(engine, follow_max=2)
    healthy = plant_measurements(["a", "b"], 700, scenario=cruise("healthy", duration_s=10.0))
    faulty = plant_measurements(["c"], 700, scenario=paper_1())  # 30 N m torque bias from 5 s
    feed(engine, [*healthy[0], *faulty[0]])
    viewer = hub.connect("vehicle", "a")
    assert hub.followed == {"a"}
    for k in range(1, 700):
        feed(engine, [*healthy[k], *faulty[k]])
    hub.tick(now=1.0)
    assert "torque_fault" in {r.kind for r in engine.alarms.for_vehicle("c")}
    assert hub.followed == {"a", "c"}  # viewed, then alarmed
    hub.disconnect(viewer)
    hub.tick(now=2.0)
    assert hub.followed == {"c", "a"}  # alarmed, then recently viewed
    hub.connect("vehicle", "b")
    assert hub.followed == {"b", "c"} and set(hub.traces) == {"b", "c"}  # a falls off: follow_max = 2
    assert engine.events.audience("estimate") == {"b", "c"}


def test_alarm_changes_reach_every_stream_and_closed_alarms_are_removed(fast_gains):
    engine = make_engine(fast_gains)
    hub = make_hub(engine)
    for row in plant_measurements(["c"], 700, scenario=paper_1()):
        feed(engine, row)
    fleet, profiles = hub.connect("fleet"), hub.connect("profiles")
    latched = next(data for name, data in frames(profiles) if name == "alarms")["upsert"]
    assert {a["kind"] for a in latched} == {"torque_fault", "steer_fault"}  # paper scenario 1 has both faults
    alarm = next(a for a in latched if a["kind"] == "torque_fault")
    assert alarm["vehicle"] == "c" and alarm["state"] == "raised" and not alarm["acknowledged"]
    frames(fleet)
    engine.acknowledge(alarm["id"], "tester")
    hub.tick(now=1.0)
    for client in (fleet, profiles):
        update = next(data for name, data in frames(client) if name == "alarms")
        record = next(r for r in update["upsert"] if r["id"] == alarm["id"])
        assert not update["full"] and record["acknowledged"] and record["latched"]
    change = engine.alarms.clear("c", "torque_fault", 0)  # the condition went away: acknowledged and cleared
    assert change is not None
    engine.events.publish(FleetEvent("alarm", "c", change.event))  # as the engine publishes its changes
    hub.tick(now=2.0)
    update = next(data for name, data in frames(profiles) if name == "alarms")
    assert update["remove"] == [alarm["id"]] and update["upsert"] == []


def test_a_browser_that_falls_behind_is_disconnected_and_its_stream_ends(fast_gains):
    engine = make_engine(fast_gains)
    hub = make_hub(engine)
    feed(engine, [constant_measurement("a", 0)])
    client = hub.connect("vehicle", "a")
    for k in range(1, CLIENT_QUEUE_FRAMES + 10):  # one trace frame per tick, never read
        feed(engine, [constant_measurement("a", 10 * k)])
        hub.tick(now=0.0)
    assert client.closed and client not in hub.clients

    async def read_all() -> list[bytes]:
        return [frame async for frame in client.frames()]

    # the queue was emptied and the stream ends at once: the browser reconnects to a fresh snapshot
    assert asyncio.run(asyncio.wait_for(read_all(), 5.0)) == []


def test_a_vehicle_view_of_an_unknown_vehicle_is_refused(fast_gains):
    hub = make_hub(make_engine(fast_gains))
    with pytest.raises(UnknownVehicle):
        hub.connect("vehicle", "nobody")
    with pytest.raises(UnknownVehicle):
        hub.connect("vehicle", None)


def test_streams_can_be_ended_from_another_thread_for_a_shutdown(fast_gains):
    engine = make_engine(fast_gains)

    async def scenario() -> list[bytes]:
        hub = DashboardHub(engine, DashboardSettings())
        hub.start()
        client = hub.connect("profiles")
        threading.Thread(target=hub.end_streams_threadsafe).start()  # as a signal handler would
        received = [frame async for frame in client.frames()]
        await hub.stop()
        return received

    # the stream ends (within the timeout, instead of sending keep-alives forever); what was queued is dropped
    assert asyncio.run(asyncio.wait_for(scenario(), 10.0)) == []


def test_a_vehicle_opened_for_the_first_time_shows_the_estimates_the_engine_keeps(fast_gains):
    engine = make_engine(fast_gains)
    hub = make_hub(engine, plot_hz=20.0)
    for k in range(300):  # 3 s, within the engine's 500-sample history
        feed(engine, [constant_measurement("a", k)])
    client = hub.connect("vehicle", "a")
    (history,) = [data for name, data in frames(client) if name == "trace"]
    assert history["history"] and len(history["points"]) == 60  # 3 s at 20 Hz
    assert all(p[1] is None and p[2] is None for p in history["points"])  # estimates only, no measurements
    for k in range(300, 320):
        feed(engine, [constant_measurement("a", k)])
    hub.tick(now=0.0)
    live = [p for name, data in frames(client) if name == "trace" for p in data["points"]]
    last = history["points"][-1][0]
    assert [round(p[0] - last, 3) for p in live] == [0.05, 0.1, 0.15, 0.2]  # the same grid goes on


def test_live_estimates_already_in_a_backfill_do_not_restart_the_plot():
    """A browser opens a vehicle: the trace is backfilled from the engine's history, then estimates that were
    still queued on the event bus arrive, older than the backfill's last point. They are dropped; only a real
    clock jump back (a sample older than everything kept) starts the plot again."""
    from service.web.hub import Trace

    period = 50_000_000  # 20 points a second
    estimate = EstimateRow(seq=0, t_ns=0, vx=10.0, vy=0.0, r=0.0, torque_fault=0.0, steer_fault=0.0, in_domain=True)
    older = Trace("v", period, 1200)
    for k in range(100):
        older.add_estimate(1_000_000_000 + k * 10_000_000, estimate, None)
    trace = Trace("v", period, 1200)
    trace.prepend(older)
    assert trace.take_new() is None and len(trace.points) == 20
    trace.add_estimate(1_000_000_000 + 95 * 10_000_000, estimate, (10.0, 0.0))  # queued before the backfill ran
    assert not trace.reset and len(trace.points) == 20
    trace.add_estimate(1_000_000_000 + 100 * 10_000_000, estimate, (10.0, 0.0))  # the next live sample
    frame = trace.take_new()
    assert frame is not None and not frame["history"] and len(frame["points"]) == 1
    trace.add_estimate(500_000_000, estimate, (10.0, 0.0))  # the vehicle's clock went back: start again
    assert trace.reset and len(trace.points) == 1


def test_a_vehicle_that_only_went_stale_is_not_followed(fast_gains):
    """Following costs an event per sample; a latched STALE alarm (cleared or not) is no reason to keep a plot."""
    clock = {"mono": 0.0}
    engine = FleetEngine(EngineConfig(), monotonic=lambda: clock["mono"])
    engine.add_profile("default", ProfileSpec.model_validate({"design": FAST_DESIGN, "alarms": ALARMS}))
    engine.activate("default", fast_gains)
    hub = make_hub(engine, follow_max=8)
    feed(engine, [constant_measurement("s", k) for k in range(5)])
    clock["mono"] = 10.0  # silent for 10 s: STALE
    engine.housekeeping()
    assert {r.kind for r in engine.alarms.latched()} == {"stale"}
    feed(engine, [constant_measurement("s", 5)])  # back: the STALE alarm clears, stays latched until acknowledged
    hub.tick(now=1.0)
    assert [r.kind for r in engine.alarms.latched()] == ["stale"]
    assert hub.followed == frozenset() and engine.events.audience("estimate") == set()
