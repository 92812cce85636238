"""The latency `agv-fe ros2-bridge` adds between a ROS 2 vehicle's messages and the service's measurement.

A vehicle (this process) puts the four mapped topics' CDR messages on their rmw_zenoh keys through a zenoh router
(this process too) at 100 Hz, each sample at a random phase within its 10 ms period, as a vehicle whose clock is
not the bridge's would; the torque field carries the sample's number. The bridge runs as `agv-fe ros2-bridge` in
its own process, a client of the router, and publishes measurements on the 10 ms grid; a subscriber in this process
receives them. Each sample's latency, from the put of its last message (the torque) to the receipt of the first
measurement carrying it, in its grid hold and what comes after the tick: agv_fe/benchmarks/bridge_latency.py.
"""

from __future__ import annotations

import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from agv_fe.benchmarks import bridge_latency, report_header
from agv_fe.benchmarks.harness import free_port

RUN_S = 30.0
VEHICLE = "bench-ros2"
MAPPING = """vx: {topic: /odom, type: nav_msgs/msg/Odometry, field: twist.twist.linear.x}
r: {topic: /imu, type: sensor_msgs/msg/Imu, field: angular_velocity.z}
torque: {topic: /drive_torque, type: std_msgs/msg/Float64, field: data}
steer: {topic: /cmd, type: ackermann_msgs/msg/AckermannDriveStamped, field: drive.steering_angle}
"""
#: the order of the puts of one sample: the torque (which numbers the sample) last
ORDER = ("/odom", "/imu", "/cmd", "/drive_torque")


def _messages(store: Any) -> dict[str, Any]:
    """Builders of one sample's messages: topic -> f(k) -> CDR bytes."""
    t = store.types
    vec = t["geometry_msgs/msg/Vector3"]
    header = t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="base")
    quat = t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)
    pose = t["geometry_msgs/msg/Pose"](position=t["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0), orientation=quat)
    twist = t["geometry_msgs/msg/Twist"](linear=vec(x=10.0, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=0.01))
    odom = t["nav_msgs/msg/Odometry"](
        header=header,
        child_frame_id="base",
        pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
    )
    imu = t["sensor_msgs/msg/Imu"](
        header=header,
        orientation=quat,
        orientation_covariance=np.zeros(9),
        angular_velocity=vec(x=0.0, y=0.0, z=0.01),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=vec(x=0.0, y=0.0, z=9.81),
        linear_acceleration_covariance=np.zeros(9),
    )
    drive = t["ackermann_msgs/msg/AckermannDrive"](
        steering_angle=0.001, steering_angle_velocity=0.0, speed=10.0, acceleration=0.0, jerk=0.0
    )
    cmd = t["ackermann_msgs/msg/AckermannDriveStamped"](header=header, drive=drive)
    fixed = {
        "/odom": bytes(store.serialize_cdr(odom, "nav_msgs/msg/Odometry")),
        "/imu": bytes(store.serialize_cdr(imu, "sensor_msgs/msg/Imu")),
        "/cmd": bytes(store.serialize_cdr(cmd, "ackermann_msgs/msg/AckermannDriveStamped")),
    }
    out: dict[str, Any] = {topic: (lambda _k, raw=raw: raw) for topic, raw in fixed.items()}
    float64 = t["std_msgs/msg/Float64"]
    out["/drive_torque"] = lambda k: bytes(store.serialize_cdr(float64(data=float(k)), "std_msgs/msg/Float64"))
    return out


def _decode_us(store: Any, builders: dict[str, Any], mapping: Any) -> float:
    """Mean time to deserialise one of the four messages with rosbags and read its field [us]."""
    from edge_client.ros2 import field_value

    signals = {s.topic: s for s in mapping.signals().values()}
    raws = [(builders[topic](7), signals[topic]) for topic in ORDER]
    repeats = 2000
    started = time.perf_counter()
    for _ in range(repeats):
        for raw, signal in raws:
            field_value(store.deserialize_cdr(raw, signal.type), signal)
    return (time.perf_counter() - started) / (repeats * len(raws)) * 1e6


def measure(run_s: float = RUN_S, seed: int = 0) -> bridge_latency.BridgeLatency:
    """Run the vehicle, the router and the bridge (module docstring); the latencies of the samples carried."""
    import yaml

    from edge_client.ros2 import RosMapping, typestore_for
    from edge_client.ros2_bridge import rmw_attachment, topic_key

    mapping = RosMapping.model_validate(yaml.safe_load(MAPPING))
    store = typestore_for(mapping)
    builders = _messages(store)
    decode_us = _decode_us(store, builders, mapping)
    port = free_port()
    session = bridge_latency.router_session(port)
    receipts = bridge_latency.MeasurementReceipts(session, VEHICLE)
    publishers = {
        topic: session.declare_publisher(topic_key(0, topic, s.type, store.hash_rihs01(s.type)))
        for topic, s in ((s.topic, s) for s in mapping.signals().values())
    }
    put_ns: dict[int, int] = {}
    said = ""
    usage_before = resource.getrusage(resource.RUSAGE_CHILDREN)
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "map.yaml").write_text(MAPPING)
        bridge = subprocess.Popen(
            [sys.executable, "-m", "agv_fe", "ros2-bridge", "--map", str(Path(tmp) / "map.yaml"), "--vehicle",
             VEHICLE, "--connect", f"tcp/127.0.0.1:{port}", "--duration", f"{run_s:g}", "--wait", "30",
             "--progress", "3600"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        try:
            _publish(publishers, builders, put_ns, bridge, run_s, seed, rmw_attachment)
            out, err = bridge.communicate(timeout=60)
            said = f"exit status {bridge.returncode}; its output ends: {(out + err)[-1500:]}"
        finally:
            if bridge.poll() is None:
                bridge.kill()
                bridge.wait(timeout=10)
            receipts.undeclare()
            for publisher in publishers.values():
                publisher.undeclare()
            session.close()
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu_s = (usage.ru_utime - usage_before.ru_utime) + (usage.ru_stime - usage_before.ru_stime)
    if not receipts.received:  # what the bridge said makes the failure explain itself
        raise RuntimeError(f"no measurement came back from the bridge ({len(put_ns)} samples put); bridge {said}")
    return bridge_latency.summarise(receipts.received, put_ns, decode_us, cpu_s, run_s)


def _publish(
    publishers: dict[str, Any],
    builders: dict[str, Any],
    put_ns: dict[int, int],
    bridge: subprocess.Popen[str],
    run_s: float,
    seed: int,
    attachment: Any,
) -> None:
    """100 Hz samples at a random phase each, until the bridge exits (bounded: its run and a minute to start)."""
    rng = np.random.default_rng(seed)
    gid = bytes(16)
    start = time.monotonic()
    for k in range(round((run_s + 60.0) * 100)):
        if bridge.poll() is not None:
            return
        due = start + 0.01 * k + float(rng.uniform(0.0, 0.01))
        time.sleep(max(due - time.monotonic(), 0.0))
        for topic in ORDER:
            raw = builders[topic](k)
            now = time.time_ns()
            publishers[topic].put(raw, attachment=attachment(k, now, gid))
        put_ns[k] = now


def run(out_dir: Path, run_s: float = RUN_S) -> Path:
    return bridge_latency.write(out_dir, "ros2_bridge", measure(run_s), report)


def report(r: bridge_latency.BridgeLatency) -> str:
    return (
        report_header("ROS 2 bridge: latency added", "ros2_bridge")
        + f"One vehicle's four topics (nav_msgs/Odometry, sensor_msgs/Imu, ackermann_msgs/AckermannDriveStamped, "
        f"std_msgs/Float64) put as CDR on their rmw_zenoh keys at 100 Hz for {r.run_s:g} s, each sample at a random "
        "phase within its period; `agv-fe ros2-bridge` in its own process turns them into the service's "
        "measurements on the 10 ms grid. Latency of a sample: from the put of its last message to the receipt of "
        "the first measurement carrying it, through a zenoh router on 127.0.0.1 (wall clock, one machine).\n\n"
        "| samples put | carried by a measurement | measurements | total p50 / p99 / max [ms] | "
        "grid hold p50 / p99 [ms] | after the tick p50 / p99 [ms] | decode per message [us] | "
        "bridge CPU (start-up included) |\n"
        "|---|---|---|---|---|---|---|---|\n" + bridge_latency.table_row(r) + "## Reading\n\n"
        f"**Added latency: {r.total_p50_ms:.1f} ms at the median, {r.total_p99_ms:.1f} ms at the 99th "
        "percentile.** Most of it is the grid by design: a message waits for the next 10 ms grid point "
        f"(grid hold, {r.hold_p50_ms:.1f} ms at the median for messages at a random phase, never more than a "
        "period plus the tick's lateness); what the bridge then does and the network hops take the rest "
        f"({r.after_tick_p50_ms:.2f} ms at the median). Decoding a message with rosbags and reading its field takes "
        f"{r.decode_us:.0f} us. A sample superseded by the next one before a grid point is not carried "
        f"({r.samples - r.carried} of {r.samples} here, as two messages of one topic fall within one period when "
        "their phases differ): the measurement carries the newer one, the zero-order hold of edge_client/grid.py.\n"
    )


if __name__ == "__main__":
    print(run(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("docs/benchmarks")))
