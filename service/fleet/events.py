"""The fleet's subscription hook: an in-process broadcast of estimate, alarm and vehicle events.

A dashboard (SSE or WebSocket) calls :meth:`EventBus.subscribe` and iterates
the returned :class:`Subscription`. Publishing never blocks and never raises:
a subscriber that falls behind loses its oldest events, counted by kind in
:attr:`EventBus.dropped` (``agv_fe_events_dropped_total`` on /metrics).
Estimate events are only built while someone listens
(:attr:`EventBus.has_subscribers`), so the hook costs nothing otherwise; a
subscription may follow only some vehicles (``vehicles``), and then only their
estimate events are built (:meth:`EventBus.audience`).
Everything runs on the asyncio loop that owns the fleet.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Any, Literal, get_args

from agv_protocol.wire import Alarm, Estimate

EventKind = Literal["estimate", "alarm", "vehicle"]
EVENT_KINDS: tuple[EventKind, ...] = get_args(EventKind)


@dataclass(frozen=True, slots=True)
class FleetEvent:
    """One event: ``estimate`` carries an :class:`Estimate`, ``alarm`` an :class:`Alarm`,
    ``vehicle`` a status dict (registered, stale, alive, profile changed).

    An estimate event also carries the measurement it answers, ``measured`` =
    (v_x [m/s], r [rad/s], T_d [N m], delta_d [rad]).
    """

    kind: EventKind
    vehicle: str
    data: Estimate | Alarm | dict[str, Any]
    measured: tuple[float, float, float, float] | None = None


class Subscription:
    """A bounded queue of events for one listener; iterate it with ``async for``."""

    def __init__(
        self, bus: EventBus, maxsize: int, kinds: frozenset[EventKind], vehicles: frozenset[str] | None = None
    ) -> None:
        self._bus = bus
        self._queue: asyncio.Queue[FleetEvent] = asyncio.Queue(maxsize)
        self.kinds = kinds
        #: only events of these vehicles (None: every vehicle); change it with :meth:`follow`
        self.vehicles = vehicles

    def follow(self, vehicles: frozenset[str] | None) -> None:
        """From now on take only the events of ``vehicles`` (None: of every vehicle)."""
        self.vehicles = vehicles

    def _offer(self, event: FleetEvent) -> FleetEvent | None:
        """Queue ``event`` if this subscription takes it; when the queue is full, the oldest event makes room and
        is returned (it is lost to this listener)."""
        if event.kind not in self.kinds:
            return None
        if self.vehicles is not None and event.vehicle not in self.vehicles:
            return None
        lost = self._queue.get_nowait() if self._queue.full() else None
        self._queue.put_nowait(event)
        return lost

    async def get(self) -> FleetEvent:
        return await self._queue.get()

    def get_nowait(self) -> FleetEvent | None:
        try:
            return self._queue.get_nowait()
        except asyncio.QueueEmpty:
            return None

    def close(self) -> None:
        self._bus._unsubscribe(self)

    def __aiter__(self) -> AsyncIterator[FleetEvent]:
        return self._iterate()

    async def _iterate(self) -> AsyncIterator[FleetEvent]:
        while True:
            yield await self._queue.get()

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()


class EventBus:
    """Fan-out of fleet events to any number of subscriptions."""

    def __init__(self) -> None:
        self._subscriptions: list[Subscription] = []
        #: events a subscription fell behind on and lost (its oldest, to make room), by kind; each subscription
        #: that loses an event counts it, and closed subscriptions' losses stay counted
        self.dropped: dict[EventKind, int] = dict.fromkeys(EVENT_KINDS, 0)

    @property
    def has_subscribers(self) -> bool:
        return bool(self._subscriptions)

    def wants(self, kind: EventKind) -> bool:
        return any(kind in s.kinds for s in self._subscriptions)

    def audience(self, kind: EventKind) -> frozenset[str] | None:
        """The vehicles whose ``kind`` events some subscription takes; None when one takes every vehicle's."""
        wanted: set[str] = set()
        for subscription in self._subscriptions:
            if kind in subscription.kinds:
                if subscription.vehicles is None:
                    return None
                wanted |= subscription.vehicles
        return frozenset(wanted)

    def subscribe(
        self,
        maxsize: int = 10_000,
        kinds: tuple[EventKind, ...] = ("estimate", "alarm", "vehicle"),
        vehicles: frozenset[str] | None = None,
    ) -> Subscription:
        subscription = Subscription(self, maxsize, frozenset(kinds), vehicles)
        self._subscriptions.append(subscription)
        return subscription

    def _unsubscribe(self, subscription: Subscription) -> None:
        if subscription in self._subscriptions:
            self._subscriptions.remove(subscription)

    def publish(self, event: FleetEvent) -> None:
        for subscription in self._subscriptions:
            if (lost := subscription._offer(event)) is not None:
                self.dropped[lost.kind] += 1
