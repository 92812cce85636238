"""`agv-fe can-bridge` (edge_client/can_bridge.py) against real parts: frames of a simulated drive encoded with the
vehicle's DBC and sent on a python-can bus (its in-process ``virtual`` interface: no SocketCAN here, and vcan needs a
kernel module this machine lacks), the bridge's command running in the same process, a real router and service
answering with estimates; a frame that does not decode, frames of other messages and a signal that stops are counted
while the bridge keeps running; a mapped road grade goes with each measurement."""

from __future__ import annotations

import json
import math
import re
import shlex
import threading
import uuid
from pathlib import Path

import numpy as np
import pytest

can = pytest.importorskip("can")
cantools = pytest.importorskip("cantools")

from agv_fe.cli import main  # noqa: E402 - after the optional-dependency check
from edge_client.can_log import decode_frame, load_mapping, resolve  # noqa: E402
from edge_client.transport import close_session, open_session  # noqa: E402
from tests.edge_client.bridge_checks import paced_periods  # noqa: E402
from tests.edge_client.ros2_messages import road_grade  # noqa: E402
from tests.edge_client.test_can_log import DBC, GRADE_DBC, GRADE_MAPPING, MAPPING  # noqa: E402
from tests.edge_client.test_publisher import Counter  # noqa: E402
from tests.edge_client.test_ros2_bridge import _drive, grid_account  # noqa: E402

pytestmark = pytest.mark.network

VEHICLE = "can-car-1"
#: at most this many 10 ms periods of sending, whatever happens (the bridge runs 5 s once every signal came)
MAX_PERIODS = 3_000


def _frames(db, vx: float, r: float, torque: float, steer: float, grade: float | None = None) -> list:
    signals = {
        256: {"VehicleSpeed": vx * 3.6},
        257: {"YawRate": math.degrees(r)},
        258: {"WheelTorqueDemand": torque},
        259: {"RoadWheelAngleDemand": steer},
    }
    if grade is not None:
        signals[260] = {"GradeDeg": math.degrees(grade)}
    return [
        can.Message(arbitration_id=frame_id, data=db.encode_message(frame_id, values), is_extended_id=False)
        for frame_id, values in signals.items()
    ]


def _documented_command(tmp_path: Path, channel: str, endpoint: str) -> list[str]:
    """docs/integration.md's `can-bridge` command, its files, bus and router those of this test."""
    text = (Path(__file__).resolve().parents[2] / "docs" / "integration.md").read_text()
    section = text[text.index("\n## CAN, live\n") :]
    (line,) = [line for line in re.findall(r"```sh\n(.*?)```", section, re.S)[0].splitlines() if line.strip()]
    words = shlex.split(line)
    assert words[:2] == ["agv-fe", "can-bridge"]
    replace = {"vehicle.dbc": str(tmp_path / "vehicle.dbc"), "can-map.yaml": str(tmp_path / "map.yaml"),
               "socketcan": "virtual", "can0": channel, "car-1": VEHICLE, "tcp/127.0.0.1:7447": endpoint}  # fmt: skip
    return [replace.get(word, word) for word in words[1:]]


def _send(bus, db, wanted, counter, stop, decoded, signals, silent_id: int) -> None:
    """The vehicle's ECUs, at 100 Hz, until ``stop`` (bounded by MAX_PERIODS): sample k of ``signals`` (y, u and the
    grade, or None) as frames; from 200 periods after the first measurement arrived, no frame of ``silent_id`` for
    0.5 s; once each at 100 periods, a truncated frame and a frame of another message. ``decoded`` collects what
    the frames carry, per column, in the protocol's units."""
    y, u, grade = signals
    for period, since in paced_periods(counter, VEHICLE, MAX_PERIODS, lambda: not stop.is_set()):
        k = period % len(y)
        for frame in _frames(db, y[k, 0], y[k, 1], u[k, 0], u[k, 1], None if grade is None else grade[k]):
            if frame.arbitration_id == silent_id and 200 <= since < 250:
                continue
            bus.send(frame)
            for column, value in decode_frame(db, frame, wanted[frame.arbitration_id]) or []:
                decoded[column].add(value)
        if since == 100:  # bad input, once each: a truncated frame, a frame of another message
            bus.send(can.Message(arbitration_id=257, data=b"\x01", is_extended_id=False))
            bus.send(can.Message(arbitration_id=2047, data=bytes(8), is_extended_id=False))


def _bridge_beside_sender(args, link, decoded, signals, gap_frame, vehicle) -> int:
    """Run the bridge (``main(args)``) in this thread, which handles Ctrl-C as only the main thread may, while
    :func:`_send` puts ``signals`` on the bus (``link``: bus, DBC, wanted frames, counter; ``gap_frame`` stops for
    0.5 s) and records what it sent in ``decoded``; then close the bus, the counter and the test's session."""
    bus, db, wanted, counter = link
    stop = threading.Event()
    sender = threading.Thread(
        target=_send, args=(bus, db, wanted, counter, stop, decoded, signals, gap_frame), daemon=True
    )
    sender.start()
    try:
        return int(main(args))
    finally:
        stop.set()
        sender.join(timeout=30)
        bus.shutdown()
        counter.close()
        close_session(vehicle)


def test_the_bridge_turns_can_frames_into_measurements_and_estimates_come_back(
    router, estimation_service, tmp_path, capsys
):
    (tmp_path / "vehicle.dbc").write_text(DBC)
    (tmp_path / "map.yaml").write_text(MAPPING)
    db = cantools.database.load_string(DBC, "dbc")
    mapping = load_mapping(tmp_path / "map.yaml")
    wanted = resolve(db, mapping, "DBC")
    channel = f"agv-fe-{uuid.uuid4().hex[:8]}"  # a virtual bus of this test alone
    y, u = _drive()
    vehicle = open_session(router.client())  # the test's eyes on the measurements the bridge sends
    counter = Counter(vehicle)
    counter.routed(router)  # the bridge's first sample, seq 0, must reach it
    bus = can.Bus(interface="virtual", channel=channel)
    extra = ["--duration", "5", "--wait", "60", "--log", str(tmp_path / "back.jsonl")]
    args = [*_documented_command(tmp_path, channel, router.endpoint), *extra]
    decoded: dict[str, set[float]] = {column: set() for column in ("vx", "r", "torque", "steer")}
    signals = (y, u, None)  # and the speed (frame 256) stops for 0.5 s
    code = _bridge_beside_sender(args, (bus, db, wanted, counter), decoded, signals, 256, vehicle)
    out = capsys.readouterr().out
    assert code == 0, out
    assert "refused 1 undecodable, 0 not finite" in out and "; 1 of other messages" in out, out
    stale = int(out.split("ticks not sent for a stale column: vx ")[1].split()[0])
    assert 35 <= stale <= 60, out  # 0.5 s without the speed frame, less the 0.1 s it may be held
    meas = counter.meas[VEHICLE]
    seqs = [m.seq for m in meas]
    assert seqs[0] == 0 and seqs == sorted(seqs) and len(meas) > 300, (seqs[:3], out)
    assert len(meas) == seqs[-1] + 1 - stale  # every tick sent but the stale ones: a gap the service counts
    # every value sent is one the frames carried, in the protocol's units (km/h and deg/s undone by the mapping)
    assert all(m.vx_mps in decoded["vx"] and m.r_radps in decoded["r"] for m in meas)
    assert all(m.torque_nm in decoded["torque"] and m.steer_rad in decoded["steer"] for m in meas)
    assert len({m.vx_mps for m in meas}) > 30  # the signal followed (in 0.01 km/h steps), not one value held
    assert all(m.grade_rad is None for m in meas) and re.search(r"used vx \d+, r \d+, torque \d+, steer \d+;", out)
    back = [json.loads(line) for line in (tmp_path / "back.jsonl").read_text().splitlines()]
    estimates = [b["message"] for b in back if b["type"] == "estimate"]
    assert len(estimates) > 250 and {e["vehicle"] for e in estimates} == {VEHICLE}
    assert {e["seq"] for e in estimates} <= set(seqs)
    assert f"sent {len(meas)} measurements" in out


def test_a_mapped_grade_goes_with_each_measurement_and_a_grade_that_stops_is_counted_by_name(router, tmp_path, capsys):
    """The documented command with the grade mapped (ROAD_GRADE, in degrees): every measurement carries the grade
    of a frame, in rad; 0.5 s without it is a gap counted under ``grade``, as the speed's is. No service: the
    test's subscriber takes the measurements."""
    (tmp_path / "vehicle.dbc").write_text(GRADE_DBC)
    (tmp_path / "map.yaml").write_text(GRADE_MAPPING)
    db = cantools.database.load_string(GRADE_DBC, "dbc")
    wanted = resolve(db, load_mapping(tmp_path / "map.yaml"), "DBC")
    channel = f"agv-fe-{uuid.uuid4().hex[:8]}"
    y, u = _drive()
    vehicle = open_session(router.client())
    counter = Counter(vehicle)
    counter.routed(router)
    bus = can.Bus(interface="virtual", channel=channel)
    args = [*_documented_command(tmp_path, channel, router.endpoint), "--duration", "4", "--wait", "60"]
    decoded: dict[str, set[float]] = {column: set() for column in ("vx", "r", "torque", "steer", "grade")}
    signals = (y, u, road_grade(0.01 * np.arange(len(y))))  # and the grade (frame 260) stops for 0.5 s
    code = _bridge_beside_sender(args, (bus, db, wanted, counter), decoded, signals, 260, vehicle)
    out = capsys.readouterr().out
    assert code == 0, out
    assert re.search(r"used vx \d+, r \d+, torque \d+, steer \d+, grade \d+;", out), out
    sampled, _, stale = grid_account(out)
    # 0.5 s without the grade frame, less the 0.1 s it may be held; the grade alone
    assert stale["grade"] >= 35 and stale["grade"] - stale.get("vx", 0) <= 60, out
    meas = counter.meas[VEHICLE]
    seqs = [m.seq for m in meas]
    assert seqs[0] == 0 and len(meas) > 200 and len(meas) == sampled, (seqs[:3], out)
    assert all(m.grade_rad is not None and m.grade_rad in decoded["grade"] for m in meas)
    assert len({m.grade_rad for m in meas}) > 30  # the grade followed, not one value held
    assert all(m.vx_mps in decoded["vx"] and m.steer_rad in decoded["steer"] for m in meas)


def test_a_silent_bus_and_an_interface_that_cannot_open_are_named(router, tmp_path, capsys):
    (tmp_path / "vehicle.dbc").write_text(DBC)
    (tmp_path / "map.yaml").write_text(MAPPING)
    common = ["can-bridge", "--dbc", str(tmp_path / "vehicle.dbc"), "--map", str(tmp_path / "map.yaml"),
              "--vehicle", VEHICLE, "--connect", router.endpoint]  # fmt: skip
    silent = f"agv-fe-{uuid.uuid4().hex[:8]}"
    assert main([*common, "--interface", "virtual", "--channel", silent, "--wait", "0.5"]) != 0
    err = capsys.readouterr().err
    assert "missing or stale: vx (WHEEL_SPEEDS.VehicleSpeed), r (IMU_RATES.YawRate)" in err, err
    assert main([*common, "--interface", "no-such-interface"]) != 0
    assert "cannot open CAN interface 'no-such-interface' channel 'can0'" in capsys.readouterr().err
    (tmp_path / "bad.yaml").write_text(MAPPING.replace("YawRate", "YawRat"))
    bad = [arg.replace("map.yaml", "bad.yaml") for arg in common]
    assert main([*bad, "--interface", "virtual", "--channel", silent]) != 0
    assert "message 'IMU_RATES' has no signal 'YawRat' (mapped to r)" in capsys.readouterr().err
