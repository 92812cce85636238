"""`agv-fe publish-csv`: a recorded stream sent as one vehicle, exactly, at 100 Hz, with estimates back."""

import json
import subprocess
import sys
import time

import numpy as np
import pytest

from edge_client.library import builtin_scenario
from edge_client.plant import PlantSimulator
from edge_client.recording import read_recording, write_recording
from edge_client.transport import close_session, open_session
from tests.edge_client.test_publisher import Counter

pytestmark = pytest.mark.network


@pytest.fixture
def recording_file(tmp_path):
    """5 s of the paper's Scenario 2 (a real vehicle would give the same columns), with extra columns."""
    plant = PlantSimulator([builtin_scenario("paper-2")])
    samples = [plant.step() for _ in range(500)]
    path = tmp_path / "log.csv"
    write_recording(
        path,
        np.array([s.t for s in samples]),
        np.array([s.y[0] for s in samples]),
        np.array([s.u[0] for s in samples]),
        extra={"vy_true": np.array([s.x[0, 1] for s in samples])},
    )
    return path


@pytest.mark.parametrize("estimates", ["json", "binary"])
def test_publish_csv_streams_the_recording_exactly_and_collects_estimates(
    router, estimation_service, recording_file, tmp_path, estimates
):
    """With --estimates binary the vehicle reads its estimates from .../estimate.bin: the same records (logged as
    their JSON documents), and the service makes them only for that key."""
    listener = open_session(router.client())
    counter = Counter(listener)
    time.sleep(0.3)
    try:
        started = time.monotonic()
        out = subprocess.run(
            [
                sys.executable,
                "-m",
                "agv_fe",
                "publish-csv",
                str(recording_file),
                "--vehicle",
                "truck-7",
                "--connect",
                router.endpoint,
                "--log",
                str(tmp_path / "back.jsonl"),
                "--estimates",
                estimates,
            ],
            capture_output=True,
            text=True,
            timeout=60,
        )
        wall = time.monotonic() - started
    finally:
        time.sleep(0.2)
        counter.close()
        close_session(listener)
    assert out.returncode == 0, out.stderr
    recording = read_recording(recording_file)
    sent = counter.meas["truck-7"]
    assert [m.seq for m in sent] == list(range(500))
    # bit for bit what the file says, in the protocol's order
    np.testing.assert_array_equal([[m.vx_mps, m.r_radps] for m in sent], recording.y)
    np.testing.assert_array_equal([[m.torque_nm, m.steer_rad] for m in sent], recording.u)
    assert set(np.diff([m.timestamp_ns for m in sent])) == {10_000_000}
    assert wall >= 4.99  # paced at 100 Hz, not as fast as possible
    assert "sent 500 of 500 samples" in out.stdout and "lost 0" in out.stdout
    assert "last estimate (seq 499)" in out.stdout
    back = [json.loads(line) for line in (tmp_path / "back.jsonl").read_text().splitlines()]
    estimates = [b["message"] for b in back if b["type"] == "estimate"]
    assert estimates and all(e["vehicle"] == "truck-7" for e in estimates)
    if getattr(estimation_service, "answers_every_sample", False):
        assert sorted(e["seq"] for e in estimates) == list(range(500))
        assert "estimates received 500" in out.stdout


def test_publish_csv_reports_the_recordings_payload_before_streaming(router, estimation_service, recording_file):
    """--payload-kg puts a PayloadReport on the vehicle's payload key once the service's subscriber is known: the
    service registers the vehicle, models it loaded, and shows the payload."""
    out = subprocess.run(
        [
            sys.executable, "-m", "agv_fe", "publish-csv", str(recording_file), "--vehicle", "loaded-7",
            "--connect", router.endpoint, "--payload-kg", "70",
        ],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "payload 70 kg reported\n" in out.stdout
    vehicle = estimation_service.get("/vehicles/loaded-7").json()
    assert vehicle["payload_kg"] == 70.0 and vehicle["counters"]["accepted"] == 500
    refused = subprocess.run(
        [sys.executable, "-m", "agv_fe", "publish-csv", str(recording_file), "--vehicle", "x", "--payload-kg", "-1"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert refused.returncode != 0 and "--payload-kg: expected kg >= 0, got -1.0" in refused.stderr


def test_publish_csv_sends_a_grade_column_as_the_measurements_road_grade(router, estimation_service, tmp_path):
    """A recording with a grade column: each sample carries its grade (flag bit 1, bytes 56-63), bit for bit the
    file's; the service accepts them all."""
    plant = PlantSimulator([builtin_scenario("paper-2")])
    samples = [plant.step() for _ in range(200)]
    grade = 0.03 * np.sin(np.arange(200) / 40.0)
    path = tmp_path / "hills.csv"
    write_recording(
        path,
        np.array([s.t for s in samples]),
        np.array([s.y[0] for s in samples]),
        np.array([s.u[0] for s in samples]),
        extra={"grade": grade},
    )
    listener = open_session(router.client())
    counter = Counter(listener)
    time.sleep(0.3)
    try:
        out = subprocess.run(
            [sys.executable, "-m", "agv_fe", "publish-csv", str(path), "--vehicle", "hill-1",
             "--connect", router.endpoint],
            capture_output=True, text=True, timeout=60,
        )  # fmt: skip
    finally:
        time.sleep(0.2)
        counter.close()
        close_session(listener)
    assert out.returncode == 0, out.stderr
    sent = counter.meas["hill-1"]
    assert [m.seq for m in sent] == list(range(200))
    recording = read_recording(path)
    assert recording.grade is not None
    np.testing.assert_array_equal([m.grade_rad for m in sent], recording.grade)
    assert all(m.flags & 0x02 for m in sent) and "lost 0" in out.stdout
    assert "last estimate (seq 199)" in out.stdout  # the service took the graded samples
    vehicle = estimation_service.get("/vehicles/hill-1").json()
    assert (vehicle["grade_rad"], vehicle["grade_seq"]) == (recording.grade[-1], 199)
