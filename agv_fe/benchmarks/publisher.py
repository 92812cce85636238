"""Publisher pacing: achieved rate, jitter and overruns against fleet size, and one process's capacity.

Each size runs the real thing: a PlantSimulator batch (RK4 at 1 ms, random
drives, the default fault mix) published through one zenoh client session,
ground truth at 10 Hz, to a router in another process that also holds the
subscriber (so matching is true and every measurement leaves the process).
One vehicle's measurements are counted back in this process to check
delivery. Run as ``python -m agv_fe.benchmarks.publisher sink PORT`` the
module is that router.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from agv_fe.benchmarks import report_header
from agv_fe.benchmarks.harness import free_port
from edge_client.pacing import PacingStats

SIZES = (50, 100, 200, 400, 800)
RUN_S = 10.0
#: The issue's criterion: 100 Hz within 1 %; and at most 1 % of the ticks start after the next deadline.
RATE_TOLERANCE = 0.01
OVERRUN_TOLERANCE = 0.01


@dataclass(frozen=True)
class SizeResult:
    vehicles: int
    #: samples published per vehicle and second [Hz]
    rate_hz: float
    #: the loop's lateness, late ticks and overruns (edge_client.pacing)
    pacing: PacingStats
    source_p50_ms: float
    source_p99_ms: float
    publish_p50_ms: float
    publish_p99_ms: float
    delivered_fraction: float
    load_before: float

    @property
    def keeps_up(self) -> bool:
        on_rate = abs(self.rate_hz - 100.0) <= 100.0 * RATE_TOLERANCE
        return on_rate and self.pacing.overruns <= OVERRUN_TOLERANCE * self.pacing.ticks

    def record(self) -> dict[str, Any]:
        """The row of publisher.json: every figure at the top level, the pacing's among them."""
        p = self.pacing
        return {
            "vehicles": self.vehicles,
            "rate_hz": self.rate_hz,
            "lateness_p50_ms": p.lateness_p50_ms,
            "lateness_p99_ms": p.lateness_p99_ms,
            "max_lag_ms": p.max_lag_ms,
            "late": p.late,
            "overruns": p.overruns,
            "ticks": p.ticks,
            "source_p50_ms": self.source_p50_ms,
            "source_p99_ms": self.source_p99_ms,
            "publish_p50_ms": self.publish_p50_ms,
            "publish_p99_ms": self.publish_p99_ms,
            "delivered_fraction": self.delivered_fraction,
            "load_before": self.load_before,
        }


def sink_main(port: int) -> None:
    """A router on 127.0.0.1:port with a subscriber to every measurement (kept in Rust: a 1-slot ring)."""
    import zenoh

    from agv_protocol.wire import fleet_selector

    config = zenoh.Config()
    config.insert_json5("mode", json.dumps("router"))
    config.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    config.insert_json5("scouting/multicast/enabled", "false")
    session: Any = zenoh.open(config)
    subscriber: Any = session.declare_subscriber(fleet_selector("meas"), zenoh.handlers.RingChannel(1))
    print("ready", flush=True)
    try:
        sys.stdin.read()  # until the benchmark closes our stdin
    finally:
        subscriber.undeclare()
        session.close()


def measure(vehicles: int, endpoint: str, run_s: float = RUN_S) -> SizeResult:
    from agv_protocol.wire import vehicle_key
    from edge_client.fleet_mix import DEFAULT_MIX, build_fleet
    from edge_client.publisher import FleetPublisher, PublisherOptions
    from edge_client.sources import SimulatedSource
    from edge_client.transport import Subscription, TransportOptions, close_session, open_session

    members = build_fleet(DEFAULT_MIX, vehicles, run_s + 1.0, seed=vehicles)
    source = SimulatedSource([m.vehicle_id for m in members], [m.scenario for m in members])
    options = TransportOptions(connect=(endpoint,))
    session = open_session(options)
    counted = [0]
    lock = threading.Lock()

    def count(_rx: object) -> None:
        with lock:
            counted[0] += 1

    probe = Subscription(session, vehicle_key(members[0].vehicle_id, "meas"), count)
    try:
        time.sleep(0.5)
        load = os.getloadavg()[0]
        with FleetPublisher(session, source, PublisherOptions(truth_rate_hz=10.0)) as publisher:
            report = publisher.run(run_s, drain_s=0.5)
    finally:
        probe.close()
        close_session(session)
    return SizeResult(
        vehicles=vehicles,
        rate_hz=report.sample_rate_hz,
        pacing=report.pacing,
        source_p50_ms=report.work_ms["source_p50"],
        source_p99_ms=report.work_ms["source_p99"],
        publish_p50_ms=report.work_ms["publish_p50"],
        publish_p99_ms=report.work_ms["publish_p99"],
        delivered_fraction=counted[0] / max(report.vehicles[0].sent, 1),
        load_before=load,
    )


def run(out_dir: Path, sizes: tuple[int, ...] = SIZES, run_s: float = RUN_S) -> Path:
    port = free_port()
    sink = subprocess.Popen(
        [sys.executable, "-m", "agv_fe.benchmarks.publisher", "sink", str(port)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    results: list[SizeResult] = []
    try:
        assert sink.stdout is not None
        if sink.stdout.readline().strip() != "ready":
            raise RuntimeError("the benchmark's router did not start")
        for n in sizes:
            result = measure(n, f"tcp/127.0.0.1:{port}", run_s)
            results.append(result)
            print(
                f"  {n} vehicles: {result.rate_hz:.2f} Hz, lateness p99 {result.pacing.lateness_p99_ms:.2f} ms, "
                f"overruns {result.pacing.overruns}, work p50 {result.source_p50_ms + result.publish_p50_ms:.2f} ms",
                flush=True,
            )
            if not result.keeps_up and result.pacing.overruns > 0.2 * result.pacing.ticks:
                break  # far past capacity: larger fleets only take longer to say so
    finally:
        if sink.stdin is not None:
            sink.stdin.close()
        try:
            sink.wait(timeout=10)
        except subprocess.TimeoutExpired:
            sink.kill()
            sink.wait()
    path = out_dir / "publisher.md"
    path.write_text(_report(results, run_s))
    (out_dir / "publisher.json").write_text(json.dumps([r.record() for r in results], indent=2))
    return path


def _report(results: list[SizeResult], run_s: float) -> str:
    lines = [
        report_header("Publisher pacing and capacity", "publisher"),
        f"Each row: one process simulates N vehicles (RK4, 10 sub-steps of 1 ms) and publishes them at 100 Hz "
        f"for {run_s:g} s through one zenoh client session to a router process that subscribes to all "
        "measurements; ground truth at 10 Hz. Rate = samples published per vehicle / elapsed. Lateness = "
        "how long after its deadline a tick started; late = more than 1 ms; overrun = after the next "
        "deadline. Work = per tick, simulation (source) and encoding + put (publish). Delivered = "
        "measurements of vehicle 0 received back by a subscriber in the publishing process / sent. Load = "
        "the machine's 1-minute load average before the run (other work shares its 2 cores).\n",
        "| vehicles | rate [Hz] | lateness p50 / p99 / max [ms] | late | overruns | work source p50 / p99 [ms] "
        "| work publish p50 / p99 [ms] | delivered | load | keeps 100 Hz |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        lines.append(
            f"| {r.vehicles} | {r.rate_hz:.2f} | {r.pacing.lateness_p50_ms:.2f} / {r.pacing.lateness_p99_ms:.2f} / "
            f"{r.pacing.max_lag_ms:.1f} | {r.pacing.late} | {r.pacing.overruns} "
            f"| {r.source_p50_ms:.2f} / {r.source_p99_ms:.2f} "
            f"| {r.publish_p50_ms:.2f} / {r.publish_p99_ms:.2f} | {r.delivered_fraction:.1%} | {r.load_before:.1f} "
            f"| {'yes' if r.keeps_up else 'no'} |"
        )
    if not results:
        return "\n".join([*lines, "", "No size was measured."]) + "\n"
    kept = [r.vehicles for r in results if r.keeps_up]
    capacity = max(kept) if kept else 0
    sizes = np.array([r.vehicles for r in results], dtype=float)
    work = np.array([r.source_p50_ms + r.publish_p50_ms for r in results])
    if len(results) >= 2:
        per_vehicle_ms, fixed_ms = np.polyfit(sizes, work, 1)
        fit = (
            f"A straight line through the median work per tick gives {fixed_ms:.1f} ms fixed plus "
            f"{1000 * per_vehicle_ms:.1f} us per vehicle, so 80 % of a 10 ms tick holds about "
            f"{(8.0 - fixed_ms) / per_vehicle_ms:.0f} vehicles when the process has a core to itself. "
        )
    else:
        fit = ""
    lines += [
        "",
        "## Reading",
        "",
        f"**Capacity.** The largest fleet that kept 100 Hz within {RATE_TOLERANCE:.0%} with at most "
        f"{OVERRUN_TOLERANCE:.0%} overruns in this run: **{capacity} vehicles** in one process. {fit}"
        "Beyond that, run several processes with different --id-prefix (each opens its own session).",
        "",
        "**Pacing.** Deadlines are absolute (t0 + k * 10 ms on the monotonic clock): a late tick is "
        "caught up, never shifts the schedule, so the rate stays at 100 Hz even when single ticks are late "
        "because the machine is busy. Late ticks and overruns count those moments; the rate says whether the "
        "loop kept up on average.",
        "",
        f"**Where the time goes.** The simulation's work is mostly fixed: {results[0].source_p50_ms:.1f} ms "
        f"per tick at {results[0].vehicles} vehicles, {results[-1].source_p50_ms:.1f} ms at "
        f"{results[-1].vehicles} (numpy call overhead of 40 RK4 stage evaluations, whatever the batch size). "
        f"Publishing grows with the fleet: {results[0].publish_p50_ms:.1f} ms and "
        f"{results[-1].publish_p50_ms:.1f} ms (encode the 64-byte Measurement, put it through zenoh, plus a "
        "tenth of the vehicles' JSON ground truth each tick). The loop runs with the collector's long-lived "
        "objects frozen and a 0.5 ms thread switch interval, so neither a full garbage collection nor the "
        "thread receiving estimates holds it up for long.",
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "sink":
        sink_main(int(sys.argv[2]))
    else:
        raise SystemExit("usage: python -m agv_fe.benchmarks.publisher sink PORT")
