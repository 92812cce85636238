"""Each vehicle's estimates put on its own keys by a process of its own (setting ``zenoh.vehicle_publisher =
'process'``), fed by the replica's fleet stream.

At 1,000 vehicles that subscribe to their own estimate keys the service puts 100,000 messages a second, one
Python-level ``put`` each. On a thread of the service (:class:`~service.transport.VehicleEstimates`, the
default) those puts share the interpreter lock with the ingest loop: the service cannot use more than one core,
and both wait on each other. In a process of its own the fan-out runs beside the service on another core: the
child is a Zenoh client of the same router that subscribes to the replica's fleet stream
(:func:`~service.protocol.fleet_estimates_key`, one message per tick, which the service publishes anyway) and
puts each estimate on its vehicle's keys, JSON and binary, with the same :class:`VehicleEstimates` (the same
documents, the same matching listeners with ``zenoh.vehicle_estimates = 'subscribed'``). An estimate takes one
more hop through the router. The child's counters reach the service's /metrics through shared memory.

The child stops when the service closes it, and on its own when the service process is gone.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import time
from typing import Any

import orjson

from service.protocol import EstimateBatch, ProtocolError, fleet_estimates_key
from service.settings import ZenohSettings
from service.transport import (
    ENCODING_NAMES,
    TransportError,
    VehicleEstimates,
    estimate_congestion,
    open_session,
    subscribe_payloads,
)

log = logging.getLogger("agv_fe.service.vehicle_fanout")

#: How long the service waits for the child to subscribe to its fleet stream [s] (a spawned interpreter's imports).
START_TIMEOUT_S = 60.0
#: How often the child copies its counters to the shared memory the service reads [s].
COUNTERS_EVERY_S = 0.2
#: The shared counters, in order, then two flags: the child subscribed, the service asks it to stop. Plain shared
#: integers, no lock: a child killed while holding a lock (of a multiprocessing Event) would hang the service's close.
_COUNTERS = (*ENCODING_NAMES.values(), "dropped", "errors", "unmatched")
_READY, _STOP = len(_COUNTERS), len(_COUNTERS) + 1


def fleet_batches(payload: bytes) -> list[EstimateBatch]:
    """The batches of a fleet-stream message (:class:`~service.protocol.FleetEstimates`) of this service."""
    try:
        message = orjson.loads(payload)
        if message.get("v") != 1:
            raise ProtocolError(f"fleet estimates of version {message.get('v')!r}: this side reads version 1")
        return [EstimateBatch.from_group(group) for group in message["groups"]]
    except (orjson.JSONDecodeError, KeyError, TypeError, ValueError, AttributeError) as exc:
        raise ProtocolError(f"not a fleet estimates message: {exc}") from exc


def fanout_main(zenoh_settings: dict[str, Any], replica_id: str, counters: Any) -> None:
    """The child: a client session on the service's endpoint, the fleet stream in, the vehicle keys out."""
    settings = ZenohSettings.model_validate(zenoh_settings)
    parent = os.getppid()
    session = open_session(
        "client",
        settings.endpoint,
        settings.connect_timeout_ms,
        config_file=settings.config_file,
        credentials_file=settings.credentials_file,
    )
    congestion = estimate_congestion(settings.estimate_congestion)
    vehicles = VehicleEstimates(session, settings.prefix, congestion, settings.vehicle_estimates == "subscribed")
    unreadable = [0]

    def arrived(payload: bytes) -> None:
        try:
            vehicles.submit(fleet_batches(payload))
        except ProtocolError as exc:
            unreadable[0] += 1
            log.error("vehicle estimates: %s", exc)

    def publish_counters() -> None:
        counts = [*(vehicles.sent[name] for name in ENCODING_NAMES.values()), vehicles.dropped]
        counters[: len(_COUNTERS)] = [*counts, vehicles.errors + unreadable[0], vehicles.unmatched]

    # the callback runs on Zenoh's receiving thread and only queues the tick
    sub = subscribe_payloads(session, fleet_estimates_key(replica_id, settings.prefix), arrived)
    counters[_READY] = 1
    try:
        while not counters[_STOP] and os.getppid() == parent:
            time.sleep(COUNTERS_EVERY_S)
            publish_counters()
    finally:
        sub.undeclare()
        vehicles.close()
        publish_counters()
        session.close()  # type: ignore[no-untyped-call]


class VehicleFanout:
    """The service's side of the child process: start, counters (as :class:`VehicleEstimates` has them), close.

    :meth:`submit` does nothing: the tick's estimates reach the child in the fleet stream."""

    def __init__(self, settings: ZenohSettings, replica_id: str) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._counters = ctx.Array("q", len(_COUNTERS) + 2, lock=False)
        self._process = ctx.Process(
            target=fanout_main,
            args=(settings.model_dump(mode="json"), replica_id, self._counters),
            name="agv-fe-vehicle-estimates",
            daemon=True,
        )

    def start(self, timeout_s: float = START_TIMEOUT_S) -> VehicleFanout:
        """Start the child and wait until it subscribes; raise :class:`TransportError` if it cannot."""
        self._process.start()
        deadline = time.monotonic() + timeout_s
        while not self._counters[_READY]:
            time.sleep(0.05)
            if not self._process.is_alive() or time.monotonic() > deadline:
                self.close()
                raise TransportError(
                    f"the vehicle estimate process did not subscribe to the fleet stream within {timeout_s:g} s "
                    f"(exit code {self._process.exitcode})"
                )
        return self

    @property
    def alive(self) -> bool:
        return self._process.is_alive()

    def submit(self, batches: Any) -> None:
        """Nothing to do: the child takes the tick from the fleet stream."""

    @property
    def sent(self) -> dict[str, int]:
        return {name: int(self._counters[k]) for k, name in enumerate(ENCODING_NAMES.values())}

    @property
    def dropped(self) -> int:
        return int(self._counters[_COUNTERS.index("dropped")])

    @property
    def errors(self) -> int:
        return int(self._counters[_COUNTERS.index("errors")])

    @property
    def unmatched(self) -> int:
        return int(self._counters[_COUNTERS.index("unmatched")])

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop the child: it publishes what it holds, undeclares its keys and closes its session."""
        self._counters[_STOP] = 1
        if self._process.pid is None:
            return
        self._process.join(timeout_s)
        if self._process.is_alive():
            log.warning("the vehicle estimate process did not stop within %g s: terminated", timeout_s)
            self._process.terminate()
            self._process.join(timeout_s)
