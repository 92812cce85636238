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
from dataclasses import dataclass
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
