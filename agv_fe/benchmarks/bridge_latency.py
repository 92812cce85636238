"""What the live bridges' latency benchmarks (ros2_bridge, can_bridge) share: their router, and how the latency of
each sample is summarised.

A vehicle numbers its samples in one of its signals; the bridge puts them on the 10 ms grid; a subscriber receives
the measurements. For each sample put while the bridge ran, from the put of its last message or frame to the
receipt of the first measurement carrying it, on the machine's wall clock:

* grid hold: from the put to the bridge's tick that sampled it (the measurement's nominal time stamp): the wait
  for the next grid point, between 0 and 10 ms by design;
* after the tick: from that tick to the receipt: the tick's lateness, the sampling, encoding and put, and the
  hops bridge -> router -> subscriber;
* total: the two together, what the bridge adds to a vehicle that would publish the protocol itself at the instant
  of its last message.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np


@dataclass(frozen=True)
class BridgeLatency:
    samples: int
    carried: int
    measurements: int
    total_p50_ms: float
    total_p99_ms: float
    total_max_ms: float
    hold_p50_ms: float
    hold_p99_ms: float
    after_tick_p50_ms: float
    after_tick_p99_ms: float
    decode_us: float
    bridge_cpu_fraction: float
    run_s: float


def router_session(port: int) -> Any:
    """A zenoh router on tcp/127.0.0.1:``port``, multicast scouting off: the bridge and the subscriber meet there."""
    import zenoh

    config = zenoh.Config()
    config.insert_json5("mode", json.dumps("router"))
    config.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    config.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(config)


class MeasurementReceipts:
    """The measurements a bridge publishes for one vehicle, as they arrive on ``session``: (sample number, the
    torque's value, which the benchmarks number the samples with; measurement time stamp [ns]; receipt [ns], wall
    clock), appended by Zenoh's thread."""

    def __init__(self, session: Any, vehicle: str) -> None:
        from agv_protocol.wire import vehicle_key

        self.received: list[tuple[int, int, int]] = []
        self._lock = threading.Lock()
        self._subscriber = session.declare_subscriber(vehicle_key(vehicle, "meas"), self._arrived)

    def _arrived(self, sample: Any) -> None:
        from agv_protocol.wire import Measurement

        now = time.time_ns()
        m = Measurement.decode(sample.payload.to_bytes())
        with self._lock:
            self.received.append((round(m.torque_nm), m.timestamp_ns, now))

    def undeclare(self) -> None:
        self._subscriber.undeclare()


def summarise(
    received: list[tuple[int, int, int]], put_ns: dict[int, int], decode_us: float, cpu_s: float, run_s: float
) -> BridgeLatency:
    """Per sample put while the bridge ran (between its first and last measurement), its first measurement.

    received : (sample number, measurement time stamp [ns], receipt [ns]) per measurement; put_ns : sample number
    -> put of its last message [ns]; all on the wall clock.
    """
    if not received:
        raise RuntimeError("no measurement came back from the bridge")
    first_tick, last_tick = min(r[1] for r in received), max(r[1] for r in received)
    window = {k: t for k, t in put_ns.items() if first_tick <= t <= last_tick}
    first: dict[int, tuple[int, int]] = {}
    for k, tick_ns, at_ns in received:
        if k in window and k not in first:
            first[k] = (tick_ns, at_ns)
    put = np.array([window[k] for k in first], dtype=np.int64)
    tick = np.array([t for t, _ in first.values()], dtype=np.int64)
    at = np.array([a for _, a in first.values()], dtype=np.int64)
    total, hold, after = (at - put) / 1e6, (tick - put) / 1e6, (at - tick) / 1e6
    return BridgeLatency(
        samples=len(window),
        carried=len(first),
        measurements=len(received),
        total_p50_ms=float(np.percentile(total, 50)),
        total_p99_ms=float(np.percentile(total, 99)),
        total_max_ms=float(total.max()),
        hold_p50_ms=float(np.percentile(hold, 50)),
        hold_p99_ms=float(np.percentile(hold, 99)),
        after_tick_p50_ms=float(np.percentile(after, 50)),
        after_tick_p99_ms=float(np.percentile(after, 99)),
        decode_us=decode_us,
        bridge_cpu_fraction=cpu_s / run_s,
        run_s=run_s,
    )


def write(out_dir: Path, name: str, result: BridgeLatency, report: Callable[[BridgeLatency], str]) -> Path:
    """``name``.json (the figures) and ``name``.md (``report`` of them) in ``out_dir``; the report's path."""
    (out_dir / f"{name}.json").write_text(json.dumps(asdict(result), indent=1) + "\n")
    path = out_dir / f"{name}.md"
    path.write_text(report(result))
    return path


def table_row(r: BridgeLatency) -> str:
    """The figures of a run as a row of the bridge reports' table, with the paragraph break after it."""
    return (
        f"| {r.samples} | {r.carried} | {r.measurements} | {r.total_p50_ms:.2f} / {r.total_p99_ms:.2f} / "
        f"{r.total_max_ms:.1f} | {r.hold_p50_ms:.2f} / {r.hold_p99_ms:.2f} | {r.after_tick_p50_ms:.2f} / "
        f"{r.after_tick_p99_ms:.2f} | {r.decode_us:.1f} | {r.bridge_cpu_fraction:.1%} of a core |\n\n"
    )
