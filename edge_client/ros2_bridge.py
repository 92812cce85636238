"""A ROS 2 vehicle live over rmw_zenoh: its topics in, the service's measurements out, on the 10 ms grid.

ROS 2's Zenoh middleware (rmw_zenoh, docs/design.md of ros2/rmw_zenoh) puts every message of a topic on the key
expression ``<domain_id>/<fully qualified name without its leading />/<DDS type name>/<type hash>``, e.g.
``0/odom/nav_msgs::msg::dds_::Odometry_/RIHS01_<64 hex digits>``, where the DDS type name of
``pkg/msg/Name`` is ``pkg::msg::dds_::Name_`` and the type hash is the RIHS01 hash of the type's description
(REP-2016; rosbags' typestore computes it). The payload is the message in CDR with its 4-byte encapsulation
header; the attachment (sequence number and source time stamp, 8 bytes each little-endian, then the publisher's
GID) is not needed here: a message counts when it arrives, as a controller subscribed to the topic would see it.

:class:`Ros2Source` subscribes to the mapped topics (edge_client/ros2.py's mapping) on those keys, with any type
type, decodes each message with rosbags and keeps the latest value of each column (edge_client/grid.py's
:class:`~edge_client.grid.LiveHold`; the road's grade too when the mapping names it, which each measurement then
carries as ``grade_rad``). It is a :class:`~edge_client.sources.SampleSource`: the 100 Hz publisher
(edge_client/publisher.py) samples it at each tick and sends the measurement in the service's protocol, with its
pacing, sequence numbers, buffering and the estimates that come back. A tick at which a column is older than the
mapping's ``max_age_s`` sends nothing (the stale column is counted by name); its sequence number is skipped, so
the service counts the missing samples. Bad input never stops the bridge; it is counted by reason: a message of
another type definition (type hash), one that does not decode (malformed CDR), a field that is not finite.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal, Self

from edge_client.grid import LiveSource
from edge_client.ros2 import RosMapping, RosSignal, field_value, typestore_for
from edge_client.transport import Received, Subscription

if TYPE_CHECKING:
    import zenoh


def dds_type_name(type_name: str) -> str:
    """``pkg/msg/Name`` -> ``pkg::msg::dds_::Name_``, the type chunk of an rmw_zenoh key."""
    package, kind, name = type_name.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def topic_key(domain_id: int, topic: str, type_name: str, type_hash: str) -> str:
    """The key expression rmw_zenoh publishes ``topic`` on: ``<domain_id>/<topic>/<DDS type>/<type hash>``."""
    return f"{domain_id}/{topic.strip('/')}/{dds_type_name(type_name)}/{type_hash}"


def rmw_attachment(seq: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """An rmw_zenoh publication's attachment: seq (i64 LE), source time stamp [ns] (i64 LE), GID length, GID."""
    return (
        seq.to_bytes(8, "little", signed=True)
        + source_timestamp_ns.to_bytes(8, "little", signed=True)
        + (bytes([len(gid)]) + gid)
    )


@dataclass
class BridgeStats:
    """What the bridge received and refused besides what :class:`~edge_client.grid.LiveSource` counts."""

    messages: int = 0
    undecodable: int = 0
    other_type: int = 0


class Ros2Source(LiveSource):
    """One ROS 2 vehicle's mapped topics over Zenoh as a one-vehicle sample source (module docstring)."""

    def __init__(
        self,
        session: zenoh.Session,
        mapping: RosMapping,
        vehicle_id: str,
        *,
        wait_s: float = 30.0,
        clock: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        super().__init__(vehicle_id, mapping.sample_period_s, mapping.max_age_s, wait_s, clock, mapping.signals())
        self.mapping = mapping
        self.store = typestore_for(mapping)
        self.stats = BridgeStats()
        self._lock = threading.Lock()
        self.keys: dict[str, str] = {}
        self._subscriptions: list[Subscription] = []
        try:
            for topic, columns in mapping.topics().items():
                type_name = columns[0][1].type
                type_hash = self.store.hash_rihs01(type_name)
                self.keys[topic] = topic_key(mapping.domain_id, topic, type_name, type_hash)
                # any type on the topic: a message of another type or type definition is counted, not ignored
                selector = f"{mapping.domain_id}/{topic.strip('/')}/*/*"
                self._subscriptions.append(Subscription(session, selector, self._receiver(columns, type_hash)))
        except BaseException:
            self.close()
            raise

    def _receiver(self, columns: list[tuple[str, RosSignal]], type_hash: str) -> Callable[[Received], None]:
        type_name = columns[0][1].type
        expected = [dds_type_name(type_name), type_hash]

        def on_message(rx: Received) -> None:
            # zenoh's thread: decode, check, hold; never raise
            from rosbags.serde import SerdeError

            with self._lock:
                self.stats.messages += 1
            if rx.key.rsplit("/", 2)[1:] != expected:
                with self._lock:
                    self.stats.other_type += 1
                return
            try:
                message = self.store.deserialize_cdr(rx.payload, type_name)
                values = [(column, field_value(message, signal)) for column, signal in columns]
            except (SerdeError, AttributeError, TypeError, ValueError):
                with self._lock:
                    self.stats.undecodable += 1
                return
            self.received(values)

        return on_message

    def describe_missing(self, columns: tuple[str, ...]) -> str:
        return ", ".join(f"{column} ({self.keys[self.mapping.signals()[column].topic]})" for column in columns)

    def describe(self) -> list[str]:
        with self._lock, self.lock:
            stats = self.stats
            return [
                f"received {stats.messages} messages: used {self.used_text()}; refused {stats.undecodable} "
                f"undecodable, {self.non_finite} not finite, {stats.other_type} of another type or type definition "
                "(type hash)",
                self.describe_grid(),
            ]

    def close(self) -> None:
        for subscription in self._subscriptions:
            subscription.close()
        self._subscriptions.clear()

    def __enter__(self) -> Ros2Source:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()


def describe_keys(source: Ros2Source) -> list[str]:
    """One line per subscribed topic: its columns and its exact rmw_zenoh key."""
    lines = []
    for topic, columns in source.mapping.topics().items():
        names = ", ".join(column for column, _ in columns)
        lines.append(f"  {names:<10} {source.keys[topic]}")
    return lines


#: diagnostic_msgs/msg/DiagnosticStatus's levels (its constants OK, WARN, ERROR, STALE).
STATUS_OK, STATUS_WARN, STATUS_ERROR, STATUS_STALE = 0, 1, 2, 3
#: The service's level as a DiagnosticStatus level: FAULT is ERROR, STALE is STALE.
DIAGNOSTIC_LEVEL = {"OK": STATUS_OK, "WARN": STATUS_WARN, "FAULT": STATUS_ERROR, "STALE": STATUS_STALE}
DIAGNOSTIC_TYPE = "diagnostic_msgs/msg/DiagnosticStatus"
#: rmw_zenoh's compact QoS of a publisher (reliable, volatile, keep last 7): the form of its design document's example.
PUBLISHER_QOS = "::,7:,:,:,,"
#: The ROS 2 node the republished topics belong to, as the ROS 2 graph lists it.
NODE_NAME = "agv_fe_bridge"


class StatusRepublisher:
    """One of the service's streams of one vehicle (``kind``), republished as a ROS 2 topic of
    ``diagnostic_msgs/msg/DiagnosticStatus`` for the vehicle's own nodes.

    Each message of the stream becomes a status (:meth:`status`, by the subclass) put on the topic's rmw_zenoh key
    with rmw_zenoh's attachment. A liveliness token of rmw_zenoh's format announces the publisher, entity
    ``entity_id`` of the node ``agv_fe_bridge`` (``ros2 topic list``); the node's own token (``ros2 node list``) goes
    with entity 1, so a bridge that republishes several streams numbers them 1, 2... Each publisher has a GID of
    its own: the session's id with the entity id in its last byte. A message that does not decode is counted in
    :attr:`bad`, never fatal.
    """

    kind: Literal["estimate", "alarm"]

    def __init__(
        self,
        session: zenoh.Session,
        store: Any,
        domain_id: int,
        topic: str,
        vehicle_id: str,
        prefix: str,
        entity_id: int = 1,
    ) -> None:
        from agv_protocol.wire import vehicle_key
        from edge_client.transport import Publication

        self.store = store
        self.vehicle_id = vehicle_id
        self.sent = 0
        self.bad = 0
        zid = str(session.zid())
        self._gid = bytes.fromhex(zid.rjust(32, "0")[-32:])[:15] + bytes([entity_id])
        type_hash = self.store.hash_rihs01(DIAGNOSTIC_TYPE)
        self.key = topic_key(domain_id, topic, DIAGNOSTIC_TYPE, type_hash)
        node = f"@ros2_lv/{domain_id}/{zid}/0/0/NN/%/%/{NODE_NAME}"
        entity = (
            f"@ros2_lv/{domain_id}/{zid}/0/{entity_id}/MP/%/%/{NODE_NAME}/{topic.replace('/', '%')}/"
            f"{dds_type_name(DIAGNOSTIC_TYPE)}/{type_hash}/{PUBLISHER_QOS}"
        )
        self._publication = Publication(session, self.key, token_keys=(node, entity) if entity_id == 1 else (entity,))
        self._start_state()  # before the subscription: a message may arrive at once
        try:
            self._subscription = Subscription(session, vehicle_key(vehicle_id, self.kind, prefix), self._on_message)
        except BaseException:
            self._publication.close()
            raise

    def _start_state(self) -> None:
        """Set up what :meth:`status` keeps between messages (a subclass's; nothing here)."""

    def status(self, payload: bytes) -> Any:
        """The DiagnosticStatus of one message of the stream; :class:`~agv_protocol.wire.ProtocolError` if it does
        not decode."""
        raise NotImplementedError

    def diagnostic_status(self, level: int, name: str, message: str, values: dict[str, str]) -> Any:
        t = self.store.types
        return t[DIAGNOSTIC_TYPE](
            level=level,
            name=name,
            message=message,
            hardware_id=self.vehicle_id,
            values=[t["diagnostic_msgs/msg/KeyValue"](key=k, value=v) for k, v in values.items()],
        )

    def _on_message(self, rx: Received) -> None:
        # zenoh's thread: decode, convert, put; never raise
        from agv_protocol.wire import ProtocolError

        try:
            status = self.status(rx.payload)
        except ProtocolError:
            self.bad += 1
            return
        payload = bytes(self.store.serialize_cdr(status, DIAGNOSTIC_TYPE))
        self.sent += 1
        self._publication.put(payload, rmw_attachment(self.sent, time.time_ns(), self._gid))

    def close(self) -> None:
        self._subscription.close()
        self._publication.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()


class EstimateRepublisher(StatusRepublisher):
    """The service's estimates of one vehicle as a ROS 2 topic (``--republish``).

    Each estimate becomes a status of level OK / WARN / ERROR (FAULT) from the estimate's level, name
    ``agv_fe/<vehicle>``, and the values (seq, vx, vy, r, torque_fault, steer_fault, in_domain, gain_version) as
    key-value strings.
    """

    kind = "estimate"

    def status(self, payload: bytes) -> Any:
        from agv_protocol.wire import Estimate

        estimate = Estimate.decode(payload)
        values = {
            "seq": str(estimate.seq),
            "vx": repr(estimate.vx),
            "vy": repr(estimate.vy),
            "r": repr(estimate.r),
            "torque_fault": repr(estimate.torque_fault),
            "steer_fault": repr(estimate.steer_fault),
            "in_domain": str(estimate.in_domain).lower(),
            "gain_version": estimate.gain_version,
        }
        return self.diagnostic_status(
            DIAGNOSTIC_LEVEL.get(estimate.level, STATUS_ERROR),
            f"agv_fe/{self.vehicle_id}",
            f"torque fault {estimate.torque_fault:.1f} N m, steering fault {estimate.steer_fault:.4f} rad",
            values,
        )


class AlarmRepublisher(StatusRepublisher):
    """The service's alarm events of one vehicle as a ROS 2 topic (``--republish-alarms``).

    Each event becomes a status named ``agv_fe/<vehicle>/<kind>`` (one diagnostic component per alarm kind, as a
    diagnostic aggregator or rqt_robot_monitor shows them), message the alarm's state and text, and the values
    id, kind, state, level (the service's own: WARN, FAULT, STALE), t_ns and, where the alarm has them, value and
    threshold. Its level is the condition's: WARN, ERROR (FAULT) or STALE while the alarm is raised, OK once it is
    cleared; an acknowledgement keeps the level of the condition last seen for that alarm id (OK after its
    ``cleared``, the alarm's level otherwise).
    """

    kind = "alarm"
    #: ids of the alarms whose last condition event was ``cleared`` (zenoh's thread only)
    _cleared: set[str]

    def _start_state(self) -> None:
        self._cleared = set()

    def status(self, payload: bytes) -> Any:
        from agv_protocol.wire import Alarm

        alarm = Alarm.decode(payload)
        if alarm.state == "raised":
            self._cleared.discard(alarm.id)
        elif alarm.state == "cleared":
            self._cleared.add(alarm.id)
        gone = alarm.id in self._cleared
        if alarm.state == "acknowledged" and gone:
            self._cleared.discard(alarm.id)  # cleared and acknowledged: the alarm is closed
        values = {"id": alarm.id, "kind": alarm.kind, "state": alarm.state, "level": alarm.level}
        values |= {"value": repr(alarm.value)} if alarm.value is not None else {}
        values |= {"threshold": repr(alarm.threshold)} if alarm.threshold is not None else {}
        values["t_ns"] = str(alarm.t_ns)
        return self.diagnostic_status(
            STATUS_OK if gone else DIAGNOSTIC_LEVEL[alarm.level],
            f"agv_fe/{self.vehicle_id}/{alarm.kind}",
            f"{alarm.state}: {alarm.message}" if alarm.message else alarm.state,
            values,
        )
