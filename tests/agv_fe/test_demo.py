"""`agv-fe demo` as a new user runs it.

With ``--duration 20``: every injected fault alarmed, no healthy vehicle. Without
it, in a terminal: the live table until Ctrl-C, then the report and nothing left running; nothing
left either when the terminal closes under it.
"""

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest


def test_demo_alarms_every_injected_fault_and_no_healthy_vehicle(tmp_path):
    summary_path = tmp_path / "summary.json"
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "agv_fe",
            "demo",
            "--duration",
            "20",
            "--data-dir",
            str(tmp_path / "data"),
            "--http-port",
            "0",
            "--zenoh-port",
            "0",
            "--summary-json",
            str(summary_path),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stdout + out.stderr
    # the closing summary says what its columns mean and where everything was kept
    assert "columns: injected = " in out.stdout and "late ticks = " in out.stdout
    assert f"kept in {tmp_path / 'data'}: service.sqlite3" in out.stdout
    assert (tmp_path / "data" / "service.sqlite3").exists() and (tmp_path / "data" / "fleet.log").exists()
    summary = json.loads(summary_path.read_text())
    vehicles = summary["vehicles"]
    assert len(vehicles) == 20
    faulty = [v for v in vehicles if v["onset_s"] is not None]
    healthy = [v for v in vehicles if v["onset_s"] is None]
    assert len(faulty) >= 10 and len(healthy) >= 6
    for v in faulty:
        expected = "torque_fault" if v["injected"].startswith("T_f") else "steer_fault"
        assert v["fault_alarms"] == [expected], v
        assert v["first_alarm_after_onset_s"] is not None, v
    for v in healthy:
        assert v["fault_alarms"] == [], v
    assert summary["false_alarms"] == 0
    # every sample sent, and an estimate back for each; on a loaded machine 9-38 of 40,000 did not come back (the
    # service drops an estimate that waits too long, zenoh.estimate_congestion "drop" and VEHICLE_QUEUE_MAX_AGE_S,
    # or it came after the fleet's wait for the last ones)
    assert summary["lost"] == 0 and summary["sent"] == 20 * 2000
    assert summary["sent"] - 40 <= summary["estimates"] <= summary["sent"]
    # every vehicle carried a load on hills and reported both (what --level-empty leaves out)
    assert all("hills ±" in v["conditions"] for v in vehicles)
    assert sum(" kg, " in v["conditions"] for v in vehicles) >= len(vehicles) // 2  # loads of 0-25 %, to 10 kg
    # what the user reads: where to look, then the per-vehicle report
    assert "web dashboard" in out.stdout and "/docs" in out.stdout
    assert f"faulty vehicles alarmed {len(faulty)}/{len(faulty)}; false alarms 0" in " ".join(out.stdout.split())


def test_the_demo_fleet_carries_loads_on_hills_unless_told_level_empty(tmp_path):
    from agv_fe.cli import build_parser
    from agv_fe.commands.demo import _fleet_arguments

    parser = build_parser()
    default = _fleet_arguments(parser.parse_args(["demo"]), "tcp/127.0.0.1:7447", tmp_path / "s.json")
    plain = _fleet_arguments(parser.parse_args(["demo", "--level-empty"]), "tcp/127.0.0.1:7447", tmp_path / "s.json")
    assert default[-2:] == ["--loads", "--hills"] and "--loads" not in plain and "--hills" not in plain
    assert default[: len(plain)] == plain


# -- the open-ended demo in a terminal: Ctrl-C, and the terminal closed ------------------------------

#: Bounds of the interactive demo tests [s]: service design + fleet start, then the shutdown.
DASHBOARD_TIMEOUT_S = 90.0
SHUTDOWN_TIMEOUT_S = 60.0
DEMO_VEHICLES = {f"veh-{i:03d}" for i in range(20)}


@dataclass(frozen=True)
class ProcessInfo:
    pid: int
    ppid: int
    start_ticks: int  # field 22 of /proc/PID/stat: tells a process from a later one with the same pid
    state: str
    cmdline: str


def process_table() -> dict[int, ProcessInfo]:
    """Every process of the machine, from /proc (zombies included, with state 'Z')."""
    table = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
        except OSError:  # it ended while we looked
            continue
        fields = stat[stat.rindex(")") + 2 :].split()  # after "pid (comm) ": state, ppid, ...
        table[int(entry.name)] = ProcessInfo(int(entry.name), int(fields[1]), int(fields[19]), fields[0], cmdline)
    return table


def descendants(root: int) -> list[ProcessInfo]:
    table = process_table()
    children: dict[int, list[int]] = {}
    for info in table.values():
        children.setdefault(info.ppid, []).append(info.pid)
    found: list[ProcessInfo] = []
    todo = list(children.get(root, []))
    while todo and len(found) < 1000:
        pid = todo.pop()
        found.append(table[pid])
        todo.extend(children.get(pid, []))
    return found


def still_running(processes: list[ProcessInfo]) -> list[ProcessInfo]:
    """Those of ``processes`` still running (the same process, and not a zombie)."""
    now = process_table()
    return [
        p for p in processes if p.pid in now and now[p.pid].start_ticks == p.start_ticks and now[p.pid].state != "Z"
    ]


#: Runs a command and writes its exit code to a file: tmux may leave a dead pane unreaped, without a status.
#: Ctrl-C signals the terminal's whole foreground group; the wrapper's no-op SIGINT handler (which exec resets
#: to the default in the command) leaves it to the command.
RECORD_EXIT = (
    "import signal, subprocess, sys\n"
    "signal.signal(signal.SIGINT, lambda *_: None)\n"
    "code = subprocess.call(sys.argv[2:])\n"
    "open(sys.argv[1], 'w').write(f'{code}\\n')\n"
)


class DemoInTmux:
    """`agv-fe demo` (no --duration, free ports, its own data dir) in a detached 80x30 tmux terminal.

    With ``exit_code_file``, the pane runs the demo under :data:`RECORD_EXIT`; otherwise it runs the demo itself.
    """

    def __init__(self, tmp_path: Path, exit_code_file: Path | None = None) -> None:
        self.data_dir = tmp_path / f"demo-{uuid.uuid4().hex[:8]}"
        self.exit_code_file = exit_code_file
        config = tmp_path / "tmux.conf"
        # remain-on-exit keeps the pane and its output after the demo ends
        config.write_text("set -g remain-on-exit on\nset -g history-limit 10000\n")
        self.tmux = ["tmux", "-u", "-L", f"agv-demo-{uuid.uuid4().hex[:8]}", "-f", str(config)]
        command = [sys.executable, "-m", "agv_fe", "demo", "--data-dir", str(self.data_dir)]
        command += ["--http-port", "0", "--zenoh-port", "0"]
        if exit_code_file is not None:
            command = [sys.executable, "-c", RECORD_EXIT, str(exit_code_file), *command]
        # rich believes LINES/COLUMNS over the terminal's size; under pytest, readline may have exported 24x80
        env = {k: v for k, v in os.environ.items() if k not in ("LINES", "COLUMNS")}
        # several arguments: tmux runs the command itself, without a shell
        tmux_command = [*self.tmux, "new-session", "-d", "-s", "demo", "-x", "80", "-y", "30", *command]
        subprocess.run(tmux_command, env=env, check=True, timeout=10)
        self.server_pid = int(self.pane("#{pid}"))
        self.socket_path = Path(self.pane("#{socket_path}"))
        self.pane_process = process_table()[int(self.pane("#{pane_pid}"))]
        self.demo_process: ProcessInfo | None = None
        self.children: list[ProcessInfo] = []

    def pane(self, fmt: str) -> str:
        command = [*self.tmux, "display-message", "-p", "-t", "demo", fmt]
        return subprocess.run(command, capture_output=True, text=True, check=True, timeout=10).stdout.strip()

    def screen(self, history: bool = False) -> str:
        """The visible screen, or (``history``) everything printed, wrapped lines joined."""
        extra = ["-J", "-S", "-"] if history else []
        command = [*self.tmux, "capture-pane", "-p", "-t", "demo", *extra]
        return subprocess.run(command, capture_output=True, text=True, check=True, timeout=10).stdout

    def tree(self) -> list[ProcessInfo]:
        """The pane's process and all its descendants, now."""
        return [self.pane_process, *descendants(self.pane_process.pid)]

    def wait_for_the_fleet_table(self) -> str:
        """The screen once the live table shows all 20 vehicles with an estimate; records the demo's processes."""
        deadline = time.monotonic() + DASHBOARD_TIMEOUT_S
        while time.monotonic() < deadline:
            time.sleep(0.5)
            if not still_running([self.pane_process]):
                pytest.fail(f"the demo ended before its table showed the fleet:\n{self.screen(history=True)}")
            frame = self.screen()
            rows = {line.split()[0]: line.split() for line in frame.splitlines() if line.startswith("veh-")}
            complete = "20 vehicles, 20 alive" in frame and set(rows) == DEMO_VEHICLES
            if complete and all(row[1] in ("OK", "WARN", "FAULT") for row in rows.values()):
                demo_command = f"{sys.executable} -m agv_fe demo "
                self.demo_process = next(p for p in self.tree() if p.cmdline.startswith(demo_command))
                self.children = descendants(self.demo_process.pid)
                return frame
        pytest.fail(f"no table of 20 vehicles within {DASHBOARD_TIMEOUT_S:.0f} s:\n{self.screen(history=True)}")

    def wait_for_exit_code(self) -> int | None:
        """The demo's exit code once it has exited, None if it still runs after SHUTDOWN_TIMEOUT_S."""
        assert self.exit_code_file is not None
        deadline = time.monotonic() + SHUTDOWN_TIMEOUT_S
        while time.monotonic() < deadline:
            if self.exit_code_file.exists() and self.exit_code_file.read_text().endswith("\n"):
                return int(self.exit_code_file.read_text())
            time.sleep(0.25)
        return None

    def strays(self, endpoint: str) -> list[ProcessInfo]:
        """Processes left of this demo: its own, or anything naming its data dir or Zenoh endpoint."""
        marks = (str(self.data_dir), endpoint)
        named = [
            p
            for p in process_table().values()
            if p.pid != self.server_pid and p.state != "Z" and any(mark in p.cmdline for mark in marks)
        ]
        mine = still_running([p for p in [self.demo_process, *self.children] if p is not None])
        return mine + [p for p in named if p not in mine]

    def close(self) -> None:
        """Close the terminal; once the demo is gone, kill whatever of it outlived it (after a failure)."""
        processes = {p.pid: p for p in [*self.tree(), *self.children]}
        subprocess.run([*self.tmux, "kill-server"], capture_output=True, timeout=10)
        deadline = time.monotonic() + SHUTDOWN_TIMEOUT_S
        leaders = [p for p in [self.pane_process, self.demo_process] if p is not None]
        while still_running(leaders) and time.monotonic() < deadline:
            time.sleep(0.25)
        for p in still_running(list(processes.values())):
            os.kill(p.pid, signal.SIGKILL)
        self.socket_path.unlink(missing_ok=True)  # kill-server leaves it behind


@pytest.fixture
def tmux_available() -> None:
    if shutil.which("tmux") is None:
        pytest.skip("tmux is not installed")


@contextmanager
def demo_in_tmux(tmp_path: Path, exit_code_file: Path | None = None) -> Iterator[DemoInTmux]:
    demo = DemoInTmux(tmp_path, exit_code_file)
    try:
        yield demo
    finally:
        demo.close()


def service_endpoint(output: str) -> str:
    found = re.search(r"Zenoh router (tcp/127\.0\.0\.1:\d+)", output)
    assert found is not None, output
    return found.group(1)


def assert_the_demo_started_the_service_and_the_fleet(children: list[ProcessInfo]) -> None:
    commands = [f"{c.cmdline} " for c in children]
    assert any(" serve " in c for c in commands), commands
    assert any(" fleet " in c for c in commands), commands


@pytest.mark.network
@pytest.mark.usefixtures("tmux_available")
def test_open_ended_demo_stops_cleanly_on_ctrl_c(tmp_path: Path) -> None:
    """`agv-fe demo` in an 80x30 terminal: the live table, then Ctrl-C: exit 0, the report, nothing left."""
    with demo_in_tmux(tmp_path, exit_code_file=tmp_path / "exit-code") as demo:
        frame = demo.wait_for_the_fleet_table()
        print("\n" + frame)
        assert all(len(line) <= 80 for line in frame.splitlines())
        assert_the_demo_started_the_service_and_the_fleet(demo.children)

        pressed = time.monotonic()
        subprocess.run([*demo.tmux, "send-keys", "-t", "demo", "C-c"], check=True, timeout=10)
        exit_code = demo.wait_for_exit_code()
        shutdown_s = time.monotonic() - pressed
        output = demo.screen(history=True)
        assert exit_code is not None, f"still running {SHUTDOWN_TIMEOUT_S:.0f} s after Ctrl-C:\n{output}"
        print(f"\nexited {shutdown_s:.1f} s after Ctrl-C, code {exit_code}\n" + output[output.find("stopping ...") :])
        assert exit_code == 0, output

        # the report: a row per vehicle, then the totals line
        assert "stopping ..." in output, output
        report = output[output.index("stopping ...") :]
        assert "fleet summary" in report
        assert {line.split()[0] for line in report.splitlines() if re.match(r"veh-\d{3}\b", line)} == DEMO_VEHICLES
        totals = " ".join(report.split())  # rich wraps the totals line at 80 columns
        assert re.search(r"20 vehicles, [\d.]+ s at [\d.]+ Hz .* faulty vehicles alarmed \d+/\d+", totals), report
        assert len(json.loads((demo.data_dir / "fleet-summary.json").read_text())["vehicles"]) == 20
        assert demo.strays(service_endpoint(output)) == []


@pytest.mark.network
@pytest.mark.usefixtures("tmux_available")
def test_open_ended_demo_stops_everything_when_its_terminal_closes(tmp_path: Path) -> None:
    """The terminal closed under the running demo (SIGHUP): the service and the fleet stop too."""
    with demo_in_tmux(tmp_path) as demo:
        demo.wait_for_the_fleet_table()
        assert_the_demo_started_the_service_and_the_fleet(demo.children)
        assert demo.demo_process == demo.pane_process  # the terminal's own process: it gets the hangup
        endpoint = service_endpoint(demo.screen(history=True))
        watched = [demo.pane_process, *demo.children]

        closed = time.monotonic()
        subprocess.run([*demo.tmux, "kill-server"], check=True, timeout=10)  # hangs up the terminal
        while still_running(watched) and time.monotonic() - closed < SHUTDOWN_TIMEOUT_S:
            time.sleep(0.25)
        print(f"\nall stopped {time.monotonic() - closed:.1f} s after the terminal closed")
        assert still_running(watched) == [] and demo.strays(endpoint) == []
        # the fleet was stopped in order, not killed: it wrote its summary
        assert len(json.loads((demo.data_dir / "fleet-summary.json").read_text())["vehicles"]) == 20
