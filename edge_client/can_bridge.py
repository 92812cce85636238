"""A vehicle's CAN bus live: its frames in (python-can, decoded with its DBC by cantools), the service's measurements
out, on the 10 ms grid.

The same mapping file as `agv-fe can2csv` (edge_client/can_log.py) names, for each of the four signals, the DBC
message and signal and the affine map to the protocol's unit; when it names the road's grade too, the grade is held
like them and each measurement carries it (``grade_rad``). :class:`CanSource` listens to a python-can bus
(SocketCAN ``can0`` on a vehicle; any python-can interface: ``pcan``, ``kvaser``, ``vector``, ``slcan``,
``virtual``...) with a :class:`can.Notifier`, decodes each mapped frame and keeps the latest value of each column
(:class:`~edge_client.grid.LiveSource`, the grid rule of edge_client/grid.py); the 100 Hz publisher
(edge_client/publisher.py) samples it at each tick. A tick at which a column is older than the mapping's
``max_age_s`` sends nothing and is counted by column. Frames of other messages, frames that do not decode and
non-finite values are counted, never fatal.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from edge_client.can_log import CanMapping, CanSignal, decode_frame, resolve
from edge_client.grid import LiveSource


@dataclass
class CanBridgeStats:
    """What the bridge read from the bus and refused besides what :class:`~edge_client.grid.LiveSource` counts."""

    frames: int = 0
    other: int = 0
    undecodable: int = 0
    errors: int = 0


class CanSource(LiveSource):
    """One vehicle's mapped CAN signals as a one-vehicle sample source (module docstring).

    ``bus`` is an open python-can bus; the source reads it on python-can's notifier thread until :meth:`close`
    (which stops the notifier, not the bus: its owner shuts it down).
    """

    def __init__(
        self,
        bus: Any,
        database: Any,
        mapping: CanMapping,
        vehicle_id: str,
        *,
        dbc_name: str = "DBC",
        wait_s: float = 30.0,
        clock: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        import can

        super().__init__(vehicle_id, mapping.sample_period_s, mapping.max_age_s, wait_s, clock, mapping.signals())
        self.mapping = mapping
        self.database = database
        self.wanted: dict[int, list[tuple[str, CanSignal]]] = resolve(database, mapping, dbc_name)
        self.stats = CanBridgeStats()
        self._lock = threading.Lock()
        self._notifier = can.Notifier(bus, [self._on_frame], timeout=0.1)
        self._notifier.add_listener(_ErrorCounter(self))

    def _on_frame(self, frame: Any) -> None:
        # python-can's notifier thread: decode, check, hold; never raise
        with self._lock:
            self.stats.frames += 1
        if frame.is_error_frame or frame.is_remote_frame:
            with self._lock:
                self.stats.other += 1
            return
        columns = self.wanted.get(frame.arbitration_id)
        if columns is None:
            with self._lock:
                self.stats.other += 1
            return
        decoded = decode_frame(self.database, frame, columns)
        if decoded is None:
            with self._lock:
                self.stats.undecodable += 1
            return
        self.received(decoded)

    def describe_missing(self, columns: tuple[str, ...]) -> str:
        signals = self.mapping.signals()
        return ", ".join(f"{c} ({signals[c].message}.{signals[c].signal})" for c in columns)

    def describe(self) -> list[str]:
        with self._lock, self.lock:
            stats = self.stats
            return [
                f"read {stats.frames} frames: used {self.used_text()}; {stats.other} of other messages; refused "
                f"{stats.undecodable} undecodable, {self.non_finite} not finite; bus errors {stats.errors}",
                self.describe_grid(),
            ]

    def close(self) -> None:
        self._notifier.stop(timeout=1.0)

    def __enter__(self) -> CanSource:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()


class _ErrorCounter:
    """A python-can listener that counts the bus's read errors (the notifier calls ``on_error``; handled, it keeps
    reading) instead of letting the notifier thread die."""

    def __init__(self, source: CanSource) -> None:
        self.source = source

    def __call__(self, frame: Any) -> None:  # frames go to CanSource._on_frame
        return None

    def on_error(self, exc: Exception) -> None:
        with self.source._lock:
            self.source.stats.errors += 1
