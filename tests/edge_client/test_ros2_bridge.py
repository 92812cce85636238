"""`agv-fe ros2-bridge` (edge_client/ros2_bridge.py) against real parts: CDR messages put by a zenoh session on the
exact rmw_zenoh key expressions (with rmw_zenoh's attachment), the bridge in its own process, the real service
answering with estimates and alarms, both republished as ROS 2 topics; bad input (malformed CDR, another type
definition, a NaN, a topic that stops) counted while the bridge keeps running; a mapped road-grade topic goes with
each measurement."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import yaml

pytest.importorskip("rosbags")

from edge_client.ros2 import RosMapping
from edge_client.ros2_bridge import dds_type_name, rmw_attachment, topic_key
from edge_client.scenario import REALISTIC_NOISE, Manoeuvre, Scenario, SpeedPoint
from edge_client.simulation import simulate_plant
from edge_client.transport import ChannelSubscription, close_session, open_session
from tests.edge_client.bridge_checks import paced_periods
from tests.edge_client.ros2_messages import (
    GRADE_MAPPING,
    GRADE_TOPIC,
    GRADE_TYPE,
    MAPPING,
    TOPICS,
    grade_message,
    messages,
    road_grade,
    store,
)
from tests.edge_client.test_publisher import Counter

pytestmark = pytest.mark.network

VEHICLE = "ros-car-1"
GID = bytes(range(16))
#: at most this many 10 ms periods of publishing, whatever happens (the bridge runs 9 s once every topic came)
MAX_PERIODS = 4_000
STATUS = "diagnostic_msgs/msg/DiagnosticStatus"
#: the service's levels as DiagnosticStatus levels (its constants OK 0, WARN 1, ERROR 2, STALE 3)
LEVELS = {"OK": 0, "WARN": 1, "FAULT": 2, "STALE": 3}
#: from this many periods after the first measurement, the steering command reads this much more than the wheels
#: turn: a steering fault of -0.05 rad, past the default profile's FAULT threshold (0.02 rad) and its warm-up
STEER_BIAS_FROM, STEER_BIAS_RAD = 300, 0.05
#: the fields of an alarm every republished alarm status carries as key-values, as they are
ALARM_FIELDS = ("id", "kind", "state", "level")


def test_the_rmw_zenoh_key_of_a_topic():
    """The format of rmw_zenoh's design document, with its own example: std_msgs/String on `chatter`."""
    ts = store(RosMapping.model_validate(yaml.safe_load(MAPPING)))
    assert dds_type_name("std_msgs/msg/String") == "std_msgs::msg::dds_::String_"
    assert topic_key(0, "/chatter", "std_msgs/msg/String", ts.hash_rihs01("std_msgs/msg/String")) == (
        "0/chatter/std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
    )
    assert (
        topic_key(2, "/robot1/odom", "nav_msgs/msg/Odometry", "H") == "2/robot1/odom/nav_msgs::msg::dds_::Odometry_/H"
    )
    assert rmw_attachment(7, 1_700_000_000_000_000_000, GID) == (
        (7).to_bytes(8, "little") + (1_700_000_000_000_000_000).to_bytes(8, "little") + b"\x10" + GID
    )


def grid_account(out: str) -> tuple[int, int, dict[str, int]]:
    """A bridge's grid account in its output: the ticks sampled, the ticks, and per column the ticks not sent as it
    was stale. A tick at which the test's sending was late by more than max_age_s (a busy machine) counts under
    every column."""
    grid = re.search(r"grid: (\d+) of (\d+) ticks sampled; ticks not sent for a stale column: (.*)", out)
    assert grid is not None, out
    stale = {column: int(n) for column, n in (item.split() for item in grid[3].split(", ") if item != "none")}
    return int(grid[1]), int(grid[2]), stale


def _drive():
    scenario = Scenario(
        name="ros2-live", duration_s=20.0, initial_speed_mps=12.0,
        speed_profile=(SpeedPoint(t_s=0.0, speed_mps=12.0),),
        manoeuvres=(Manoeuvre(kind="lane_change", start_s=3.0, duration_s=4.0, amplitude_rad=0.02),),
        noise=REALISTIC_NOISE, seed=11,
    )  # fmt: skip
    result = simulate_plant([scenario])
    return result.y[:, 0], result.u[:, 0].astype(np.float32).astype(float)


def test_the_bridge_turns_rmw_zenoh_topics_into_measurements_and_estimates_come_back(
    router, estimation_service, tmp_path
):
    mapping = RosMapping.model_validate(yaml.safe_load(MAPPING))
    ts = store(mapping)
    (tmp_path / "map.yaml").write_text(MAPPING)
    y, u = _drive()
    vehicle = open_session(router.client())  # the ROS 2 nodes' side, and the test's eyes on the measurements
    counter = Counter(vehicle)
    counter.routed(router)  # the bridge's first sample, seq 0, must reach it
    publishers = {
        topic: vehicle.declare_publisher(topic_key(0, topic, kind, ts.hash_rihs01(kind)))
        for topic, kind in TOPICS.items()
    }
    other_definition = vehicle.declare_publisher(topic_key(0, "/imu", TOPICS["/imu"], "RIHS01_" + "0" * 64))
    other_type = vehicle.declare_publisher(topic_key(0, "/imu", "std_msgs/msg/Float64", "RIHS01_" + "1" * 64))
    # the vehicle's own node listening to the estimates republished as a ROS 2 topic, and to the ROS 2 graph
    status_key = topic_key(0, "/agv_fe/status", STATUS, ts.hash_rihs01(STATUS))
    statuses = ChannelSubscription(vehicle, status_key)
    alarms_key = topic_key(0, "/agv_fe/alarms", STATUS, ts.hash_rihs01(STATUS))
    alarm_statuses = ChannelSubscription(vehicle, alarms_key)
    graph = ChannelSubscription(vehicle, "@ros2_lv/0/**", liveliness=True)
    bridge = subprocess.Popen(
        [sys.executable, "-m", "agv_fe", "ros2-bridge", "--map", str(tmp_path / "map.yaml"), "--vehicle", VEHICLE,
         "--connect", router.endpoint, "--duration", "9", "--wait", "60", "--republish", "/agv_fe/status",
         "--republish-alarms", "/agv_fe/alarms", "--log", str(tmp_path / "back.jsonl")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    sent = {column: set() for column in ("vx", "r", "torque", "steer")}
    try:
        for period, since in paced_periods(counter, VEHICLE, MAX_PERIODS, lambda: bridge.poll() is None):
            k = period % len(y)
            now_ns = time.time_ns()
            # the command's steering angle is a float32, as _drive's u already is
            steer = float(np.float32(u[k, 1] + (STEER_BIAS_RAD if since >= STEER_BIAS_FROM else 0.0)))
            for topic, raw in messages(ts, y[k, 0], y[k, 1], u[k, 0], steer, now_ns).items():
                if topic == "/odom" and 200 <= since < 250:  # the odometry stops for 0.5 s
                    continue
                publishers[topic].put(raw, attachment=rmw_attachment(period, now_ns, GID))
            sent["vx"].add(y[k, 0]), sent["r"].add(y[k, 1]), sent["torque"].add(u[k, 0]), sent["steer"].add(steer)
            if since == 100:  # bad input, once each: malformed CDR, another type definition, another type, a NaN
                publishers["/drive_torque"].put(b"\x00\x01\x00\x00\x07", attachment=rmw_attachment(0, now_ns, GID))
                other_definition.put(messages(ts, 1.0, 1.0, 1.0, 1.0, now_ns)["/imu"])
                other_type.put(messages(ts, 1.0, 1.0, 1.0, 1.0, now_ns)["/drive_torque"])
                publishers["/odom"].put(messages(ts, float("nan"), 0.0, 0.0, 0.0, now_ns)["/odom"])
        out, err = bridge.communicate(timeout=60)
    finally:
        if bridge.poll() is None:
            bridge.kill()
            bridge.wait(timeout=10)
        time.sleep(0.2)
        received_statuses = statuses.drain()
        received_alarms = alarm_statuses.drain()
        tokens = [rx.key for rx in graph.drain() if rx.put]
        statuses.close()
        alarm_statuses.close()
        graph.close()
        counter.close()
        for publisher in (*publishers.values(), other_definition, other_type):
            publisher.undeclare()
        close_session(vehicle)
    assert bridge.returncode == 0, err
    assert "1 undecodable, 1 not finite, 2 of another type or type definition" in out, out
    sampled, ticks, stale = grid_account(out)
    # 0.5 s without odometry, less the 0.1 s it may be held; v_x alone (r is stale only when everything is)
    assert stale["vx"] >= 35 and stale["vx"] - stale.get("r", 0) <= 60, out
    meas = counter.meas[VEHICLE]
    seqs = [m.seq for m in meas]
    assert seqs == sorted(seqs) and seqs[-1] < ticks and len(meas) > 400
    assert len(meas) == sampled  # every tick sampled was sent; the others are a gap the service counts
    # every value sent is one the vehicle's messages carried, sign and scale undone (torque halved, r negated)
    assert all(m.vx_mps in sent["vx"] and m.r_radps in sent["r"] for m in meas)
    assert all(m.torque_nm in sent["torque"] and m.steer_rad in sent["steer"] for m in meas)
    assert all(m.grade_rad is None for m in meas)  # no grade mapped: the measurements carry none
    back = [json.loads(line) for line in (tmp_path / "back.jsonl").read_text().splitlines()]
    estimates = [b["message"] for b in back if b["type"] == "estimate"]
    # most of the 9 s on an idle machine (over 300); a loaded service lags the bridge's end by seconds (256 came)
    assert len(estimates) > 150 and {e["vehicle"] for e in estimates} == {VEHICLE}
    assert {e["seq"] for e in estimates} <= set(seqs)
    assert f"sent {len(meas)} measurements" in out
    # the estimates as diagnostic_msgs/DiagnosticStatus on the topic's rmw_zenoh key, decoded by rosbags
    by_seq = {e["seq"]: e for e in estimates}
    decoded = [ts.deserialize_cdr(rx.payload, STATUS) for rx in received_statuses]
    assert len(decoded) > 150 and f"republished {len(decoded)} estimates on {status_key}" in out
    for status in decoded:
        values = {kv.key: kv.value for kv in status.values}
        estimate = by_seq[int(values["seq"])]
        assert status.hardware_id == VEHICLE and status.level == LEVELS[estimate["level"]]
        assert float(values["torque_fault"]) == estimate["torque_fault"]
        assert float(values["steer_fault"]) == estimate["steer_fault"]
    # the service's alarms (the steering fault at least) as DiagnosticStatus on their topic's rmw_zenoh key
    alarms = [b["message"] for b in back if b["type"] == "alarm"]
    assert any(a["kind"] == "steer_fault" and a["state"] == "raised" for a in alarms), alarms
    decoded_alarms = [ts.deserialize_cdr(rx.payload, STATUS) for rx in received_alarms]
    assert len(decoded_alarms) == len(alarms) and f"republished {len(alarms)} alarms on {alarms_key}" in out
    for status, alarm in zip(decoded_alarms, alarms, strict=True):
        values = {kv.key: kv.value for kv in status.values}
        assert [values[k] for k in ALARM_FIELDS] == [alarm[k] for k in ALARM_FIELDS]
        assert status.name == f"agv_fe/{VEHICLE}/{alarm['kind']}" and status.hardware_id == VEHICLE
        assert status.level == (0 if alarm["state"] == "cleared" else LEVELS[alarm["level"]])
    # and the ROS 2 graph sees the bridge's node and its publishers (liveliness tokens of rmw_zenoh's format)
    assert any(key.endswith("/0/0/NN/%/%/agv_fe_bridge") for key in tokens), tokens
    assert any(f"/0/1/MP/%/%/agv_fe_bridge/%agv_fe%status/{dds_type_name(STATUS)}/" in key for key in tokens), tokens
    assert any(f"/0/2/MP/%/%/agv_fe_bridge/%agv_fe%alarms/{dds_type_name(STATUS)}/" in key for key in tokens), tokens


#: The alarm events the service's side puts, and the DiagnosticStatus level each must become (module docstring of
#: AlarmRepublisher): a steering alarm raised, escalated, acknowledged while raised, cleared, acknowledged after
#: it cleared (closed); a STALE alarm; the acknowledgement of an alarm the bridge never saw raised.
ALARM_EVENTS = [
    (dict(id="al-1", kind="steer_fault", level="WARN", state="raised", value=-0.012, threshold=0.01,
          message="|delta_f| >= 0.01 rad for 0.5 s"), 1),
    (dict(id="al-1", kind="steer_fault", level="FAULT", state="raised", value=-0.031, threshold=0.02,
          message="|delta_f| >= 0.02 rad for 0.5 s"), 2),
    (dict(id="al-1", kind="steer_fault", level="FAULT", state="acknowledged", value=-0.031, threshold=0.02), 2),
    (dict(id="al-1", kind="steer_fault", level="FAULT", state="cleared", value=-0.031, threshold=0.02), 0),
    (dict(id="al-1", kind="steer_fault", level="FAULT", state="acknowledged", value=-0.031, threshold=0.02), 0),
    (dict(id="al-2", kind="stale", level="STALE", state="raised", message="no measurement for 1.2 s"), 3),
    (dict(id="al-3", kind="out_of_domain", level="WARN", state="acknowledged"), 1),
]  # fmt: skip
#: at most this many rounds of 10 ms waiting for the republished statuses: only against a hang
MAX_ROUNDS = 6_000


def test_alarm_events_become_diagnostic_statuses_on_their_rmw_zenoh_key(router):
    """The service's alarm events (agv_protocol.wire's encoder, on the vehicle's alarm key) republished by the
    bridge's AlarmRepublisher beside its EstimateRepublisher, decoded by a ROS 2 node's side from CDR on the topic's
    rmw_zenoh key; the graph sees one node and its two publishers."""
    from agv_protocol.wire import Alarm, vehicle_key
    from edge_client.ros2_bridge import AlarmRepublisher, EstimateRepublisher

    ts = store(RosMapping.model_validate(yaml.safe_load(MAPPING)))
    alarms_key = topic_key(0, "/agv_fe/alarms", STATUS, ts.hash_rihs01(STATUS))
    service, bridge, vehicle = (open_session(router.client()) for _ in range(3))
    statuses = ChannelSubscription(vehicle, alarms_key)
    graph = ChannelSubscription(vehicle, "@ros2_lv/0/**", liveliness=True)
    events = [Alarm(vehicle=VEHICLE, t_ns=1_700_000_000_000_000_000 + i, **e).encode() for i, (e, _) in
              enumerate(ALARM_EVENTS)]  # fmt: skip
    alarm_publisher = service.declare_publisher(vehicle_key(VEHICLE, "alarm"))
    last_name = f"agv_fe/{VEHICLE}/{ALARM_EVENTS[-1][0]['kind']}"
    received = []
    try:
        with (
            EstimateRepublisher(bridge, ts, 0, "/agv_fe/status", VEHICLE, "agv", entity_id=1),
            AlarmRepublisher(bridge, ts, 0, "/agv_fe/alarms", VEHICLE, "agv", entity_id=2) as republisher,
        ):
            # the first event again until its status comes back (the path is up), then the others once each, in
            # order behind the repeats still on their way
            for _ in range(MAX_ROUNDS):
                alarm_publisher.put(events[0])
                time.sleep(0.01)
                if received := statuses.drain():
                    break
            alarm_publisher.put(b"{not an alarm")
            for event in events[1:]:
                alarm_publisher.put(event)
            for _ in range(MAX_ROUNDS):
                if received and ts.deserialize_cdr(received[-1].payload, STATUS).name == last_name:
                    break
                time.sleep(0.01)
                received += statuses.drain()
            sent, bad = republisher.sent, republisher.bad
            tokens = [rx.key for rx in graph.drain() if rx.put]  # declared before any status was put
    finally:
        alarm_publisher.undeclare()
        statuses.close()
        graph.close()
        for session in (service, bridge, vehicle):
            close_session(session)
    repeats = len(received) - (len(events) - 1)  # statuses of the first event
    assert repeats >= 1 and bad == 1 and sent == len(received), (repeats, bad, sent)
    assert all(rx.key == alarms_key for rx in received)
    decoded = [ts.deserialize_cdr(rx.payload, STATUS) for rx in received]
    assert all(status == decoded[0] for status in decoded[:repeats])
    for status, (event, level) in zip(decoded[repeats - 1 :], ALARM_EVENTS, strict=True):
        values = {kv.key: kv.value for kv in status.values}
        assert (status.level, status.name, status.hardware_id) == (level, f"agv_fe/{VEHICLE}/{event['kind']}", VEHICLE)
        assert [values[k] for k in ALARM_FIELDS] == [event[k] for k in ALARM_FIELDS]
        assert ("value" in values, "threshold" in values) == ("value" in event, "threshold" in event)
        if "value" in event:
            assert float(values["value"]) == event["value"] and float(values["threshold"]) == event["threshold"]
        assert status.message == (f"{event['state']}: {event['message']}" if "message" in event else event["state"])
    # one node, its two publishers numbered 1 and 2
    assert sum(key.endswith("/0/0/NN/%/%/agv_fe_bridge") for key in tokens) == 1, tokens
    assert any(f"/0/1/MP/%/%/agv_fe_bridge/%agv_fe%status/{dds_type_name(STATUS)}/" in key for key in tokens), tokens
    assert any(f"/0/2/MP/%/%/agv_fe_bridge/%agv_fe%alarms/{dds_type_name(STATUS)}/" in key for key in tokens), tokens


def test_a_mapping_the_bridge_cannot_use_is_refused_before_it_joins_the_network(tmp_path, capsys):
    from agv_fe.cli import main

    cases = {
        "unknown type": (MAPPING.replace("std_msgs/msg/Float64", "acme_msgs/msg/Torque"),
                         "unknown message type acme_msgs/msg/Torque (mapped to torque)"),
        "missing field": (MAPPING.replace("drive.steering_angle", "drive.angle"), "has no field 'angle'"),
        "bad topic": (MAPPING.replace("/odom", "odom"), "vx.topic"),
    }  # fmt: skip
    for name, (text, message) in cases.items():
        (tmp_path / "map.yaml").write_text(text)
        code = main(["ros2-bridge", "--map", str(tmp_path / "map.yaml"), "--vehicle", VEHICLE, "--connect",
                     "tcp/127.0.0.1:9"])  # fmt: skip
        assert code == 2 and message in capsys.readouterr().err, name


def test_republished_topics_are_checked_before_the_bridge_joins_the_network(tmp_path, capsys):
    from agv_fe.cli import main

    (tmp_path / "map.yaml").write_text(MAPPING)
    cases = {
        "not fully qualified": (["--republish-alarms", "agv_fe/alarms"],
                                "--republish-alarms: expected a fully qualified topic name such as /agv_fe/alarms"),
        "one topic for both": (["--republish", "/agv_fe/x", "--republish-alarms", "/agv_fe/x"],
                               "--republish and --republish-alarms name the same topic /agv_fe/x"),
    }  # fmt: skip
    for name, (flags, message) in cases.items():
        code = main(["ros2-bridge", "--map", str(tmp_path / "map.yaml"), "--vehicle", VEHICLE, "--connect",
                     "tcp/127.0.0.1:9", *flags])  # fmt: skip
        assert code == 2 and message in capsys.readouterr().err, name


@pytest.mark.network
def test_a_topic_that_never_comes_is_named(router, tmp_path, capsys):
    """No vehicle on the network: after --wait the bridge stops, naming every signal and its exact key."""
    from agv_fe.cli import main

    (tmp_path / "map.yaml").write_text(MAPPING)
    code = main(["ros2-bridge", "--map", str(tmp_path / "map.yaml"), "--vehicle", VEHICLE, "--connect",
                 router.endpoint, "--wait", "0.5"])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and "missing or stale: vx (0/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_" in err, err
    assert "steer (0/cmd/ackermann_msgs::msg::dds_::AckermannDriveStamped_/RIHS01_" in err


@pytest.mark.network
def test_a_mapped_grade_topic_goes_with_each_measurement_and_a_grade_that_stops_is_counted_by_name(
    router, tmp_path, capsys
):
    """The bridge with the grade mapped (a Float64 topic [rad]): every measurement carries a grade that was
    published; 0.5 s without it is a gap counted under ``grade``. No service: the test's subscriber takes the
    measurements."""
    from agv_fe.cli import main

    ts = store(RosMapping.model_validate(yaml.safe_load(GRADE_MAPPING)))
    (tmp_path / "map.yaml").write_text(GRADE_MAPPING)
    y, u = _drive()
    grade = road_grade(0.01 * np.arange(len(y)))
    vehicle = open_session(router.client())
    counter = Counter(vehicle)
    counter.routed(router)
    kinds = {**TOPICS, GRADE_TOPIC: GRADE_TYPE}
    publishers = {t: vehicle.declare_publisher(topic_key(0, t, k, ts.hash_rihs01(k))) for t, k in kinds.items()}
    sent_grades: set[float] = set()
    stop = threading.Event()

    def send() -> None:  # the vehicle's nodes, at 100 Hz, until the bridge is done (bounded by MAX_PERIODS)
        for period, since in paced_periods(counter, VEHICLE, MAX_PERIODS, lambda: not stop.is_set()):
            k = period % len(y)
            now_ns = time.time_ns()
            raws = messages(ts, y[k, 0], y[k, 1], u[k, 0], u[k, 1], now_ns)
            if not 200 <= since < 250:  # the grade stops for 0.5 s
                raws[GRADE_TOPIC] = grade_message(ts, float(grade[k]))
                sent_grades.add(float(grade[k]))
            for topic, raw in raws.items():
                publishers[topic].put(raw, attachment=rmw_attachment(period, now_ns, GID))

    sender = threading.Thread(target=send, daemon=True)
    sender.start()
    try:
        code = main(["ros2-bridge", "--map", str(tmp_path / "map.yaml"), "--vehicle", VEHICLE, "--connect",
                     router.endpoint, "--duration", "4", "--wait", "60"])  # fmt: skip
    finally:
        stop.set()
        sender.join(timeout=30)
        counter.close()
        for publisher in publishers.values():
            publisher.undeclare()
        close_session(vehicle)
    out = capsys.readouterr().out
    assert code == 0, out
    assert topic_key(0, GRADE_TOPIC, GRADE_TYPE, ts.hash_rihs01(GRADE_TYPE)) in out  # subscribed to its key
    assert re.search(r"used vx \d+, r \d+, torque \d+, steer \d+, grade \d+;", out), out
    sampled, _, stale = grid_account(out)
    # 0.5 s without the grade, less the 0.1 s it may be held; the grade alone
    assert stale["grade"] >= 35 and stale["grade"] - stale.get("vx", 0) <= 60, out
    meas = counter.meas[VEHICLE]
    assert len(meas) == sampled and len(meas) > 200, out
    assert all(m.grade_rad is not None and m.grade_rad in sent_grades for m in meas)
    assert len({m.grade_rad for m in meas}) > 30  # the grade followed, not one value held
    assert all(m.vx_mps in set(y[:, 0]) and m.torque_nm in set(u[:, 0]) for m in meas)
