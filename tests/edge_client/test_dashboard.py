"""The terminal dashboard: its table rendered to text, and the live command driven in tmux."""

import itertools
import shutil
import subprocess
import sys
import time
import uuid

import pytest

from agv_protocol.wire import Alarm, Estimate, vehicle_key
from edge_client.dashboard import DashboardModel
from edge_client.transport import Received

WIDTH = 80


class Clock:
    def __init__(self) -> None:
        self.now = 10_000_000_000

    def __call__(self) -> int:
        return self.now


def estimate(vehicle, seq=1, level="OK", torque=0.0, steer=0.0):
    return Estimate(
        vehicle=vehicle,
        seq=seq,
        t_ns=0,
        vx=12.345,
        vy=-0.123,
        r=0.05,
        torque_fault=torque,
        steer_fault=steer,
        in_domain=True,
        gain_version="abc",
        level=level,
    )


def alarm(vehicle, kind, state, serial=1):
    return Alarm(
        vehicle=vehicle, id=f"{vehicle}-{kind}-{serial}", kind=kind, level="FAULT", state=state, t_ns=0, value=1.0
    )


def received(message, kind, clock):
    return Received(vehicle_key(message.vehicle, kind), message.encode(), clock())


def test_table_shows_levels_estimates_and_alarms_in_80_columns():
    clock = Clock()
    model = DashboardModel(clock=clock)
    model.on_estimate(received(estimate("veh-ok"), "estimate", clock))
    model.on_estimate(received(estimate("veh-torque", level="FAULT", torque=111.6), "estimate", clock))
    model.on_estimate(received(estimate("veh-steer", level="FAULT", steer=-0.0292), "estimate", clock))
    model.on_alarm(received(alarm("veh-torque", "torque_fault", "raised"), "alarm", clock))
    model.on_alarm(received(alarm("veh-steer", "steer_fault", "raised"), "alarm", clock))
    model.on_alarm(received(alarm("veh-steer", "steer_fault", "cleared"), "alarm", clock))
    model.on_alive(Received(vehicle_key("veh-ok", "alive"), b"", clock()))
    model.on_alive(Received(vehicle_key("veh-waiting", "alive"), b"", clock()))
    model.settle()
    text = model.render_text(WIDTH)
    lines = text.splitlines()
    print("\n" + text)
    assert all(len(line) <= WIDTH for line in lines)
    assert "4 vehicles, 2 alive" in lines[0] and "2 FAULT, 1 OK" in lines[0]
    for column in ("vehicle", "level", "v_x", "v_y est", "T_f est", "δ_f est", "alarms"):
        assert column in lines[1]
    rows = {line.split()[0]: line for line in lines[2:]}
    # most severe first, then by id
    assert [line.split()[0] for line in lines[2:]] == ["veh-steer", "veh-torque", "veh-ok", "veh-waiting"]
    assert rows["veh-torque"].split()[1:7] == ["FAULT", "12.3", "-0.12", "+111.6", "+0.0000", "torque"]
    assert rows["veh-steer"].split()[1:7] == ["FAULT", "12.3", "-0.12", "+0.0", "-0.0292", "-"]  # cleared
    assert rows["veh-waiting"].split()[1:3] == ["-", "-"]
    # no estimate for 2 s: the dashboard says so itself
    clock.now += 2_500_000_000
    model.on_estimate(received(estimate("veh-ok", seq=2), "estimate", clock))
    model.settle()
    rows = {line.split()[0]: line for line in model.render_text(WIDTH).splitlines()[2:]}
    assert rows["veh-torque"].split()[1] == "STALE" and rows["veh-ok"].split()[1] == "OK"


def test_many_vehicles_are_cut_to_the_rows_that_fit():
    clock = Clock()
    model = DashboardModel(clock=clock)
    for i in range(30):
        level = "FAULT" if i == 17 else "OK"
        model.apply_estimate(estimate(f"veh-{i:03d}", level=level), clock())
    lines = model.render_text(WIDTH, max_rows=10).splitlines()
    assert lines[2].split()[:2] == ["veh-017", "FAULT"]
    assert lines[-1].strip() == "... and 20 more vehicles"
    assert len(lines) == 2 + 10 + 1


def test_bad_messages_are_counted_not_shown():
    clock = Clock()
    model = DashboardModel(clock=clock)
    model.on_estimate(Received("agv/v1/b00/x/y/z", b"{}", clock()))
    model.on_alarm(Received(vehicle_key("veh-1", "alarm"), b"not json", clock()))
    model.on_estimate(Received(vehicle_key("veh-2", "estimate"), b'{"v": 1}', clock()))
    model.settle()
    assert model.bad_messages == 3
    assert "veh-1" not in model.render_text(WIDTH)


#: The live test's vehicles' levels, sorted: two each of healthy, torque bias, steering bias
EXPECTED = ["FAULT"] * 4 + ["OK"] * 2


def _levels(frame: str) -> list[str]:
    """The level column of a dashboard frame's vehicle rows, sorted."""
    lines = [line for line in frame.splitlines() if line.strip()]
    return sorted(line.split()[1] for line in lines[2:] if len(line.split()) > 1)


@pytest.mark.network
@pytest.mark.skipif(shutil.which("tmux") is None, reason="tmux is not installed")
def test_live_dashboard_in_an_80_column_terminal(router, estimation_service):
    """`agv-fe dashboard` in tmux (80x24) during a fleet run: every vehicle shows, faults show, it redraws >= 2 Hz."""
    socket_name = f"agv-test-{uuid.uuid4().hex[:8]}"
    fleet = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "agv_fe",
            "fleet",
            "--connect",
            router.endpoint,
            "--vehicles",
            "6",
            "--duration",
            "14",
            "--scenario-mix",
            "healthy=1,torque_bias=1,steer_bias=1",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    tmux = ["tmux", "-L", socket_name]
    try:
        command = f"{sys.executable} -m agv_fe dashboard --connect {router.endpoint} --duration 30 --refresh 4"
        subprocess.run([*tmux, "new-session", "-d", "-x", "80", "-y", "24", command], check=True, timeout=10)
        frames = []
        # 11 s, or up to 14 s while the faults have not all reached FAULT yet (a loaded machine starts the fleet
        # late; the fleet's 14 s run keeps every vehicle alive till then)
        start = time.monotonic()
        while (now := time.monotonic()) < start + 11.0 or (now < start + 14.0 and _levels(frames[-1][1]) != EXPECTED):
            time.sleep(0.25)
            frame = subprocess.run(
                [*tmux, "capture-pane", "-p"], capture_output=True, text=True, check=True, timeout=10
            ).stdout
            frames.append((time.monotonic(), frame))
        last = frames[-1][1]
        print("\n" + last)
        lines = [line for line in last.splitlines() if line.strip()]
        assert all(len(line) <= WIDTH for line in lines)
        assert "6 vehicles, 6 alive" in lines[0]
        rows = {line.split()[0]: line.split() for line in lines[2:]}
        assert set(rows) == {f"veh-{i:03d}" for i in range(6)}
        assert _levels(last) == EXPECTED  # faults start at 2-5 s of the 14 s run
        # redrawn at least twice a second: over the last 2 s the screen changed at least 4 times
        recent = [frame for t, frame in frames if t >= frames[-1][0] - 2.0]
        changes = sum(1 for a, b in itertools.pairwise(recent) if a != b)
        assert changes >= 4
    finally:
        subprocess.run([*tmux, "kill-server"], capture_output=True, timeout=10)
        fleet.kill()
        fleet.wait(timeout=10)
