"""The dashboard bridge: fleet state and fleet events in, server-sent events out.

One :class:`DashboardHub` per service, on the asyncio loop that owns the
fleet. Each browser tab opens one stream (:meth:`DashboardHub.connect`) for
the view it shows:

``fleet``     every vehicle's row (level, last seen, fault estimates): all rows
              on connect, then only the rows that changed, ``fleet_hz`` times a
              second; and the bucket ownership changes of every replica (bucket
              leases): the last ``OWNERSHIP_KEPT`` on connect, then each new one;
``vehicle``   one vehicle's status and its plot trace: the last ``history_s``
              of estimates decimated to ``plot_hz``, with the measurement each
              answers and, when a simulator publishes it, the ground truth;
              then the new points, ``push_hz`` times a second;
``profiles``  nothing but the alarms.

Every view gets the latched alarms on connect, then each change.

Where the data comes from: the hub subscribes to the fleet's event bus for
alarm events of every vehicle and for estimate events of the vehicles it
*follows* only (those being viewed, then those with latched alarms, then the
recently viewed; at most ``follow_max``), so the engine builds no event for
the rest of the fleet. Fleet rows are read from the engine's arrays at
``fleet_hz``: no per-sample work for the fleet view, whatever the fleet size.
Ownership changes are the replicas' announcements on Zenoh
(:class:`~agv_protocol.wire.OwnershipChange`, this replica's included), so a
page shows the whole fleet's whichever replica it is connected to.
A browser that does not keep up (its queue of frames fills) is disconnected
and reconnects to a fresh snapshot.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import time
from collections import deque
from collections.abc import AsyncIterator, Collection, Iterable
from typing import Any, Literal, Protocol

from agv_protocol.wire import (
    COLUMN_UNITS,
    ESTIMATE_COLUMNS,
    STATE_COLUMNS,
    Alarm,
    Estimate,
    EstimateRow,
    GroundTruth,
    OwnershipChange,
    ProtocolError,
)
from service.fleet import FleetEngine, Subscription, UnknownVehicle, Vehicle
from service.settings import DashboardSettings

log = logging.getLogger("agv_fe.service.web")

View = Literal["fleet", "vehicle", "profiles"]
VIEWS: tuple[View, ...] = ("fleet", "vehicle", "profiles")

#: Columns of a fleet row. last_seen_s: service clock [s since the epoch, whole seconds]; vx [m/s];
#: torque_fault [N m]; steer_fault [rad]; alive: liveliness token present (null: the vehicle declares none);
#: payload_kg: what the vehicle reported it carries [kg] (0: none reported).
FLEET_COLUMNS = ("id", "profile", "level", "last_seen_s", "vx", "torque_fault", "steer_fault", "alive", "payload_kg")
#: Columns of a plot point: t [s, vehicle clock], measured v_x [m/s] and r [rad/s] (null when not known),
#: then the estimate's float columns (agv_protocol.wire.ESTIMATE_COLUMNS; null when the profile has none).
POINT_COLUMNS = ("t", "vx_meas", "r_meas", *ESTIMATE_COLUMNS)
#: Columns of a ground-truth point: t [s, simulator clock], then the state columns (v_x, v_y, r, T_f, delta_f).
TRUTH_COLUMNS = ("t", *STATE_COLUMNS)
#: Decimal places a plot point keeps, by the column's unit.
_DIGITS_BY_UNIT = {"m/s": 4, "rad/s": 5, "N m": 2, "rad": 5, "1": 4}
#: Frames waiting for one browser; a browser that falls this far behind is disconnected.
CLIENT_QUEUE_FRAMES = 256
#: Ownership changes a fleet view gets on connect (the newest).
OWNERSHIP_KEPT = 20
#: A comment line is sent after this long without a frame, so proxies keep the stream open [s].
KEEPALIVE_S = 15.0
#: Alarm kinds that make a vehicle worth following first (faults before staleness or rejected inputs).
_FAULT_KINDS = frozenset(
    {"torque_fault", "steer_fault", "torque_effectiveness", "steer_effectiveness", "out_of_domain"}
)

Measured = tuple[float, float, float, float]
FleetRow = tuple[str, str, str, int | None, float | None, float | None, float | None, bool | None, float | None]


class TruthSource(Protocol):
    """Where ground truth comes from (the Zenoh transport): subscribe per vehicle, drain payloads."""

    def follow_truth(self, vehicle_ids: Collection[str]) -> None: ...

    def drain_truth(self) -> list[tuple[str, bytes]]: ...


class OwnershipSource(Protocol):
    """Where the replicas' ownership announcements come from (the Zenoh transport): payloads, oldest first."""

    def drain_ownership(self) -> list[bytes]: ...


def sse(event: str, data: Any) -> bytes:
    """One server-sent event with a JSON payload."""
    return f"event: {event}\ndata: {json.dumps(data, separators=(',', ':'), allow_nan=False)}\n\n".encode()


def _rounded_columns(record: EstimateRow | GroundTruth, columns: tuple[str, ...]) -> list[float | None]:
    """The record's values of ``columns``, rounded for a plot point by each column's unit (None: absent)."""
    values = (getattr(record, name, None) for name in columns)
    return [
        None if v is None else _rounded(v, _DIGITS_BY_UNIT[COLUMN_UNITS[name]])
        for name, v in zip(columns, values, strict=True)
    ]


def _rounded(value: float, digits: int) -> float | None:
    return round(value, digits) if math.isfinite(value) else None


class Client:
    """One browser stream: a bounded queue of encoded frames; ``None`` ends the stream."""

    def __init__(self, view: View, vehicle: str | None) -> None:
        self.view = view
        self.vehicle = vehicle
        self.queue: asyncio.Queue[bytes | None] = asyncio.Queue(CLIENT_QUEUE_FRAMES + 1)
        self.closed = False

    def send(self, frame: bytes) -> None:
        if self.closed:
            return
        if self.queue.qsize() >= CLIENT_QUEUE_FRAMES:
            self.close()  # too slow: it reconnects and starts from a fresh snapshot
            return
        self.queue.put_nowait(frame)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        while not self.queue.empty():
            self.queue.get_nowait()
        self.queue.put_nowait(None)

    async def frames(self) -> AsyncIterator[bytes]:
        """The stream's bytes: frames as they come, a keep-alive comment when idle; ends when closed."""
        while True:
            try:
                frame = await asyncio.wait_for(self.queue.get(), KEEPALIVE_S)
            except TimeoutError:
                yield b": keep-alive\n\n"
                continue
            if frame is None:
                return
            yield frame


class Trace:
    """The plot history of one vehicle: points decimated to one per ``period_ns`` of vehicle time."""

    def __init__(self, vehicle: str, period_ns: int, maxlen: int) -> None:
        self.vehicle = vehicle
        self.period_ns = period_ns
        self.points: deque[list[float | None]] = deque(maxlen=maxlen)
        self.truth: deque[list[float | None]] = deque(maxlen=maxlen)
        self.new_points: list[list[float | None]] = []
        self.new_truth: list[list[float | None]] = []
        self.reset = False
        self.has_truth = False
        self.viewed_mono = 0.0
        self._next_point_ns = 0
        self._last_point_ns = 0
        self._next_truth_ns = 0
        self._last_truth_ns = 0
        #: estimates up to this time came from the engine's history (a backfill); live events for them,
        #: still queued on the event bus when the backfill ran, are dropped rather than seen as a clock reset
        self._backfilled_from_ns = 0
        self._backfilled_until_ns = 0

    def _take(self, t_ns: int, next_ns: int, last_ns: int) -> int | None:
        """The next decimation time if the sample at ``t_ns`` is kept, else None."""
        if t_ns < last_ns:  # the vehicle's clock went back: start the plot again
            self.points.clear()
            self.truth.clear()
            self.new_points.clear()
            self.new_truth.clear()
            self._last_point_ns = self._last_truth_ns = 0
            self._next_point_ns = self._next_truth_ns = 0
            self.reset = True
            next_ns = 0
        if t_ns < next_ns:
            return None
        return t_ns - t_ns % self.period_ns + self.period_ns

    def add_estimate(self, t_ns: int, estimate: EstimateRow, measured: Measured | None) -> None:
        """One estimate and the measurement (v_x, r, T_d, delta_d) it answers."""
        if self._backfilled_from_ns <= t_ns <= self._backfilled_until_ns:
            return
        following = self._take(t_ns, self._next_point_ns, self._last_point_ns)
        if following is None:
            return
        self._next_point_ns, self._last_point_ns = following, t_ns
        meas_vx, meas_r = (None, None) if measured is None else (measured[0], measured[1])
        point = [
            round(t_ns / 1e9, 3),
            None if meas_vx is None else _rounded(meas_vx, 4),
            None if meas_r is None else _rounded(meas_r, 5),
            *_rounded_columns(estimate, ESTIMATE_COLUMNS),
        ]
        self.points.append(point)
        self.new_points.append(point)

    def add_truth(self, truth: GroundTruth) -> None:
        self.has_truth = True
        following = self._take(truth.t_ns, self._next_truth_ns, self._last_truth_ns)
        if following is None:
            return
        self._next_truth_ns, self._last_truth_ns = following, truth.t_ns
        point = [round(truth.t_ns / 1e9, 3), *_rounded_columns(truth, STATE_COLUMNS)]
        self.truth.append(point)
        self.new_truth.append(point)

    def prepend(self, older: Trace) -> None:
        """Put the points of ``older`` (all before this trace's first point) in front, as room allows."""
        room = (self.points.maxlen or 0) - len(self.points)
        if not older.points or room <= 0:
            return
        if not self.points:  # decimation goes on from the last point put in
            self._next_point_ns, self._last_point_ns = older._next_point_ns, older._last_point_ns
            self._backfilled_until_ns = older._last_point_ns
            self._backfilled_from_ns = round(float(older.points[0][0] or 0.0) * 1e9)
        self.points.extendleft(reversed(list(older.points)[-room:]))

    def history(self) -> dict[str, Any]:
        return {"vehicle": self.vehicle, "history": True, "points": list(self.points), "truth": list(self.truth)}

    def take_new(self) -> dict[str, Any] | None:
        """The points added since the last call (everything after a reset), or None."""
        if self.reset:
            self.reset = False
            self.new_points, self.new_truth = [], []
            return self.history()
        if not self.new_points and not self.new_truth:
            return None
        frame = {"vehicle": self.vehicle, "history": False, "points": self.new_points, "truth": self.new_truth}
        self.new_points, self.new_truth = [], []
        return frame


class DashboardHub:
    """Browser streams fed from the fleet engine's state and events (see the module docstring)."""

    def __init__(self, engine: FleetEngine, settings: DashboardSettings, replica: str = "") -> None:
        self.engine = engine
        self.settings = settings
        self.replica = replica
        self.clients: list[Client] = []
        self.traces: dict[str, Trace] = {}
        self.followed: frozenset[str] = frozenset()
        self._period_ns = max(1, round(1e9 / settings.plot_hz))
        self._maxlen = max(2, math.ceil(settings.history_s * settings.plot_hz))
        self._fleet_rows: dict[str, FleetRow] = {}
        #: the newest ownership changes of every replica, oldest first (OwnershipChange as JSON)
        self.ownership: deque[dict[str, Any]] = deque(maxlen=OWNERSHIP_KEPT)
        self._ownership: OwnershipSource | None = None
        self._fleet_due = 0.0
        self._follow_dirty = True
        self._alarms: Subscription | None = None
        self._estimates: Subscription | None = None
        self._truth: TruthSource | None = None
        self._task: asyncio.Task[None] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self.ticks = 0
        #: how long the slowest tick and the last fleet update took on the loop [s]
        self.tick_seconds_max = 0.0
        self.fleet_seconds_last = 0.0

    # ------------------------------------------------------------------ life cycle

    def attach(self, truth: TruthSource | None = None, ownership: OwnershipSource | None = None) -> None:
        """Subscribe to the fleet's alarm events, and to estimate events of the vehicles followed (none yet)."""
        self._truth = truth if self.settings.ground_truth else None
        self._ownership = ownership
        self._alarms = self.engine.events.subscribe(maxsize=100_000, kinds=("alarm",))
        self._estimates = self.engine.events.subscribe(maxsize=100_000, kinds=("estimate",), vehicles=frozenset())

    def start(self, truth: TruthSource | None = None, ownership: OwnershipSource | None = None) -> None:
        """Attach, then push ``push_hz`` times a second (on the running loop)."""
        self.attach(truth, ownership)
        self._loop = asyncio.get_running_loop()
        self._task = self._loop.create_task(self._run(), name="dashboard")

    def end_streams_threadsafe(self) -> None:
        """End every browser stream soon; callable from a signal handler or another thread (the server is
        shutting down: browsers reconnect to whichever replica answers)."""
        if self._loop is not None and not self._loop.is_closed():
            self._loop.call_soon_threadsafe(self._end_streams)

    def _end_streams(self) -> None:
        for client in list(self.clients):
            self.disconnect(client)

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
        for client in self.clients:
            client.close()
        self.clients = []
        for subscription in (self._alarms, self._estimates):
            if subscription is not None:
                subscription.close()
        self._alarms = self._estimates = None

    async def _run(self) -> None:
        period = 1.0 / self.settings.push_hz
        while True:
            await asyncio.sleep(period)
            try:
                self.tick()
            except Exception:  # a bug in one frame must not end the dashboard
                log.exception("dashboard tick failed")

    # ------------------------------------------------------------------ clients

    def connect(self, view: View, vehicle_id: str | None = None) -> Client:
        """A new browser stream with its first frames queued; raise UnknownVehicle for a vehicle not known."""
        vehicle = self.engine.vehicle(vehicle_id) if view == "vehicle" and vehicle_id is not None else None
        if view == "vehicle" and vehicle is None:
            raise UnknownVehicle("a vehicle view needs a vehicle id")
        client = Client(view, None if vehicle is None else vehicle.id)
        client.send(sse("hello", self._hello(client)))
        client.send(sse("alarms", {"full": True, "upsert": self._latched(), "remove": []}))
        if view == "fleet":
            if not any(c.view == "fleet" for c in self.clients):
                self._fleet_rows = self._rows(self.engine.vehicles.values())
            client.send(sse("fleet", {"full": True, "now_s": time.time(), "rows": list(self._fleet_rows.values())}))
            client.send(sse("ownership", {"full": True, "changes": list(self.ownership)}))
        if vehicle is not None:
            trace = self._trace(vehicle)
            self._backfill(trace, vehicle)
            trace.viewed_mono = time.monotonic()
            client.send(sse("status", self._status(vehicle)))
            client.send(sse("trace", trace.history()))
        self.clients.append(client)
        if vehicle is not None:
            self._refresh_follow()
        return client

    def disconnect(self, client: Client) -> None:
        client.close()
        if client in self.clients:
            self.clients.remove(client)
        if client.vehicle is not None:
            trace = self.traces.get(client.vehicle)
            if trace is not None:
                trace.viewed_mono = time.monotonic()
            self._follow_dirty = True

    def _send(self, frame: bytes, clients: Iterable[Client]) -> None:
        for client in clients:
            client.send(frame)
        if any(c.closed for c in self.clients):
            for client in [c for c in self.clients if c.closed]:
                self.disconnect(client)

    def _hello(self, client: Client) -> dict[str, Any]:
        s = self.settings
        return {
            "view": client.view,
            "vehicle": client.vehicle,
            "replica": self.replica,
            "now_s": time.time(),
            "fleet_hz": s.fleet_hz,
            "push_hz": s.push_hz,
            "plot_hz": s.plot_hz,
            "history_s": s.history_s,
            "fleet_columns": FLEET_COLUMNS,
            "point_columns": POINT_COLUMNS,
            "truth_columns": TRUTH_COLUMNS,
        }

    # ------------------------------------------------------------------ one round

    def tick(self, now: float | None = None) -> None:
        """Drain the fleet's events and the ground truth, then push what changed (``now``: monotonic [s])."""
        started = time.perf_counter()
        self.ticks += 1
        self._drain_estimates()
        self._drain_truth()
        self._push_alarms()
        self._push_ownership()
        if self._follow_dirty:
            self._refresh_follow()
        self._push_traces()
        now = time.monotonic() if now is None else now
        if now >= self._fleet_due:
            self._fleet_due = now + 1.0 / self.settings.fleet_hz
            fleet_started = time.perf_counter()
            self._push_fleet()
            self.fleet_seconds_last = time.perf_counter() - fleet_started
        self.tick_seconds_max = max(self.tick_seconds_max, time.perf_counter() - started)

    def _drain_estimates(self) -> None:
        if self._estimates is None:
            return
        traces = self.traces
        while (event := self._estimates.get_nowait()) is not None:
            trace = traces.get(event.vehicle)
            estimate = event.data
            if trace is None or not isinstance(estimate, Estimate):
                continue
            trace.add_estimate(estimate.t_ns, estimate, event.measured)

    def _drain_truth(self) -> None:
        if self._truth is None:
            return
        for vehicle_id, payload in self._truth.drain_truth():
            trace = self.traces.get(vehicle_id)
            if trace is None:
                continue
            try:
                truth = GroundTruth.model_validate_json(payload)
            except ValueError:
                continue  # not ours to judge: the dashboard only shows truth
            if truth.vehicle == vehicle_id:
                trace.add_truth(truth)

    def _push_alarms(self) -> None:
        if self._alarms is None:
            return
        changed: dict[str, Alarm] = {}
        while (event := self._alarms.get_nowait()) is not None:
            if isinstance(event.data, Alarm):
                changed[event.data.id] = event.data
        if not changed:
            return
        self._follow_dirty = True
        upsert, remove = [], []
        for alarm_id in changed:
            record = self.engine.alarms.get(alarm_id)
            if record is None:
                remove.append(alarm_id)  # cleared and acknowledged: no longer latched
            else:
                upsert.append({**record.to_dict(), "latched": True})
        self._send(sse("alarms", {"full": False, "upsert": upsert, "remove": remove}), self.clients)

    def _push_ownership(self) -> None:
        """The ownership changes announced since the last round, to the fleet views."""
        if self._ownership is None:
            return
        changes = []
        for payload in self._ownership.drain_ownership():
            try:
                changes.append(OwnershipChange.decode(payload).model_dump(mode="json"))
            except ProtocolError as exc:  # not ours to judge: the dashboard only shows them
                log.warning("dashboard: an ownership announcement not shown: %s", exc)
        if not changes:
            return
        self.ownership.extend(changes)
        fleet_clients = [c for c in self.clients if c.view == "fleet"]
        if fleet_clients:
            self._send(sse("ownership", {"full": False, "changes": changes}), fleet_clients)

    def _push_traces(self) -> None:
        for vehicle_id, trace in self.traces.items():
            listeners = [c for c in self.clients if c.vehicle == vehicle_id]
            frame = trace.take_new()
            if frame is not None and listeners:
                self._send(sse("trace", frame), listeners)

    def _push_fleet(self) -> None:
        fleet_clients = [c for c in self.clients if c.view == "fleet"]
        if fleet_clients:
            rows = self._rows(self.engine.vehicles.values())
            changed = [row for vid, row in rows.items() if self._fleet_rows.get(vid) != row]
            removed = [vid for vid in self._fleet_rows if vid not in rows]
            self._fleet_rows = rows
            if changed or removed:
                frame = {"full": False, "now_s": time.time(), "rows": changed, "removed": removed}
                self._send(sse("fleet", frame), fleet_clients)
        for client in [c for c in self.clients if c.vehicle is not None]:
            vehicle = self.engine.vehicles.get(client.vehicle or "")
            if vehicle is not None:
                self._send(sse("status", self._status(vehicle)), [client])

    # ------------------------------------------------------------------ state reads

    def _rows(self, vehicles: Iterable[Vehicle]) -> dict[str, FleetRow]:
        engine = self.engine
        rows: dict[str, FleetRow] = {}
        for vehicle in vehicles:
            vx, _, _, tf, df = vehicle.bank.last_values[vehicle.slot, : len(STATE_COLUMNS)].tolist()
            seen = None if vehicle.last_seen_ns is None else vehicle.last_seen_ns // 1_000_000_000
            rows[vehicle.id] = (
                vehicle.id,
                vehicle.profile,
                engine.level_of(vehicle),
                seen,
                _rounded(vx, 2),
                _rounded(tf, 1),
                _rounded(df, 4),
                vehicle.alive,
                _rounded(vehicle.payload_kg, 1),
            )
        return rows

    def _status(self, vehicle: Vehicle) -> dict[str, Any]:
        alarms = vehicle.bank.spec.alarms
        trace = self.traces.get(vehicle.id)
        return {
            "now_s": time.time(),
            "row": self._rows([vehicle])[vehicle.id],
            "gain_version": vehicle.bank.version,
            "last_seq": vehicle.last_seq if vehicle.last_seq >= 0 else None,
            "thresholds": {
                "torque_warn_nm": alarms.torque_warn_nm,
                "torque_fault_nm": alarms.torque_fault_nm,
                "steer_warn_rad": alarms.steer_warn_rad,
                "steer_fault_rad": alarms.steer_fault_rad,
                "effectiveness_warn": alarms.effectiveness_warn,
                "effectiveness_fault": alarms.effectiveness_fault,
            },
            "effectiveness": vehicle.bank.stage is not None,
            "truth": trace is not None and trace.has_truth,
            "payload_kg": vehicle.payload_kg,
            **self._grade(vehicle),
            **self._judging(vehicle),
        }

    def _judging(self, vehicle: Vehicle) -> dict[str, Any]:
        """Whether the fault alarms judged the vehicle's latest estimate and why not, as GET /vehicles/{id}
        says (faults_judged, unjudged_because)."""
        status = self.engine.vehicle_status(vehicle)
        return {key: status[key] for key in ("faults_judged", "unjudged_because")}

    @staticmethod
    def _grade(vehicle: Vehicle) -> dict[str, float | int | None]:
        """The road grade of the vehicle's last sample that carried one and that sample's seq, None when none has."""
        seq = int(vehicle.bank.grade_seq[vehicle.slot])
        if seq < 0:
            return {"grade_rad": None, "grade_seq": None}
        return {"grade_rad": float(vehicle.bank.grade_rad[vehicle.slot]), "grade_seq": seq}

    def _latched(self) -> list[dict[str, Any]]:
        records = sorted(self.engine.alarms.latched(), key=lambda r: r.updated_t_ns, reverse=True)
        return [{**r.to_dict(), "latched": True} for r in records]

    # ------------------------------------------------------------------ following

    def _trace(self, vehicle: Vehicle) -> Trace:
        trace = self.traces.get(vehicle.id)
        if trace is None:
            trace = self.traces[vehicle.id] = Trace(vehicle.id, self._period_ns, self._maxlen)
        return trace

    def _backfill(self, trace: Trace, vehicle: Vehicle) -> None:
        """Put the estimates the engine keeps (its last ``ingest.history_samples``) before the trace's first
        point: a vehicle opened for the first time shows its recent past at once. Done when a browser
        opens the vehicle, not when it is followed, so following many vehicles costs nothing up front."""
        first_ns = round(trace.points[0][0] * 1e9) if trace.points and trace.points[0][0] is not None else None
        older = Trace(vehicle.id, self._period_ns, self._maxlen)
        for row in self.engine.estimate_history(vehicle, vehicle.bank.history_samples):
            if first_ns is not None and row.t_ns >= first_ns - self._period_ns // 2:
                break
            older.add_estimate(row.t_ns, row, None)
        trace.prepend(older)

    def _refresh_follow(self) -> None:
        """Follow the viewed vehicles, then those with latched fault or out-of-domain alarms, then the recently
        viewed. A latched STALE or rejected-input alarm alone does not make a vehicle worth a plot history:
        following costs an event per sample, and a fleet that once went silent would keep follow_max
        vehicles followed for nothing."""
        self._follow_dirty = False
        vehicles = self.engine.vehicles
        follow: dict[str, None] = dict.fromkeys(c.vehicle for c in self.clients if c.vehicle in vehicles)
        latched = sorted(
            (r for r in self.engine.alarms.latched() if r.kind in _FAULT_KINDS), key=lambda r: -r.updated_t_ns
        )
        recent = sorted((t for t in self.traces.values() if t.viewed_mono > 0), key=lambda t: -t.viewed_mono)
        for vehicle_id in [r.vehicle for r in latched] + [t.vehicle for t in recent]:
            if len(follow) >= self.settings.follow_max:
                break
            if vehicle_id in vehicles:
                follow.setdefault(vehicle_id)
        wanted = frozenset(follow)
        for vehicle_id in [v for v in self.traces if v not in wanted]:
            del self.traces[vehicle_id]
        for vehicle_id in follow:
            self._trace(vehicles[vehicle_id])
        if wanted == self.followed:
            return
        self.followed = wanted
        if self._estimates is not None:
            self._estimates.follow(wanted)
        if self._truth is not None:
            try:
                self._truth.follow_truth(wanted)
            except Exception as exc:  # the plots go on without truth
                log.warning("dashboard: cannot subscribe to ground truth: %s", exc)
