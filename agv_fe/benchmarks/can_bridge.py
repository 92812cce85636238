"""The latency `agv-fe can-bridge` adds between a vehicle's CAN frames and the service's measurement.

A vehicle (a thread of this process) sends its frames, encoded with its DBC by cantools, on python-can's ``virtual``
bus at their rates: WHEEL_SPEEDS, IMU_RATES, STEER_DEMAND and DRIVE_DEMAND at 100 Hz, each cycle at a random phase
within its 10 ms period (a vehicle whose clock is not the bridge's), DRIVE_DEMAND last, and BODY_STATUS, which the
mapping does not use, at 10 Hz; the torque signal carries the sample's number. The bridge runs as `agv-fe
can-bridge --interface virtual` in this process's main thread (the virtual bus joins the buses of one process only),
a client of a zenoh router in this process too, and publishes measurements on the 10 ms grid; a subscriber here
receives them. Each sample's latency, from the send of its last frame (the torque) to the receipt of the first
measurement carrying it, in its grid hold and what comes after the tick: agv_fe/benchmarks/bridge_latency.py.

The vehicle, the router, the subscriber and the bridge share one interpreter, so the figures include their turns on
it; the bridge's CPU is bounded by the process's less the vehicle thread's. The virtual bus delivers a frame at once:
the bus's own transmission time (about 0.22 to 0.27 ms for a frame of 8 data bytes at 500 kbit/s) is not in them.
"""

from __future__ import annotations

import contextlib
import io
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np

from agv_fe.benchmarks import bridge_latency, report_header
from agv_fe.benchmarks.harness import free_port

RUN_S = 30.0
#: How long the bridge waits for every signal at its start, and the vehicle sends beyond its run [s].
WAIT_S = 30.0
VEHICLE = "bench-can"
#: The vehicle's CAN database (tests/edge_client/test_can_log.py uses it too), km/h and deg/s as on many vehicles.
DBC = """VERSION ""

NS_ :

BS_:

BU_: ECU

BO_ 256 WHEEL_SPEEDS: 8 ECU
 SG_ VehicleSpeed : 0|16@1+ (0.01,0) [0|655.35] "km/h" Vector__XXX

BO_ 257 IMU_RATES: 8 ECU
 SG_ YawRate : 0|16@1- (0.01,0) [-327.68|327.67] "deg/s" Vector__XXX

BO_ 258 DRIVE_DEMAND: 8 ECU
 SG_ WheelTorqueDemand : 0|16@1- (0.5,0) [-16384|16383.5] "Nm" Vector__XXX

BO_ 259 STEER_DEMAND: 8 ECU
 SG_ RoadWheelAngleDemand : 0|16@1- (0.0001,0) [-3.2768|3.2767] "rad" Vector__XXX

BO_ 2047 BODY_STATUS: 8 ECU
 SG_ DoorOpen : 0|1@1+ (1,0) [0|1] "" Vector__XXX
"""
MAPPING = """vx: {message: WHEEL_SPEEDS, signal: VehicleSpeed, scale: 0.2777777777777778}
r: {message: IMU_RATES, signal: YawRate, scale: 0.017453292519943295}
torque: {message: DRIVE_DEMAND, signal: WheelTorqueDemand}
steer: {message: STEER_DEMAND, signal: RoadWheelAngleDemand}
"""
#: The frames of one 100 Hz cycle, in the order sent: the torque (which numbers the sample) last. Signal values in
#: the DBC's units: 36 km/h, 0.573 deg/s (0.01 rad/s), 0.001 rad.
CYCLE = (
    ("WHEEL_SPEEDS", {"VehicleSpeed": 36.0}),
    ("IMU_RATES", {"YawRate": 0.573}),
    ("STEER_DEMAND", {"RoadWheelAngleDemand": 0.001}),
)
#: The frame of a message the mapping does not use, sent every this many cycles (10 Hz).
BODY_EVERY = 10
#: The torque signal numbers the samples: 16 bits of 0.5 N m hold the numbers up to this one.
LAST_SAMPLE_NUMBER = 16_383


def _frames(database: Any) -> tuple[list[Any], Any, Any]:
    """The cycle's fixed frames, a builder of its torque frame for sample k, and the body frame."""
    import can

    def frame(name: str, values: dict[str, float]) -> Any:
        message = database.get_message_by_name(name)
        return can.Message(arbitration_id=message.frame_id, data=message.encode(values), is_extended_id=False)

    fixed = [frame(name, values) for name, values in CYCLE]
    return (
        fixed,
        lambda k: frame("DRIVE_DEMAND", {"WheelTorqueDemand": float(k)}),
        frame("BODY_STATUS", {"DoorOpen": 0}),
    )


def _decode_us(database: Any, frames: list[Any]) -> float:
    """Mean time to decode one of the cycle's frames with cantools and map its signal [us]."""
    from edge_client.can_log import decode_frame, load_mapping, resolve

    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "map.yaml").write_text(MAPPING)
        wanted = resolve(database, load_mapping(Path(tmp) / "map.yaml"), "DBC")
    repeats = 2000
    started = time.perf_counter()
    for _ in range(repeats):
        for frame in frames:
            decode_frame(database, frame, wanted[frame.arbitration_id])
    return (time.perf_counter() - started) / (repeats * len(frames)) * 1e6


def measure(run_s: float = RUN_S, seed: int = 0) -> bridge_latency.BridgeLatency:
    """Run the vehicle, the router and the bridge (module docstring); the latencies of the samples carried."""
    import can
    import cantools

    if round((run_s + WAIT_S) * 100) > LAST_SAMPLE_NUMBER:
        raise ValueError(f"run_s = {run_s:g} s: the torque signal numbers at most {LAST_SAMPLE_NUMBER} samples")
    database = cantools.database.load_string(DBC, "dbc")
    fixed, torque, body = _frames(database)
    decode_us = _decode_us(database, [*fixed, torque(7)])
    port = free_port()
    session = bridge_latency.router_session(port)
    receipts = bridge_latency.MeasurementReceipts(session, VEHICLE)
    channel = f"agv-fe-bench-{uuid.uuid4().hex[:8]}"  # a virtual bus of this run alone
    bus = can.Bus(interface="virtual", channel=channel)
    put_ns: dict[int, int] = {}
    vehicle_cpu_s: list[float] = []
    stop = threading.Event()
    vehicle = threading.Thread(
        target=_send, args=(bus, fixed, torque, body, put_ns, stop, run_s, seed, vehicle_cpu_s), daemon=True
    )
    cpu_before = time.process_time()
    try:
        with tempfile.TemporaryDirectory() as tmp:
            (Path(tmp) / "vehicle.dbc").write_text(DBC)
            (Path(tmp) / "map.yaml").write_text(MAPPING)
            vehicle.start()
            _bridge(Path(tmp), channel, port, run_s)
    finally:
        stop.set()
        vehicle.join(timeout=30)
        bus.shutdown()
        receipts.undeclare()
        session.close()
    cpu_s = time.process_time() - cpu_before - sum(vehicle_cpu_s)
    return bridge_latency.summarise(receipts.received, put_ns, decode_us, cpu_s, run_s)


def _bridge(files: Path, channel: str, port: int, run_s: float) -> None:
    """`agv-fe can-bridge` on the virtual bus ``channel`` for ``run_s``, its output kept; raise if it fails."""
    from agv_fe.cli import main

    args = ["can-bridge", "--dbc", str(files / "vehicle.dbc"), "--map", str(files / "map.yaml"), "--interface",
            "virtual", "--channel", channel, "--vehicle", VEHICLE, "--connect", f"tcp/127.0.0.1:{port}",
            "--duration", f"{run_s:g}", "--wait", f"{WAIT_S:g}", "--progress", "3600"]  # fmt: skip
    output = io.StringIO()
    with contextlib.redirect_stdout(output), contextlib.redirect_stderr(output):
        code = main(args)
    if code != 0:
        raise RuntimeError(f"agv-fe can-bridge exited with {code}:\n{output.getvalue()}")


def _send(
    bus: Any,
    fixed: list[Any],
    torque: Any,
    body: Any,
    put_ns: dict[int, int],
    stop: threading.Event,
    run_s: float,
    seed: int,
    cpu_s: list[float],
) -> None:
    """100 Hz cycles at a random phase each, until ``stop`` (bounded: the bridge's run and its wait); the CPU time
    of this thread is appended to ``cpu_s``."""
    rng = np.random.default_rng(seed)
    start = time.monotonic()
    try:
        for k in range(round((run_s + WAIT_S) * 100)):
            if stop.is_set():
                return
            due = start + 0.01 * k + float(rng.uniform(0.0, 0.01))
            time.sleep(max(due - time.monotonic(), 0.0))
            if k % BODY_EVERY == 0:
                bus.send(body)
            for frame in [*fixed, torque(k)]:
                now = time.time_ns()
                bus.send(frame)
            put_ns[k] = now
    finally:
        cpu_s.append(time.thread_time())


def run(out_dir: Path, run_s: float = RUN_S) -> Path:
    return bridge_latency.write(out_dir, "can_bridge", measure(run_s), report)


def report(r: bridge_latency.BridgeLatency) -> str:
    return (
        report_header("CAN bridge: latency added", "can_bridge")
        + "One vehicle's CAN frames, encoded with its DBC by cantools, sent on python-can's in-process `virtual` bus "
        f"for {r.run_s:g} s: speed, yaw rate, steering and drive-torque demand at 100 Hz, each cycle at a random "
        "phase within its period, and an unmapped body message at 10 Hz; `agv-fe can-bridge` turns them into the "
        "service's measurements on the 10 ms grid. Latency of a sample: from the send of its last frame to the "
        "receipt of the first measurement carrying it, through a zenoh router on 127.0.0.1 (wall clock; the vehicle, "
        "the router and the bridge in one process, as the virtual bus joins the buses of one process only).\n\n"
        "| samples sent | carried by a measurement | measurements | total p50 / p99 / max [ms] | "
        "grid hold p50 / p99 [ms] | after the tick p50 / p99 [ms] | decode per frame [us] | "
        "bridge CPU, at most (start-up included) |\n"
        "|---|---|---|---|---|---|---|---|\n" + bridge_latency.table_row(r) + "## Reading\n\n"
        f"**Added latency: {r.total_p50_ms:.1f} ms at the median, {r.total_p99_ms:.1f} ms at the 99th "
        "percentile.** Most of it is the grid by design: a frame waits for the next 10 ms grid point "
        f"(grid hold, {r.hold_p50_ms:.1f} ms at the median for frames at a random phase, never more than a "
        "period plus the tick's lateness); what the bridge then does and the network hops take the rest "
        f"({r.after_tick_p50_ms:.2f} ms at the median). Decoding a frame with cantools and mapping its signal takes "
        f"{r.decode_us:.0f} us. A sample superseded by the next one before a grid point is not carried "
        f"({r.samples - r.carried} of {r.samples} here, as two cycles fall within one period when their phases "
        "differ): the measurement carries the newer one, the zero-order hold of edge_client/grid.py.\n\n"
        "Not in these figures: the bus's own transmission time, which the virtual bus does not have (a frame of 8 "
        "data bytes takes about 0.22 to 0.27 ms at 500 kbit/s, so about 1 ms for a cycle's four), and the kernel's "
        "SocketCAN path (no vcan module on this machine). In them, unlike on a vehicle's gateway: the vehicle's "
        "thread, the router and the subscriber take turns with the bridge on one Python interpreter; the bridge's "
        "CPU is the process's less the vehicle thread's, so it still holds the router's and the subscriber's share.\n"
    )


if __name__ == "__main__":
    print(run(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("docs/benchmarks")))
