"""ROS 2 messages as the estimator's four signals: the mapping file, CDR decoding with rosbags, and rosbag2 recordings.

A ROS 2 vehicle publishes v_x, r, the drive-torque demand and the steering demand (docs/protocol.md, "What each
signal is") as fields of its own topics. A mapping file names, for each column, the topic, its message type, the
field path inside the message and the affine map to the protocol's unit, value = scale x field + offset (a negative
scale flips the sign); optionally ``grade`` too, the road's grade [rad, + uphill] (not the body's pitch), which a
bag's recording then carries as its grade column and the live bridge sends with each measurement:

.. code-block:: yaml

    vx:     {topic: /odom, type: nav_msgs/msg/Odometry, field: twist.twist.linear.x}
    r:      {topic: /imu, type: sensor_msgs/msg/Imu, field: angular_velocity.z}
    torque: {topic: /drive_torque, type: std_msgs/msg/Float64, field: data, scale: 2.0}   # per wheel -> total
    steer:  {topic: /cmd, type: ackermann_msgs/msg/AckermannDriveStamped, field: drive.steering_angle}
    grade:  {topic: /road_grade, type: std_msgs/msg/Float64, field: data}   # optional [rad]
    domain_id: 0          # the live bridge's ROS_DOMAIN_ID
    types: {}             # message definitions (.msg text) of custom types, by name

Messages are (de)serialised by rosbags' typestore (ROS 2 Jazzy's standard messages, plus ``ackermann_msgs`` and
the mapping's ``types``), never by hand. Time: a message counts at the time it was received (a bag's record time,
the bridge's arrival time), as a controller subscribed to the topics would see it; the grid rule is
edge_client/grid.py's (zero-order hold, stale columns refused by name). A message that does not decode, a field
that is not a finite number: counted and reported, not used.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from edge_client.grid import COLUMNS, hold_on_grid
from edge_client.recording import OPTIONAL_COLUMNS, Recording, RecordingError

#: Message types that vehicles use and rosbags' ROS 2 store lacks, registered from their .msg text
#: (ackermann_msgs 2.0: AckermannDrive.msg, AckermannDriveStamped.msg).
EXTRA_TYPES = {
    "ackermann_msgs/msg/AckermannDrive": (
        "float32 steering_angle\nfloat32 steering_angle_velocity\nfloat32 speed\nfloat32 acceleration\nfloat32 jerk\n"
    ),
    "ackermann_msgs/msg/AckermannDriveStamped": "std_msgs/Header header\nAckermannDrive drive\n",
}
#: rosbags' message store: the ROS 2 distribution whose standard message definitions (and type hashes) are used.
ROS_DISTRIBUTION = "ROS2_JAZZY"


class RosSignal(BaseModel):
    """Where one column comes from: a topic, its message type, a field path, and value = scale x field + offset."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    topic: str = Field(pattern=r"^(/[A-Za-z_][A-Za-z0-9_]*)+$", description="fully qualified topic name, e.g. /odom")
    type: str = Field(pattern=r"^[A-Za-z0-9_]+/msg/[A-Za-z0-9_]+$", description="e.g. nav_msgs/msg/Odometry")
    field: str = Field(pattern=r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$", description="dotted path")
    scale: float = Field(1.0, allow_inf_nan=False, description="to the protocol's unit (and sign): multiply by this")
    offset: float = Field(0.0, allow_inf_nan=False, description="then add this")


class RosMapping(BaseModel):
    """The recording's four columns (and optionally its grade) as ROS 2 message fields, the grid, the domain and
    custom message types."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    vx: RosSignal
    r: RosSignal
    torque: RosSignal
    steer: RosSignal
    grade: RosSignal | None = Field(None, description="optional: the road's grade [rad], + uphill (not the pitch)")
    sample_period_s: float = Field(0.01, gt=0, le=1, description="the recording's sample period [s]")
    max_age_s: float = Field(0.1, gt=0, le=10, description="a value older than this at a grid point is missing [s]")
    domain_id: int = Field(0, ge=0, le=232, description="ROS_DOMAIN_ID of the vehicle's nodes (the live bridge)")
    types: dict[str, str] = Field(default_factory=dict, description="type name -> .msg definition, custom types")

    @field_validator("types")
    @classmethod
    def _type_names(cls, types: dict[str, str]) -> dict[str, str]:
        for name in types:
            if len(name.split("/")) != 3 or name.split("/")[1] != "msg":
                raise ValueError(f"type name {name!r} is not of the form package/msg/Name")
        return types

    def signals(self) -> dict[str, RosSignal]:
        """Column -> its signal: the four :data:`~edge_client.grid.COLUMNS`, then the optional ones mapped."""
        optional = [column for column in OPTIONAL_COLUMNS if getattr(self, column) is not None]
        return {column: getattr(self, column) for column in (*COLUMNS, *optional)}

    def topics(self) -> dict[str, list[tuple[str, RosSignal]]]:
        """Topic -> the columns it carries (one topic may carry several, e.g. v_x and r from one odometry)."""
        out: dict[str, list[tuple[str, RosSignal]]] = {}
        for column, signal in self.signals().items():
            out.setdefault(signal.topic, []).append((column, signal))
        return out


@dataclass
class RosStats:
    """What was read: messages of the mapped topics, values used per mapped column, and those refused, by reason."""

    messages: int = 0
    used: dict[str, int] = field(default_factory=lambda: dict.fromkeys(COLUMNS, 0))
    undecodable: int = 0
    non_finite: int = 0
    first_complete_s: float | None = None

    def describe(self) -> str:
        used = ", ".join(f"{column} {count}" for column, count in self.used.items())
        return (
            f"read {self.messages} messages: used {used}; {self.undecodable} undecodable, {self.non_finite} not finite"
        )


def load_ros_mapping(path: str | Path) -> RosMapping:
    """Read a mapping file (YAML or JSON); a :class:`RecordingError` names the file and the field."""
    try:
        data = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise RecordingError(f"{path}: cannot read the mapping: {exc}") from exc
    try:
        return RosMapping.model_validate(data)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        raise RecordingError(f"{path}: invalid mapping: {problems}") from exc


def typestore_for(mapping: RosMapping) -> Any:
    """rosbags' ROS 2 typestore with :data:`EXTRA_TYPES` and the mapping's own types registered, every mapped type
    known and every field path present (a :class:`RecordingError` names the column otherwise)."""
    from rosbags.typesys import Stores, TypesysError, get_types_from_msg, get_typestore

    store = get_typestore(Stores[ROS_DISTRIBUTION])
    types: dict[str, Any] = {}
    try:
        for name, text in {**EXTRA_TYPES, **mapping.types}.items():
            types.update(get_types_from_msg(text, name))
        store.register(types)
    except TypesysError as exc:
        raise RecordingError(f"invalid message definition in the mapping's types: {exc}") from exc
    for column, signal in mapping.signals().items():
        check_field(store, signal, column)
    for topic, columns in mapping.topics().items():
        kinds = {signal.type for _, signal in columns}
        if len(kinds) > 1:
            raise RecordingError(f"topic {topic} is mapped with two types: {', '.join(sorted(kinds))}")
    return store


def check_field(store: Any, signal: RosSignal, column: str) -> None:
    """The field path names a numeric field of the type (walked through rosbags' field definitions)."""
    from rosbags.interfaces import Nodetype

    if signal.type not in store.fielddefs:
        raise RecordingError(
            f"unknown message type {signal.type} (mapped to {column}): add its .msg definition under 'types'"
        )
    typename = signal.type
    parts = signal.field.split(".")
    for depth, name in enumerate(parts):
        fields = dict(store.fielddefs[typename][1])
        if name not in fields:
            raise RecordingError(
                f"{typename} has no field {name!r} (mapped to {column} as {signal.field}); "
                f"its fields: {', '.join(fields)}"
            )
        kind, detail = fields[name]
        last = depth == len(parts) - 1
        if kind == Nodetype.NAME and not last:
            typename = detail
            continue
        numeric = kind == Nodetype.BASE and detail[0] not in ("string", "bool")
        if not (last and numeric):
            raise RecordingError(f"{signal.type} field {signal.field} (mapped to {column}) is not a number")


def field_value(message: Any, signal: RosSignal) -> float:
    """scale x (the field at the signal's path) + offset, in the protocol's unit; may be non-finite."""
    value = message
    for name in signal.field.split("."):
        value = getattr(value, name)
    return signal.scale * float(value) + signal.offset


def read_bag(path: str | Path, mapping: RosMapping) -> tuple[Recording, RosStats]:
    """A rosbag2 recording (a bag directory with metadata.yaml, or one .db3 / .mcap file) on the grid."""
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.serde import SerdeError

    store = typestore_for(mapping)
    wanted = mapping.topics()
    columns = tuple(mapping.signals())
    samples: dict[str, tuple[list[float], list[float]]] = {column: ([], []) for column in columns}
    stats = RosStats(used=dict.fromkeys(columns, 0))
    try:
        with AnyReader([Path(path)], default_typestore=store) as reader:
            connections = _connections(reader, wanted, str(path))
            for connection, t_ns, raw in reader.messages(connections=connections):
                stats.messages += 1
                try:
                    message = reader.deserialize(raw, connection.msgtype)
                except (SerdeError, AnyReaderError):  # AnyReader wraps the serde error
                    stats.undecodable += 1
                    continue
                t_s = (t_ns - reader.start_time) * 1e-9
                for column, signal in wanted[connection.topic]:
                    try:
                        value = field_value(message, signal)
                    except (AttributeError, TypeError, ValueError):  # the bag's own definition of the type differs
                        stats.undecodable += 1
                        continue
                    if not math.isfinite(value):
                        stats.non_finite += 1
                        continue
                    samples[column][0].append(t_s)
                    samples[column][1].append(value)
                    stats.used[column] += 1
    except (AnyReaderError, OSError) as exc:
        raise RecordingError(f"{path}: cannot read the bag: {exc}") from exc
    recording, stats.first_complete_s = hold_on_grid(samples, mapping.sample_period_s, mapping.max_age_s, str(path))
    return recording, stats


def _connections(reader: Any, wanted: dict[str, list[tuple[str, RosSignal]]], source: str) -> list[Any]:
    """The bag's connections of the mapped topics; a topic absent, or recorded with another type, is an error."""
    found = {c.topic: c for c in reader.connections}
    out: list[Any] = []
    for topic, columns in wanted.items():
        names = ", ".join(column for column, _ in columns)
        connection = found.get(topic)
        if connection is None:
            raise RecordingError(
                f"{source}: no topic {topic} in the bag (mapped to {names}); its topics: {', '.join(sorted(found))}"
            )
        if connection.msgtype != columns[0][1].type:
            raise RecordingError(
                f"{source}: topic {topic} is {connection.msgtype} in the bag, the mapping says {columns[0][1].type}"
            )
        out.extend(c for c in reader.connections if c.topic == topic)
    return out
