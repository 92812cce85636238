"""Real ROS 2 messages for the bag and bridge tests, serialised by rosbags' typestore: a drive's sample k as an
odometry (v_x), an IMU sample (r), an Ackermann command (steering) and a Float64 torque demand; and a road that
climbs and descends, whose grade a Float64 topic carries (the CAN tests use the road too)."""

from __future__ import annotations

from typing import Any

import numpy as np

from edge_client.ros2 import RosMapping, typestore_for

MAPPING = """vx: {topic: /odom, type: nav_msgs/msg/Odometry, field: twist.twist.linear.x}
r: {topic: /imu, type: sensor_msgs/msg/Imu, field: angular_velocity.z, scale: -1.0}   # this IMU's z points down
torque: {topic: /drive_torque, type: std_msgs/msg/Float64, field: data, scale: 0.5}   # published doubled
steer: {topic: /cmd, type: ackermann_msgs/msg/AckermannDriveStamped, field: drive.steering_angle}
"""
#: :data:`MAPPING` with the road's grade, in radians on a topic of its own (:func:`grade_message`).
GRADE_MAPPING = MAPPING + "grade: {topic: /road_grade, type: std_msgs/msg/Float64, field: data}\n"
GRADE_TOPIC, GRADE_TYPE = "/road_grade", "std_msgs/msg/Float64"
TOPICS = {
    "/odom": "nav_msgs/msg/Odometry",
    "/imu": "sensor_msgs/msg/Imu",
    "/drive_torque": "std_msgs/msg/Float64",
    "/cmd": "ackermann_msgs/msg/AckermannDriveStamped",
}


def store(mapping: RosMapping) -> Any:
    return typestore_for(mapping)


def grade_message(ts: Any, grade_rad: float) -> bytes:
    """The CDR bytes of one road-grade message [rad] on :data:`GRADE_TOPIC`."""
    return bytes(ts.serialize_cdr(ts.types[GRADE_TYPE](data=grade_rad), GRADE_TYPE))


def road_grade(t_s: np.ndarray) -> np.ndarray:
    """A road that climbs and descends, +-0.05 rad (5 %) over 7.5 s [rad], at the times ``t_s`` [s]."""
    return 0.05 * np.sin(2 * np.pi * t_s / 7.5)


def _header(ts: Any, stamp_ns: int) -> Any:
    t = ts.types
    return t["std_msgs/msg/Header"](
        stamp=t["builtin_interfaces/msg/Time"](sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000),
        frame_id="base_link",
    )


def messages(
    ts: Any,
    vx: float,
    r: float,
    torque: float,
    steer: float,
    stamp_ns: int,
    imu_sign: float = -1.0,
    torque_factor: float = 2.0,
) -> dict[str, bytes]:
    """Topic -> CDR bytes of one sample's four messages: the IMU's z is ``imu_sign`` r and the torque message
    carries ``torque_factor`` T_d (the defaults are what :data:`MAPPING`'s sign and scale undo)."""
    t = ts.types
    vec = t["geometry_msgs/msg/Vector3"]
    zero6 = np.zeros(36)
    twist = t["geometry_msgs/msg/Twist"](linear=vec(x=vx, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=r))
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
    )
    odom = t["nav_msgs/msg/Odometry"](
        header=_header(ts, stamp_ns),
        child_frame_id="base_link",
        pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=zero6),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=zero6),
    )
    zero3 = np.zeros(9)
    imu = t["sensor_msgs/msg/Imu"](
        header=_header(ts, stamp_ns),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=zero3,
        angular_velocity=vec(x=0.0, y=0.0, z=imu_sign * r),
        angular_velocity_covariance=zero3,
        linear_acceleration=vec(x=0.0, y=0.0, z=9.81),
        linear_acceleration_covariance=zero3,
    )
    drive = t["ackermann_msgs/msg/AckermannDrive"](
        steering_angle=steer, steering_angle_velocity=0.0, speed=vx, acceleration=0.0, jerk=0.0
    )
    cmd = t["ackermann_msgs/msg/AckermannDriveStamped"](header=_header(ts, stamp_ns), drive=drive)
    torque_msg = t["std_msgs/msg/Float64"](data=torque_factor * torque)
    built = {"/odom": odom, "/imu": imu, "/drive_torque": torque_msg, "/cmd": cmd}
    return {topic: bytes(ts.serialize_cdr(message, TOPICS[topic])) for topic, message in built.items()}
