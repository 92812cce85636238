"""Each vehicle's estimates put on its own keys by a process of its own (setting ``zenoh.vehicle_publisher =
'process'``), fed by the replica's fleet stream.

At 1,000 vehicles that subscribe to their own estimate keys the service puts 100,000 messages a second, one
Python-level ``put`` each. On a thread of the service (:class:`~service.transport.VehicleEstimates`, the
default) those puts share the interpreter lock with the ingest loop: the service cannot use more than one core,
and both wait on each other. In a process of its own the fan-out runs beside the service on another core: the
child is a Zenoh client of the same router that subscribes to the replica's fleet stream
(:func:`~agv_protocol.wire.fleet_estimates_key`, one message per tick, which the service publishes anyway) and
puts each estimate on its vehicle's keys, JSON and binary, with the same :class:`VehicleEstimates` (the same
documents, the same matching listeners with ``zenoh.vehicle_estimates = 'subscribed'``). An estimate takes one
more hop through the router. The child's counters reach the service's /metrics through shared memory, and it
stops as every such child does (service/fleet_child.py).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from agv_protocol.wire import EstimateBatch
from service.fleet_child import POLL_S, FleetStreamChild, child_session, fleet_key, serve_fleet_stream
from service.metrics import END_TO_END_BUCKETS_S, Histogram
from service.settings import ZenohSettings
from service.transport import ENCODING_NAMES, VehicleEstimates, estimate_congestion

#: The shared counters, in order (service/fleet_child.py adds the two flags): the publisher's counters, its
#: backlog [us], then its delay histogram: a count per bucket (the last above every bound) and the sum [s] (a
#: float64's bits: years-old time stamps would overflow any integer unit).
_COUNTERS = (*ENCODING_NAMES.values(), "dropped", "errors", "unmatched", "backlog_us")
_DELAY_AT = len(_COUNTERS)
_DELAY_SLOTS = len(END_TO_END_BUCKETS_S) + 2


def fanout_main(zenoh_settings: dict[str, Any], replica_id: str, child_dir: str | None, counters: Any) -> None:
    """The child: a client session of the service's router (fleet_child.child_session), the fleet stream in, the
    vehicle keys out."""
    settings, session = child_session(zenoh_settings, child_dir)
    congestion = estimate_congestion(settings.estimate_congestion)
    vehicles = VehicleEstimates(session, settings.prefix, congestion, settings.vehicle_estimates == "subscribed")
    unreadable = [0]

    def publish_counters(unread: int) -> None:
        unreadable[0] = unread
        counts = [*(vehicles.sent[name] for name in ENCODING_NAMES.values()), vehicles.dropped]
        backlog_us = round(vehicles.backlog_s * 1e6)
        counters[:_DELAY_AT] = [*counts, vehicles.errors + unread, vehicles.unmatched, backlog_us]
        delay = vehicles.delay
        total_bits = int(np.float64(delay.sum).view(np.int64))
        counters[_DELAY_AT : _DELAY_AT + _DELAY_SLOTS] = [*delay.counts.tolist(), total_bits]

    def every_poll(unread: int) -> None:
        time.sleep(POLL_S)
        publish_counters(unread)

    try:  # the messages' batches are queued on Zenoh's receiving thread, put by the publisher's
        serve_fleet_stream(session, fleet_key(replica_id, settings), counters, vehicles.submit, every_poll)
    finally:
        vehicles.close()
        publish_counters(unreadable[0])
        session.close()  # type: ignore[no-untyped-call]


class VehicleFanout(FleetStreamChild):
    """The service's side of the child process: start, counters (as :class:`VehicleEstimates` has them), close.

    :meth:`submit` does nothing: the tick's estimates reach the child in the fleet stream."""

    def __init__(self, settings: ZenohSettings, replica_id: str, child_dir: str | None = None) -> None:
        """``child_dir``: where the child connects (fleet_child.child_session)."""
        args = (settings.model_dump(mode="json"), replica_id, child_dir)
        super().__init__(fanout_main, args, _DELAY_AT + _DELAY_SLOTS, "vehicle estimate")

    def start(self) -> VehicleFanout:
        """Start the child and wait until it subscribes; raise TransportError if it cannot."""
        self.start_child()
        return self

    def submit(self, batches: Sequence[EstimateBatch]) -> None:
        """Nothing to do: the child takes the tick from the fleet stream."""

    @property
    def sent(self) -> dict[str, int]:
        return {name: int(self.shared[k]) for k, name in enumerate(ENCODING_NAMES.values())}

    @property
    def dropped(self) -> int:
        return int(self.shared[_COUNTERS.index("dropped")])

    @property
    def errors(self) -> int:
        return int(self.shared[_COUNTERS.index("errors")])

    @property
    def unmatched(self) -> int:
        return int(self.shared[_COUNTERS.index("unmatched")])

    @property
    def delay(self) -> Histogram:
        """The child's delay histogram (VehicleEstimates.delay) as of its last poll."""
        histogram = Histogram(END_TO_END_BUCKETS_S)
        slots = self.shared[_DELAY_AT : _DELAY_AT + _DELAY_SLOTS]
        histogram.counts[:] = slots[:-1]
        histogram.count = int(histogram.counts.sum())
        histogram.sum = float(np.int64(slots[-1]).view(np.float64))
        return histogram

    @property
    def backlog_s(self) -> float:
        return self.shared[_COUNTERS.index("backlog_us")] * 1e-6
