"""Every example of docs/integration.md, copied from the page and run: the ROS 2 mapping, `replay` of a bag and of a
CAN log, and against the real service the bridge, `publish-csv` of a bag and the plain-Zenoh vehicle. (The C
example is run by tests/test_c_header.py.)"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

pytest.importorskip("rosbags")
pytest.importorskip("cantools")

from rosbags.rosbag2 import StoragePlugin, Writer

from agv_fe.cli import main
from edge_client.ros2 import RosMapping, typestore_for
from edge_client.ros2_bridge import rmw_attachment, topic_key
from edge_client.scenario import REALISTIC_NOISE, Manoeuvre, Scenario, SpeedPoint
from edge_client.simulation import simulate_plant
from edge_client.transport import close_session, open_session
from tests.edge_client.ros2_messages import TOPICS, messages
from tests.edge_client.test_can_log import DBC, write_log

DOC = Path(__file__).resolve().parents[2] / "docs" / "integration.md"
DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"


def blocks(heading: str, language: str) -> list[str]:
    """The fenced blocks of ``language`` in the section under ``heading`` (up to the next '## ')."""
    text = DOC.read_text()
    start = text.index(f"\n## {heading}\n")
    end = text.find("\n## ", start + 1)
    section = text[start : end if end > 0 else len(text)]
    return re.findall(rf"```{language}\n(.*?)```", section, re.S)


def commands(heading: str) -> list[list[str]]:
    return [shlex.split(line) for block in blocks(heading, "sh") for line in block.splitlines() if line.strip()]


@pytest.fixture(scope="module")
def drive():
    scenario = Scenario(
        name="doc", duration_s=6.0, initial_speed_mps=10.0, speed_profile=(SpeedPoint(t_s=0.0, speed_mps=10.0),),
        manoeuvres=(Manoeuvre(kind="lane_change", start_s=2.0, duration_s=3.0, amplitude_rad=0.02),),
        noise=REALISTIC_NOISE, seed=3,
    )  # fmt: skip
    return simulate_plant([scenario])


@pytest.fixture
def ros2_files(tmp_path, drive, monkeypatch):
    """The page's mapping as ros2-map.yaml and the drive as the bag drive_bag, in the working directory."""
    (mapping_text,) = blocks("The mapping file (ROS 2)", "yaml")
    (tmp_path / "ros2-map.yaml").write_text(mapping_text)
    ts = typestore_for(RosMapping.model_validate(yaml.safe_load(mapping_text)))
    y, u = drive.y[:, 0], drive.u[:, 0]
    with Writer(tmp_path / "drive_bag", version=9, storage_plugin=StoragePlugin.SQLITE3) as writer:
        conns = {topic: writer.add_connection(topic, kind, typestore=ts) for topic, kind in TOPICS.items()}
        for k, tk in enumerate(drive.t):
            stamp = 1_700_000_000_000_000_000 + round(tk * 1e9)
            for i, (topic, raw) in enumerate(messages(ts, *y[k], *u[k], stamp, 1.0, 1.0).items()):
                writer.write(conns[topic], stamp + 100_000 * (i + 1), raw)
    monkeypatch.chdir(tmp_path)
    return tmp_path, ts


def test_the_bag_and_can_examples_run(ros2_files, drive, capsys):
    root, _ = ros2_files
    (replay,) = [c for c in commands("ROS 2 bags") if c[1] == "replay"]
    assert main(replay[1:]) == 0, capsys.readouterr().err
    assert (root / "estimates.csv").stat().st_size > 0 and "0 undecodable" in capsys.readouterr().out
    (can_mapping,) = blocks("CAN logs", "yaml")
    (root / "can-map.yaml").write_text(can_mapping)
    (root / "vehicle.dbc").write_text(DBC)
    write_log(root / "drive.log", drive)
    (root / "estimates.csv").unlink()
    for command in commands("CAN logs"):
        assert main(command[1:]) == 0, capsys.readouterr().err
    assert len((root / "estimates.csv").read_text().splitlines()) == len(drive.t)  # header + all but the last sample


def _local(command: list[str], endpoint: str) -> list[str]:
    """A page's command with the test router's endpoint, run by this interpreter."""
    assert DEFAULT_ENDPOINT in command
    return [sys.executable, "-m", "agv_fe", *[endpoint if a == DEFAULT_ENDPOINT else a for a in command[1:]]]


def _run_bridge(command: list[str], endpoint: str, ts, drive) -> str:
    """The page's bridge command for 3 s while this test plays the vehicle's ROS 2 nodes (bounded: 30 s)."""
    vehicle = open_session(open_options(endpoint))
    publishers = {t: vehicle.declare_publisher(topic_key(0, t, k, ts.hash_rihs01(k))) for t, k in TOPICS.items()}
    bridge = subprocess.Popen([*_local(command, endpoint), "--duration", "3"], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        y, u = drive.y[:, 0], drive.u[:, 0]
        for period in range(3_000):
            if bridge.poll() is not None:
                break
            k = period % len(y)
            now = time.time_ns()
            for topic, raw in messages(ts, *y[k], *u[k], now, 1.0, 1.0).items():
                publishers[topic].put(raw, attachment=rmw_attachment(period, now, bytes(16)))
            time.sleep(0.01)
        out, err = bridge.communicate(timeout=60)
    finally:
        if bridge.poll() is None:
            bridge.kill()
            bridge.wait(timeout=10)
        for publisher in publishers.values():
            publisher.undeclare()
        close_session(vehicle)
    assert bridge.returncode == 0, err
    return out


def open_options(endpoint: str):
    from edge_client.transport import TransportOptions

    return TransportOptions(mode="client", connect=(endpoint,), connect_timeout_s=5.0)


@pytest.mark.network
def test_the_live_examples_run_against_the_service(router, estimation_service, ros2_files, drive, tmp_path):
    root, ts = ros2_files
    (bridge_command,) = commands("ROS 2, live (over rmw_zenoh)")
    out = _run_bridge(bridge_command, router.endpoint, ts, drive)
    received = int(re.search(r"estimates received (\d+)", out).group(1))
    assert received > 150 and "republished" in out, out
    (publish,) = [c for c in commands("ROS 2 bags") if c[1] == "publish-csv"]
    sent = subprocess.run(_local(publish, router.endpoint), capture_output=True, text=True, timeout=60)
    assert sent.returncode == 0 and "lost 0" in sent.stdout, sent.stdout + sent.stderr
    assert int(re.search(r"estimates received (\d+)", sent.stdout).group(1)) > 150
    (script,) = blocks("Plain Zenoh", "python")
    (root / "vehicle.py").write_text(script)
    env = {**os.environ, "ZENOH_ENDPOINT": router.endpoint}
    plain = subprocess.run([sys.executable, "vehicle.py"], capture_output=True, text=True, timeout=60, env=env)
    assert plain.returncode == 0, plain.stderr
    count = int(plain.stdout.split()[0])
    assert count >= 250 and "'vehicle': 'agv-17'" in plain.stdout, plain.stdout
