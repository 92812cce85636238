"""A terminal dashboard of the fleet: every vehicle's level, speed, estimated faults and alarms.

It needs nothing but a zenoh router: it subscribes to all estimates and alarms
(:func:`agv_protocol.wire.fleet_selector`) and to the vehicles' liveliness
tokens, and redraws a rich table a few times a second. :class:`DashboardModel`
is the table's state, fed by decoded messages; it renders to text for tests
and for non-terminal output. Only the newest estimate of each vehicle is
decoded at each refresh, so a fleet at 100 Hz costs one decode per vehicle per
refresh, not one per message.
"""

from __future__ import annotations

import io
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime
from typing import TYPE_CHECKING

from rich.console import Console, Group, RenderableType
from rich.live import Live
from rich.table import Table
from rich.text import Text

from agv_protocol.wire import Alarm, Estimate, ProtocolError, fleet_selector, parse_vehicle_key
from edge_client.pacing import DeadlinePacer
from edge_client.transport import ChannelSubscription, Received

if TYPE_CHECKING:
    import zenoh

#: Display order of levels, most severe first; "-" is a vehicle without an estimate yet.
LEVEL_ORDER = {"FAULT": 0, "STALE": 1, "WARN": 2, "OK": 3, "-": 4}
LEVEL_STYLE = {"FAULT": "bold red", "STALE": "magenta", "WARN": "yellow", "OK": "green", "-": "dim"}
#: An estimate older than this makes the dashboard show the vehicle as STALE [s].
STALE_AFTER_S = 2.0
SHORT_KIND = {
    "torque_fault": "torque",
    "steer_fault": "steer",
    "out_of_domain": "domain",
    "stale": "stale",
    "unserved": "unserved",
    "rejected_inputs": "inputs",
    "sequence_rejected": "sequence",
}


@dataclass
class VehicleRow:
    """What the dashboard knows of one vehicle."""

    vehicle_id: str
    alive: bool | None = None
    estimate: Estimate | None = None
    estimate_received_ns: int = 0
    pending_estimate: bytes | None = None
    active_alarms: dict[str, Alarm] = field(default_factory=dict)
    alarms_raised: int = 0

    def level(self, now_ns: int) -> str:
        if self.estimate is None:
            return "-"
        if now_ns - self.estimate_received_ns > STALE_AFTER_S * 1e9:
            return "STALE"
        return self.estimate.level


class DashboardModel:
    """The dashboard's state: vehicles by id, fed by raw or decoded messages."""

    def __init__(self, clock: Callable[[], int] = time.monotonic_ns) -> None:
        self._clock = clock
        self.vehicles: dict[str, VehicleRow] = {}
        self.estimates_received = 0
        self.alarms_received = 0
        self.bad_messages = 0
        self._rate_window: tuple[int, int] = (clock(), 0)
        self.estimate_rate_hz = 0.0

    def _row(self, vehicle_id: str) -> VehicleRow:
        row = self.vehicles.get(vehicle_id)
        if row is None:
            row = self.vehicles[vehicle_id] = VehicleRow(vehicle_id)
        return row

    def _vehicle_of(self, key: str) -> str | None:
        try:
            return parse_vehicle_key(key)[0]
        except ProtocolError:
            self.bad_messages += 1
            return None

    def on_estimate(self, rx: Received) -> None:
        """Keep the newest raw estimate; it is decoded in :meth:`settle`."""
        vehicle_id = self._vehicle_of(rx.key)
        if vehicle_id is None:
            return
        row = self._row(vehicle_id)
        row.pending_estimate = rx.payload
        row.estimate_received_ns = rx.received_ns
        self.estimates_received += 1

    def on_alarm(self, rx: Received) -> None:
        vehicle_id = self._vehicle_of(rx.key)
        if vehicle_id is None:
            return
        alarm = rx.decode(Alarm.decode)
        if alarm is None:
            self.bad_messages += 1
            return
        self.apply_alarm(alarm)

    def apply_alarm(self, alarm: Alarm) -> None:
        row = self._row(alarm.vehicle)
        self.alarms_received += 1
        if alarm.state == "cleared":
            row.active_alarms.pop(alarm.id, None)
        else:
            if alarm.state == "raised" and alarm.id not in row.active_alarms:
                row.alarms_raised += 1
            row.active_alarms[alarm.id] = alarm

    def on_alive(self, rx: Received) -> None:
        vehicle_id = self._vehicle_of(rx.key)
        if vehicle_id is not None:
            self._row(vehicle_id).alive = rx.put

    def apply_estimate(self, estimate: Estimate, received_ns: int | None = None) -> None:
        row = self._row(estimate.vehicle)
        row.estimate = estimate
        row.pending_estimate = None
        row.estimate_received_ns = self._clock() if received_ns is None else received_ns
        self.estimates_received += 1

    def settle(self) -> None:
        """Decode each vehicle's newest estimate and update the message rate."""
        for row in self.vehicles.values():
            if row.pending_estimate is not None:
                try:
                    row.estimate = Estimate.decode(row.pending_estimate)
                except ProtocolError:
                    self.bad_messages += 1
                row.pending_estimate = None
        now = self._clock()
        since_ns, count = self._rate_window
        if now - since_ns >= 1e9:
            self.estimate_rate_hz = (self.estimates_received - count) / ((now - since_ns) / 1e9)
            self._rate_window = (now, self.estimates_received)

    def rows(self) -> list[VehicleRow]:
        """Vehicles, most severe level first, then by id."""
        now = self._clock()
        return sorted(self.vehicles.values(), key=lambda r: (LEVEL_ORDER.get(r.level(now), 5), r.vehicle_id))

    def level_counts(self) -> dict[str, int]:
        now = self._clock()
        counts = dict.fromkeys(LEVEL_ORDER, 0)
        for row in self.vehicles.values():
            counts[row.level(now)] = counts.get(row.level(now), 0) + 1
        return counts

    def renderable(self, max_rows: int | None = None) -> RenderableType:
        """Header line plus the vehicle table (at most ``max_rows`` rows, most severe first)."""
        now = self._clock()
        counts = self.level_counts()
        alive = sum(1 for r in self.vehicles.values() if r.alive)
        summary = ", ".join(f"{n} {level}" for level, n in counts.items() if n and level != "-")
        header = Text.assemble(
            ("AGV fleet ", "bold"),
            f"{datetime.now().strftime('%H:%M:%S')}  {len(self.vehicles)} vehicles, {alive} alive",
            f"  {summary}" if summary else "",
            f"  {self.estimate_rate_hz:.0f} est/s",
        )
        table = Table(expand=False, pad_edge=False, box=None, header_style="bold")
        table.add_column("vehicle", no_wrap=True, max_width=16)
        table.add_column("level", no_wrap=True)
        table.add_column("v_x m/s", justify="right", no_wrap=True)
        table.add_column("v_y est", justify="right", no_wrap=True)
        table.add_column("T_f est N m", justify="right", no_wrap=True)
        table.add_column("δ_f est rad", justify="right", no_wrap=True)
        table.add_column("alarms", no_wrap=True, max_width=18, overflow="ellipsis")
        table.add_column("age", justify="right", no_wrap=True)
        rows = self.rows()
        shown = rows if max_rows is None else rows[: max(max_rows, 0)]
        for row in shown:
            level = row.level(now)
            e = row.estimate
            alarms = " ".join(
                SHORT_KIND.get(a.kind, a.kind) + ("(ack)" if a.state == "acknowledged" else "")
                for a in sorted(row.active_alarms.values(), key=lambda a: a.kind)
            )
            vehicle = Text(row.vehicle_id, style="dim" if row.alive is False else "")
            age = f"{(now - row.estimate_received_ns) / 1e9:.1f}s" if e is not None else "-"
            table.add_row(
                vehicle,
                Text(level, style=LEVEL_STYLE.get(level, "")),
                f"{e.vx:.1f}" if e else "-",
                f"{e.vy:+.2f}" if e else "-",
                f"{e.torque_fault:+.1f}" if e else "-",
                f"{e.steer_fault:+.4f}" if e else "-",
                Text(alarms or "-", style="red" if row.active_alarms else "dim"),
                age,
            )
        parts: list[RenderableType] = [header, table]
        if len(shown) < len(rows):
            parts.append(Text(f"... and {len(rows) - len(shown)} more vehicles", style="dim"))
        return Group(*parts)

    def render_text(self, width: int = 80, max_rows: int | None = None) -> str:
        """The dashboard as plain text, ``width`` columns wide."""
        console = Console(width=width, record=True, color_system=None, file=io.StringIO(), force_terminal=False)
        console.print(self.renderable(max_rows))
        return console.export_text()


class FleetSubscriptions:
    """The dashboard's subscriptions on one session: estimates (ring), alarms (FIFO), liveliness."""

    def __init__(self, session: zenoh.Session, prefix: str) -> None:
        self._subs: list[ChannelSubscription] = []
        try:
            self.estimates = self._add(
                ChannelSubscription(session, fleet_selector("estimate", prefix), 100_000, ring=True)
            )
            self.alarms = self._add(ChannelSubscription(session, fleet_selector("alarm", prefix), 20_000))
            self.alive = self._add(
                ChannelSubscription(session, fleet_selector("alive", prefix), 20_000, liveliness=True)
            )
        except BaseException:
            self.close()
            raise

    def _add(self, sub: ChannelSubscription) -> ChannelSubscription:
        self._subs.append(sub)
        return sub

    def feed(self, model: DashboardModel) -> None:
        """Move everything received so far into ``model``."""
        for rx in self.alive.drain():
            model.on_alive(rx)
        for rx in self.alarms.drain():
            model.on_alarm(rx)
        for rx in self.estimates.drain():
            model.on_estimate(rx)
        model.settle()

    def close(self) -> None:
        for sub in self._subs:
            sub.close()
        self._subs.clear()


def run_dashboard(
    session: zenoh.Session,
    prefix: str,
    *,
    console: Console | None = None,
    refresh_hz: float = 4.0,
    duration_s: float | None = None,
    stop: threading.Event | None = None,
) -> DashboardModel:
    """Show the live table until ``duration_s`` passes or ``stop`` is set; return the final model.

    On a terminal the table is redrawn in place ``refresh_hz`` times a second;
    otherwise only the final table is printed.
    """
    if not 0.5 <= refresh_hz <= 50:
        raise ValueError(f"refresh_hz must be in [0.5, 50], got {refresh_hz}")
    console = console or Console()
    model = DashboardModel()
    subscriptions = FleetSubscriptions(session, prefix)
    pacer = DeadlinePacer(1.0 / refresh_hz)
    end_ns = None if duration_s is None else time.monotonic_ns() + round(duration_s * 1e9)

    def max_rows() -> int | None:
        return max(console.size.height - 5, 3) if console.is_terminal else None

    def running() -> bool:
        return not (stop is not None and stop.is_set()) and (end_ns is None or time.monotonic_ns() < end_ns)

    try:
        if console.is_terminal:
            with Live(console=console, auto_refresh=False, transient=False) as live:
                while running():
                    pacer.wait()
                    subscriptions.feed(model)
                    live.update(model.renderable(max_rows()), refresh=True)
        else:
            while running():
                pacer.wait()
                subscriptions.feed(model)
            console.print(model.renderable())
    finally:
        subscriptions.close()
    return model
