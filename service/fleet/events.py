"""The fleet's subscription hook: an in-process broadcast of estimate, alarm and vehicle events.

A dashboard (SSE or WebSocket) calls :meth:`EventBus.subscribe` and iterates
the returned :class:`Subscription`. Publishing never blocks and never raises:
a subscriber that falls behind loses its oldest events and sees the count in
``Subscription.dropped``. Estimate events are only built while someone
listens (:attr:`EventBus.has_subscribers`), so the hook costs nothing
otherwise. Everything runs on the asyncio loop that owns the fleet.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Any, Literal

from service.protocol import Alarm, Estimate

EventKind = Literal["estimate", "alarm", "vehicle"]


@dataclass(frozen=True, slots=True)
class FleetEvent:
    """One event: ``estimate`` carries an :class:`Estimate`, ``alarm`` an :class:`Alarm`,
    ``vehicle`` a status dict (registered, stale, alive, profile changed)."""

    kind: EventKind
    vehicle: str
    data: Estimate | Alarm | dict[str, Any]


class Subscription:
    """A bounded queue of events for one listener; iterate it with ``async for``."""

    def __init__(self, bus: EventBus, maxsize: int, kinds: frozenset[EventKind]) -> None:
        self._bus = bus
        self._queue: asyncio.Queue[FleetEvent] = asyncio.Queue(maxsize)
        self.kinds = kinds
        self.dropped = 0

    def _offer(self, event: FleetEvent) -> None:
        if event.kind not in self.kinds:
            return
        if self._queue.full():
            self._queue.get_nowait()
            self.dropped += 1
        self._queue.put_nowait(event)

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

    @property
    def has_subscribers(self) -> bool:
        return bool(self._subscriptions)

    def wants(self, kind: EventKind) -> bool:
        return any(kind in s.kinds for s in self._subscriptions)

    def subscribe(
        self, maxsize: int = 10_000, kinds: tuple[EventKind, ...] = ("estimate", "alarm", "vehicle")
    ) -> Subscription:
        subscription = Subscription(self, maxsize, frozenset(kinds))
        self._subscriptions.append(subscription)
        return subscription

    def _unsubscribe(self, subscription: Subscription) -> None:
        if subscription in self._subscriptions:
            self._subscriptions.remove(subscription)

    def publish(self, event: FleetEvent) -> None:
        for subscription in self._subscriptions:
            subscription._offer(event)
