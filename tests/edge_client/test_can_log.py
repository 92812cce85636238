"""A recording from a CAN log and a DBC (edge_client/can_log.py, `agv-fe can2csv`): a simulated drive encoded into
frames at the vehicle's own rates and units, written as a candump log by python-can, decoded back onto the grid;
with a road-grade signal mapped, the recording's grade column too."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

can = pytest.importorskip("can")
cantools = pytest.importorskip("cantools")

from agv_fe.benchmarks.can_bridge import DBC, MAPPING  # noqa: E402
from agv_fe.cli import main  # noqa: E402 - after the optional-dependency check
from edge_client.can_log import load_mapping, read_can_log  # noqa: E402
from edge_client.recording import RecordingError, read_recording, write_recording  # noqa: E402
from edge_client.scenario import REALISTIC_NOISE, Manoeuvre, Scenario, SpeedPoint  # noqa: E402
from edge_client.simulation import simulate_plant  # noqa: E402
from tests.edge_client.bridge_checks import assert_grade_held  # noqa: E402
from tests.edge_client.ros2_messages import road_grade  # noqa: E402
from tests.tolerances import (  # noqa: E402
    CAN_GRADE_ATOL_RAD,
    CAN_SPEED_ATOL_MPS,
    CAN_STEER_ATOL_RAD,
    CAN_TORQUE_ATOL_NM,
    CAN_YAW_RATE_ATOL_RADPS,
    CSV_ROUND_TRIP_ATOL,
    CSV_ROUND_TRIP_RTOL,
)

# the vehicle's CAN database and mapping: the CAN bridge benchmark's (km/h and deg/s as on many vehicles)
T0 = 1_700_000_000.0
#: The vehicle's road grade in degrees, a message the benchmark's DBC lacks, and the mapping that takes it (to rad).
GRADE_DBC = (
    DBC
    + """
BO_ 260 ROAD_GRADE: 8 ECU
 SG_ GradeDeg : 0|16@1- (0.001,0) [-32.768|32.767] "deg" Vector__XXX
"""
)
GRADE_MAPPING = MAPPING + "grade: {message: ROAD_GRADE, signal: GradeDeg, scale: 0.017453292519943295}\n"


@pytest.fixture(scope="module")
def drive():
    """15 s of the paper's vehicle: speed changes and a lane change, realistic sensor noise."""
    scenario = Scenario(
        name="can",
        duration_s=15.0,
        initial_speed_mps=10.0,
        speed_profile=(SpeedPoint(t_s=0.0, speed_mps=10.0), SpeedPoint(t_s=6.0, speed_mps=14.0)),
        manoeuvres=(Manoeuvre(kind="lane_change", start_s=7.0, duration_s=4.0, amplitude_rad=0.03),),
        noise=REALISTIC_NOISE,
        seed=9,
    )
    return simulate_plant([scenario])


def write_log(
    path: Path, drive, stop_speed_after_s: float | None = None, *, grade=None, stop_grade_after_s: float | None = None
) -> Path:
    """The drive as frames: speed and yaw rate at 100 Hz, steering at 100 Hz, torque at 50 Hz, each message
    at its own phase within the period, a body message at 10 Hz, and one truncated yaw frame; with ``grade`` [rad]
    (one per sample of the drive), the road grade in degrees at 50 Hz too."""
    db = cantools.database.load_string(GRADE_DBC, "dbc")
    y, u, t = drive.y[:, 0], drive.u[:, 0], drive.t
    frames: list[tuple[float, int, bytes]] = []
    for k, tk in enumerate(t):
        if stop_speed_after_s is None or tk < stop_speed_after_s:
            frames.append((tk + 0.0002, 256, db.encode_message(256, {"VehicleSpeed": y[k, 0] * 3.6})))
        if grade is not None and k % 2 == 0 and (stop_grade_after_s is None or tk < stop_grade_after_s):
            frames.append((tk + 0.0003, 260, db.encode_message(260, {"GradeDeg": math.degrees(grade[k])})))
        frames.append((tk + 0.0004, 257, db.encode_message(257, {"YawRate": math.degrees(y[k, 1])})))
        frames.append((tk + 0.0006, 259, db.encode_message(259, {"RoadWheelAngleDemand": u[k, 1]})))
        if k % 2 == 0:
            frames.append((tk + 0.0008, 258, db.encode_message(258, {"WheelTorqueDemand": u[k, 0]})))
        if k % 10 == 0:
            frames.append((tk + 0.0009, 2047, db.encode_message(2047, {"DoorOpen": 0})))
    frames.append((t[500] + 0.0005, 257, b"\x01"))  # truncated: does not decode
    frames.sort()
    with can.CanutilsLogWriter(str(path), channel="can0") as writer:
        for ts, frame_id, data in frames:
            writer.on_message_received(can.Message(timestamp=T0 + ts, arbitration_id=frame_id, data=data))
    return path


@pytest.fixture(scope="module")
def files(tmp_path_factory, drive):
    root = tmp_path_factory.mktemp("can")
    (root / "vehicle.dbc").write_text(DBC)
    (root / "map.yaml").write_text(MAPPING)
    return root, write_log(root / "drive.log", drive)


def test_the_log_decodes_onto_the_grid_as_the_drive_was_sampled(files, drive):
    root, log = files
    recording, stats = read_can_log(log, root / "vehicle.dbc", load_mapping(root / "map.yaml"))
    n = len(recording)
    # the grid starts once every column is known (the torque frame of sample 0 comes last, 0.8 ms in): sample k of
    # the drive is grid point k, every 10 ms, up to the last sample whose frames all came before the log ends
    assert n == len(drive.t) - 1 and np.allclose(np.diff(recording.t), 0.01)
    y, u = drive.y[:n, 0], drive.u[:n, 0]
    # half the DBC's scaling steps: 0.01 km/h, 0.01 deg/s, 0.0001 rad, 0.5 N m
    np.testing.assert_allclose(recording.y[:, 0], y[:, 0], atol=CAN_SPEED_ATOL_MPS)
    np.testing.assert_allclose(recording.y[:, 1], y[:, 1], atol=CAN_YAW_RATE_ATOL_RADPS)
    np.testing.assert_allclose(recording.u[:, 1], u[:, 1], atol=CAN_STEER_ATOL_RAD)
    # torque at 50 Hz: fresh on even samples, held on odd ones
    np.testing.assert_allclose(recording.u[::2, 0], u[::2, 0], atol=CAN_TORQUE_ATOL_NM)
    np.testing.assert_allclose(recording.u[1::2, 0], u[0:-1:2, 0][: len(recording.u[1::2])], atol=CAN_TORQUE_ATOL_NM)
    samples = len(drive.t)
    assert stats.used["vx"] == samples and stats.used["torque"] == (samples + 1) // 2
    assert stats.other == math.ceil(samples / 10) and stats.undecodable == 1


def test_can2csv_writes_a_recording_that_replay_reads(tmp_path, files, drive, capsys):
    root, log = files
    out = tmp_path / "rec.csv"
    code = main(["can2csv", str(log), "--dbc", str(root / "vehicle.dbc"), "--map", str(root / "map.yaml"),
                 "--out", str(out)])  # fmt: skip
    printed = capsys.readouterr().out
    assert code == 0 and "1 undecodable" in printed and f"{len(drive.t) - 1} samples" in printed
    assert read_recording(out).grade is None  # no grade mapped: no grade column
    # replayed, the CAN recording gives the estimates of the drive's own CSV to within the DBC's resolution
    original = tmp_path / "original.csv"
    n = len(drive.t) - 1
    write_recording(original, drive.t[:n], drive.y[:n, 0], drive.u[:n, 0])
    results = {}
    for name, rec in (("can", out), ("csv", original)):
        assert main(["replay", str(rec), "--out", str(tmp_path / f"{name}-est.csv")]) == 0
        with (tmp_path / f"{name}-est.csv").open() as handle:
            results[name] = np.array(
                [[float(r["vy_hat"]), float(r["torque_fault_hat"])] for r in csv.DictReader(handle)]
            )
    capsys.readouterr()
    difference = np.abs(results["can"] - results["csv"])[300:]
    assert difference[:, 0].max() < 0.01 and difference[:, 1].max() < 5.0


def test_what_cannot_be_decoded_is_said(tmp_path, files, drive):
    root, _ = files
    mapping = load_mapping(root / "map.yaml")
    bad_map = tmp_path / "bad.yaml"
    bad_map.write_text(MAPPING.replace("IMU_RATES", "IMU"))
    with pytest.raises(RecordingError, match="no message 'IMU' \\(mapped to r\\)"):
        read_can_log(files[1], root / "vehicle.dbc", load_mapping(bad_map))
    # the speed frames stop at 8 s: the recording is refused at the first grid point they are missing, by name
    stopped = write_log(tmp_path / "stopped.log", drive, stop_speed_after_s=8.0)
    with pytest.raises(RecordingError, match=r"vx not received for 0\.1\d+ s at t = 8\.\d+ s"):
        read_can_log(stopped, root / "vehicle.dbc", mapping)
    (tmp_path / "typo.yaml").write_text(MAPPING.replace("scale: 0.2777777777777778", "scale: fast"))
    with pytest.raises(RecordingError, match=r"vx\.scale"):
        load_mapping(tmp_path / "typo.yaml")


@pytest.fixture(scope="module")
def graded(tmp_path_factory, drive):
    """The drive's log with the road's grade (ROAD_GRADE frames), the DBC that has them and the mapping that maps
    them."""
    root = tmp_path_factory.mktemp("can-grade")
    (root / "vehicle.dbc").write_text(GRADE_DBC)
    (root / "map.yaml").write_text(GRADE_MAPPING)
    return root, write_log(root / "drive.log", drive, grade=road_grade(drive.t))


def test_a_mapped_grade_signal_fills_the_grade_column_and_an_unmapped_one_changes_nothing(files, graded, drive):
    plain, _ = read_can_log(files[1], files[0] / "vehicle.dbc", load_mapping(files[0] / "map.yaml"))
    root, log = graded
    samples, grade = len(drive.t), road_grade(drive.t)
    # the grade frames in the log, the mapping without them: other messages, and the recording of the plain log
    unmapped, unmapped_stats = read_can_log(log, root / "vehicle.dbc", load_mapping(files[0] / "map.yaml"))
    assert unmapped.grade is None and list(unmapped_stats.used) == ["vx", "r", "torque", "steer"]
    assert unmapped_stats.other == math.ceil(samples / 10) + (samples + 1) // 2
    # mapped: the same grid and signals, and the grade as encoded (0.001 deg steps, deg -> rad by the mapping's
    # scale), fresh on even samples (50 Hz), held on odd ones
    recording, stats = read_can_log(log, root / "vehicle.dbc", load_mapping(root / "map.yaml"))
    assert_grade_held(plain, unmapped, recording, grade, CAN_GRADE_ATOL_RAD)
    assert stats.used["grade"] == (samples + 1) // 2 and stats.other == math.ceil(samples / 10)


def test_can2csv_writes_the_mapped_grade_and_a_stale_grade_is_refused_by_name(tmp_path, graded, drive, capsys):
    root, log = graded
    out = tmp_path / "rec.csv"
    code = main(["can2csv", str(log), "--dbc", str(root / "vehicle.dbc"), "--map", str(root / "map.yaml"),
                 "--out", str(out)])  # fmt: skip
    assert code == 0 and f"grade {(len(drive.t) + 1) // 2};" in capsys.readouterr().out
    recording, _ = read_can_log(log, root / "vehicle.dbc", load_mapping(root / "map.yaml"))
    written = read_recording(out)
    assert written.grade is not None and recording.grade is not None
    np.testing.assert_allclose(written.grade, recording.grade, rtol=CSV_ROUND_TRIP_RTOL, atol=CSV_ROUND_TRIP_ATOL)
    # the grade frames stop at 8 s: refused at the first grid point the grade is missing, by name, like the others
    stopped = write_log(tmp_path / "stopped.log", drive, grade=road_grade(drive.t), stop_grade_after_s=8.0)
    with pytest.raises(RecordingError, match=r"grade not received for 0\.1\d+ s at t = 8\.\d+ s"):
        read_can_log(stopped, root / "vehicle.dbc", load_mapping(root / "map.yaml"))
