"""ROS 2 bags (edge_client/ros2.py, `agv-fe replay --map`): a simulated drive written as real rosbag2 recordings
(sqlite3 and mcap) by rosbags' writer and serialiser, replayed to the estimates of the equivalent CSV; with a road
grade topic mapped, the recording's grade column too."""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

rosbags = pytest.importorskip("rosbags")

from rosbags.rosbag2 import StoragePlugin, Writer  # noqa: E402 - after the optional-dependency check

from agv_fe.cli import main  # noqa: E402
from edge_client.recording import RecordingError  # noqa: E402
from edge_client.ros2 import RosMapping, load_ros_mapping, read_bag  # noqa: E402
from edge_client.scenario import REALISTIC_NOISE, Manoeuvre, Scenario, SpeedPoint  # noqa: E402
from edge_client.simulation import simulate_plant  # noqa: E402
from tests.edge_client.bridge_checks import assert_grade_held  # noqa: E402
from tests.edge_client.ros2_messages import (  # noqa: E402
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

#: each topic's phase within the 10 ms period [ns]: the grid starts at the last one (the torque's)
PHASE_NS = {"/odom": 200_000, "/imu": 400_000, "/cmd": 600_000, "/drive_torque": 800_000}
T0_NS = 1_700_000_000_000_000_000


@pytest.fixture(scope="module")
def drive():
    """12 s of the paper's vehicle: a speed change and a lane change, realistic sensor noise; the steering demand
    rounded to float32, as AckermannDrive carries it."""
    scenario = Scenario(
        name="ros2",
        duration_s=12.0,
        initial_speed_mps=10.0,
        speed_profile=(SpeedPoint(t_s=0.0, speed_mps=10.0), SpeedPoint(t_s=5.0, speed_mps=13.0)),
        manoeuvres=(Manoeuvre(kind="lane_change", start_s=6.0, duration_s=4.0, amplitude_rad=0.03),),
        noise=REALISTIC_NOISE,
        seed=4,
    )
    result = simulate_plant([scenario])
    result.u[:, 0, 1] = result.u[:, 0, 1].astype(np.float32)
    return result


def write_bag(
    path: Path,
    drive,
    plugin: StoragePlugin,
    stop_odom_after_s: float | None = None,
    *,
    grade=None,
    stop_grade_after_s: float | None = None,
) -> Path:
    """Each sample's four messages at their phases, a 10 Hz topic the mapping ignores, one truncated torque message;
    with ``grade`` [rad] (one per sample of the drive), the road grade on its own topic at 50 Hz too."""
    mapping = load_ros_mapping_text(MAPPING)
    ts = store(mapping)
    y, u, t = drive.y[:, 0], drive.u[:, 0], drive.t
    with Writer(path, version=9, storage_plugin=plugin) as writer:
        conns = {topic: writer.add_connection(topic, kind, typestore=ts) for topic, kind in TOPICS.items()}
        other = writer.add_connection("/battery", "std_msgs/msg/Float64", typestore=ts)
        graded = None if grade is None else writer.add_connection(GRADE_TOPIC, GRADE_TYPE, typestore=ts)
        for k, tk in enumerate(t):
            base = T0_NS + round(tk * 1e9)
            if graded is not None and k % 2 == 0 and (stop_grade_after_s is None or tk < stop_grade_after_s):
                writer.write(graded, base + 300_000, grade_message(ts, float(grade[k])))
            for topic, raw in messages(ts, y[k, 0], y[k, 1], u[k, 0], u[k, 1], base).items():
                if topic == "/odom" and stop_odom_after_s is not None and tk >= stop_odom_after_s:
                    continue
                writer.write(conns[topic], base + PHASE_NS[topic], raw)
            if k % 10 == 0:
                writer.write(other, base + 900_000, bytes(ts.serialize_cdr(ts.types["std_msgs/msg/Float64"](data=48.0),
                                                                           "std_msgs/msg/Float64")))  # fmt: skip
            if k == 300:
                writer.write(conns["/drive_torque"], base + 850_000, b"\x00\x01\x00\x00\x01")  # truncated CDR
    return path


def load_ros_mapping_text(text: str) -> RosMapping:
    return RosMapping.model_validate(yaml.safe_load(text))


@pytest.fixture(scope="module")
def bags(tmp_path_factory, drive):
    root = tmp_path_factory.mktemp("bags")
    (root / "map.yaml").write_text(MAPPING)
    return root, {
        "sqlite3": write_bag(root / "drive_sqlite3", drive, StoragePlugin.SQLITE3),
        "mcap": write_bag(root / "drive_mcap", drive, StoragePlugin.MCAP),
    }


def _estimates(path: Path) -> list[list[str]]:
    with path.open() as handle:
        return [[row["vy_hat"], row["torque_fault_hat"], row["steer_fault_hat"]] for row in csv.DictReader(handle)]


def test_a_bag_decodes_onto_the_grid_as_the_drive_was_sampled(bags, drive):
    root, paths = bags
    mapping = load_ros_mapping(root / "map.yaml")
    for storage, path in paths.items():
        recording, stats = read_bag(path, mapping)
        n = len(recording)
        assert n >= len(drive.t) - 1, storage
        np.testing.assert_array_equal(recording.y, drive.y[:n, 0])  # float64 fields, sign and scale undone exactly
        np.testing.assert_array_equal(recording.u, drive.u[:n, 0])
        assert stats.undecodable == 1 and stats.used["torque"] == len(drive.t) and stats.non_finite == 0
        assert recording.grade is None and list(stats.used) == ["vx", "r", "torque", "steer"]  # no grade mapped


def test_replaying_a_bag_gives_the_estimates_of_the_equivalent_csv(tmp_path, bags, drive, capsys):
    root, paths = bags
    n = len(read_bag(paths["mcap"], load_ros_mapping(root / "map.yaml"))[0])
    original = tmp_path / "drive.csv"
    with original.open("w", newline="") as handle:  # every digit (repr), so that the CSV holds the bag's numbers
        rows = np.column_stack([drive.t[:n], drive.y[:n, 0], drive.u[:n, 0]])
        csv.writer(handle).writerows(
            [["t", "vx", "r", "torque", "steer"], *([repr(float(v)) for v in row] for row in rows)]
        )
    assert main(["replay", str(original), "--out", str(tmp_path / "csv-est.csv")]) == 0
    expected = _estimates(tmp_path / "csv-est.csv")
    for storage, path in paths.items():
        out = tmp_path / f"{storage}-est.csv"
        assert main(["replay", str(path), "--map", str(root / "map.yaml"), "--out", str(out)]) == 0
        assert "1 undecodable" in capsys.readouterr().out
        assert _estimates(out) == expected, storage  # the same numbers, digit for digit


def test_what_cannot_be_read_is_said(tmp_path, bags, drive, capsys):
    root, paths = bags
    mapping = load_ros_mapping(root / "map.yaml")
    cases = {
        "unknown type": (MAPPING.replace("std_msgs/msg/Float64", "acme_msgs/msg/Torque"),
                         r"unknown message type acme_msgs/msg/Torque \(mapped to torque\)"),
        "missing field": (MAPPING.replace("angular_velocity.z", "angular_velocity.w"),
                          r"geometry_msgs/msg/Vector3 has no field 'w' \(mapped to r as angular_velocity.w\)"),
        "not a number": (MAPPING.replace("field: data", "field: data.x"), r"field data.x \(mapped to torque\) is not"),
        "unknown topic": (MAPPING.replace("/imu", "/imu_raw"), r"no topic /imu_raw in the bag \(mapped to r\)"),
    }  # fmt: skip
    for name, (text, message) in cases.items():
        (tmp_path / "bad.yaml").write_text(text)
        assert main(["replay", str(paths["mcap"]), "--map", str(tmp_path / "bad.yaml"), "--out", "x.csv"]) == 2, name
        err = capsys.readouterr().err
        assert re.search(message, err), (name, err)
    # the odometry stops at 6 s: refused at the first grid point it is missing, by name
    stopped = write_bag(tmp_path / "stopped", drive, StoragePlugin.SQLITE3, stop_odom_after_s=6.0)
    with pytest.raises(RecordingError, match=r"vx not received for 0\.1\d+ s at t = 6\.\d+ s"):
        read_bag(stopped, mapping)


def test_calibrate_reads_bags_with_the_mapping(tmp_path, bags, capsys):
    """The same --map for calibrate: the bag is read (12 s of driving, too little to identify the vehicle: refused
    with the calibration's reason, exit 3), and a path that is no bag is said."""
    from tests.calibration_data import BASE

    root, paths = bags
    base = tmp_path / "base.json"
    base.write_text(json.dumps({"params": BASE}))
    command = ["calibrate", str(paths["mcap"]), "--map", str(root / "map.yaml"), "--base", str(base), "--out",
               str(tmp_path / "profile.json")]  # fmt: skip
    assert main(command) == 3
    captured = capsys.readouterr()
    assert "1 undecodable" in captured.out and "calibration refused" in captured.err
    command[1] = str(tmp_path / "no-bag")
    assert main(command) == 2 and "cannot read the bag" in capsys.readouterr().err


def test_a_mapped_grade_topic_fills_the_grade_column_and_replays_as_the_csv_with_it(tmp_path, bags, drive, capsys):
    root, paths = bags
    plain, _ = read_bag(paths["mcap"], load_ros_mapping(root / "map.yaml"))
    grade = road_grade(drive.t)
    bag = write_bag(tmp_path / "graded", drive, StoragePlugin.MCAP, grade=grade)
    # the grade topic in the bag, the mapping without it: the recording of the plain bag
    unmapped, unmapped_stats = read_bag(bag, load_ros_mapping_text(MAPPING))
    assert unmapped.grade is None and list(unmapped_stats.used) == ["vx", "r", "torque", "steer"]
    # mapped: the same grid and signals, and the grade as published (float64 [rad]), fresh on even samples
    # (50 Hz), held on odd ones
    recording, stats = read_bag(bag, load_ros_mapping_text(GRADE_MAPPING))
    assert_grade_held(plain, unmapped, recording, grade)
    assert stats.used["grade"] == (len(drive.t) + 1) // 2
    # `replay --map` of the bag gives the estimates of the CSV with the grade column, digit for digit (the grade
    # applied: not those of the plain bag)
    original = tmp_path / "graded.csv"
    with original.open("w", newline="") as handle:
        rows = np.column_stack([recording.t, recording.y, recording.u, recording.grade])
        csv.writer(handle).writerows(
            [["t", "vx", "r", "torque", "steer", "grade"], *([repr(float(v)) for v in row] for row in rows)]
        )
    (tmp_path / "map.yaml").write_text(GRADE_MAPPING)
    for name, command in (("csv", [str(original)]), ("bag", [str(bag), "--map", str(tmp_path / "map.yaml")]),
                          ("plain", [str(paths["mcap"]), "--map", str(root / "map.yaml")])):  # fmt: skip
        assert main(["replay", *command, "--out", str(tmp_path / f"{name}-est.csv")]) == 0, name
    assert f"grade {(len(drive.t) + 1) // 2}; 1 undecodable" in capsys.readouterr().out
    graded_estimates = _estimates(tmp_path / "bag-est.csv")
    assert graded_estimates == _estimates(tmp_path / "csv-est.csv")
    assert graded_estimates != _estimates(tmp_path / "plain-est.csv")


def test_a_grade_topic_that_stops_is_refused_by_name(tmp_path, drive):
    stopped = write_bag(tmp_path / "stopped", drive, StoragePlugin.SQLITE3, grade=road_grade(drive.t),
                        stop_grade_after_s=6.0)  # fmt: skip
    with pytest.raises(RecordingError, match=r"grade not received for 0\.1\d+ s at t = 6\.\d+ s"):
        read_bag(stopped, load_ros_mapping_text(GRADE_MAPPING))
    # a mapped grade topic the bag does not have is named too
    with pytest.raises(RecordingError, match=r"no topic /road_grade in the bag \(mapped to grade\)"):
        read_bag(write_bag(tmp_path / "level", drive, StoragePlugin.SQLITE3), load_ros_mapping_text(GRADE_MAPPING))
