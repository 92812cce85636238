"""`agv-fe ros2-bridge`: a ROS 2 vehicle's topics (rmw_zenoh) to the service's measurements, live, at 100 Hz."""

from __future__ import annotations

import argparse
import contextlib
import re
import textwrap
from typing import Any

from agv_fe.common import CommandError, fail
from agv_fe.edge_args import add_bridge_arguments, check_bridge_arguments, run_bridge


def register(sub: Any) -> None:
    parser = sub.add_parser(
        "ros2-bridge",
        help="bridge a ROS 2 vehicle (rmw_zenoh) to the service, live",
        description="Subscribe over Zenoh to the ROS 2 topics a mapping file names, on the key expressions of ROS 2's "
        "Zenoh middleware rmw_zenoh (<domain_id>/<topic>/<type>/<type hash>), decode their CDR messages (rosbags), "
        "hold the latest value of each signal and send it every 10 ms as one vehicle's measurement in the service's "
        "protocol; a tick at which a signal is older than the mapping's max_age_s is not sent. Collects the "
        "estimates and alarms that come back. Join the zenoh router the vehicle's nodes use (rmw_zenohd, "
        "tcp/127.0.0.1:7447 by default) and that the service reaches. Needs the 'ros2' extra (rosbags).",
    )
    parser.add_argument("--map", required=True, metavar="MAPPING.yaml", help="which topic field is which signal")
    add_bridge_arguments(parser)
    parser.add_argument(
        "--republish",
        metavar="TOPIC",
        help="also republish the vehicle's estimates as this ROS 2 topic (diagnostic_msgs/msg/DiagnosticStatus, "
        "level OK / WARN / ERROR), for the vehicle's own nodes",
    )
    parser.add_argument(
        "--republish-alarms",
        metavar="TOPIC",
        help="also republish the vehicle's alarm events as this ROS 2 topic (diagnostic_msgs/msg/DiagnosticStatus "
        "named agv_fe/<vehicle>/<kind>, level WARN / ERROR / STALE while raised, OK once cleared)",
    )
    parser.set_defaults(handler=run)


def _check(args: argparse.Namespace) -> tuple[Any, Any]:
    """The mapping and the transport options, or a CommandError naming the flag at fault."""
    from edge_client.recording import RecordingError

    transport = check_bridge_arguments(args)
    for flag, topic, example in (("--republish", args.republish, "/agv_fe/status"),
                                 ("--republish-alarms", args.republish_alarms, "/agv_fe/alarms")):  # fmt: skip
        if topic is not None and not re.fullmatch(r"(/[A-Za-z_][A-Za-z0-9_]*)+", topic):
            raise CommandError(f"{flag}: expected a fully qualified topic name such as {example}, got {topic!r}")
    if args.republish is not None and args.republish == args.republish_alarms:
        raise CommandError(f"--republish and --republish-alarms name the same topic {args.republish}")
    try:
        from edge_client.ros2 import load_ros_mapping, typestore_for
    except ImportError as exc:
        raise CommandError(f"ros2-bridge needs rosbags: pip install 'agv-fault-estimator[ros2]' ({exc})") from exc
    try:
        mapping = load_ros_mapping(args.map)
        typestore_for(mapping)  # unknown types and field paths are refused before joining the network
    except RecordingError as exc:
        raise CommandError(str(exc)) from exc
    return mapping, transport


def run(args: argparse.Namespace) -> int:
    from agv_protocol.zenoh_session import TransportError
    from edge_client.ros2_bridge import AlarmRepublisher, EstimateRepublisher, Ros2Source, describe_keys
    from edge_client.transport import open_session

    try:
        mapping, transport = _check(args)
        session = open_session(transport)
    except (CommandError, TransportError) as exc:
        return fail(exc if isinstance(exc, CommandError) else CommandError(str(exc)))
    print(textwrap.fill(f"bridging ROS 2 domain {mapping.domain_id} to vehicle {args.vehicle}; zenoh "
                        f"{transport.describe()}", 100))  # fmt: skip
    republishers: list[Any] = []

    def open_source(stack: contextlib.ExitStack[Any]) -> Any:
        source = stack.enter_context(Ros2Source(session, mapping, args.vehicle, wait_s=args.wait))
        print("\n".join(["subscribed (signal, rmw_zenoh key):", *describe_keys(source)]), flush=True)
        streams = ((EstimateRepublisher, args.republish), (AlarmRepublisher, args.republish_alarms))
        wanted = [(republisher, topic) for republisher, topic in streams if topic]
        for entity_id, (republisher, topic) in enumerate(wanted, start=1):  # the publishers of the bridge's node
            opened = republisher(session, source.store, mapping.domain_id, topic, args.vehicle, args.prefix, entity_id)
            republishers.append(stack.enter_context(opened))
            print(f"{opened.kind}s republished on {opened.key}", flush=True)
        return source

    def extra_lines() -> list[str]:
        return [f"republished {r.sent} {r.kind}s on {r.key}" for r in republishers]

    return run_bridge(args, session, open_source, extra_lines)
