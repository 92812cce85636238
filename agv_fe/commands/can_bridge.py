"""`agv-fe can-bridge`: a vehicle's CAN bus (python-can, a DBC) to the service's measurements, live, at 100 Hz."""

from __future__ import annotations

import argparse
import contextlib
import textwrap
from typing import Any

from agv_fe.common import CommandError, fail
from agv_fe.edge_args import add_bridge_arguments, check_bridge_arguments, run_bridge


def register(sub: Any) -> None:
    parser = sub.add_parser(
        "can-bridge",
        help="bridge a vehicle's CAN bus to the service, live",
        description="Read the vehicle's CAN bus with python-can (SocketCAN by default), decode the frames a mapping "
        "file names with the vehicle's DBC (cantools; the mapping of `agv-fe can2csv`), hold the latest value of "
        "each signal and send it every 10 ms as one vehicle's measurement in the service's protocol; a tick at "
        "which a signal is older than the mapping's max_age_s is not sent. Collects the estimates and alarms that "
        "come back. Needs the 'can' extra (python-can, cantools).",
    )
    parser.add_argument("--dbc", required=True, metavar="VEHICLE.dbc", help="the vehicle's CAN database")
    parser.add_argument("--map", required=True, metavar="MAPPING.yaml", help="which DBC signal is which column")
    parser.add_argument(
        "--interface", default="socketcan", help="python-can interface (default socketcan; pcan, kvaser, slcan...)"
    )
    parser.add_argument("--channel", default="can0", help="the interface's channel (default can0)")
    parser.add_argument("--bitrate", type=int, default=None, help="bit rate, for interfaces that set it [bit/s]")
    add_bridge_arguments(parser)
    parser.set_defaults(handler=run)


def _check(args: argparse.Namespace) -> tuple[Any, Any, Any]:
    """The mapping, the DBC database and the transport options, or a CommandError naming what is wrong."""
    transport = check_bridge_arguments(args)
    if args.bitrate is not None and args.bitrate <= 0:
        raise CommandError(f"--bitrate: expected bit/s > 0, got {args.bitrate}")
    try:
        import can  # noqa: F401 - the extra is there
        import cantools  # noqa: F401
    except ImportError as exc:
        raise CommandError(
            f"can-bridge needs python-can and cantools: pip install 'agv-fault-estimator[can]' ({exc})"
        ) from exc
    from edge_client.can_log import load_dbc, load_mapping, resolve
    from edge_client.recording import RecordingError

    try:
        mapping = load_mapping(args.map)
        database = load_dbc(args.dbc)
        resolve(database, mapping, args.dbc)  # every mapped message and signal exists, before the bus is opened
    except RecordingError as exc:
        raise CommandError(str(exc)) from exc
    return mapping, database, transport


def open_bus(args: argparse.Namespace) -> Any:
    """The python-can bus the flags name; a CommandError says why it cannot be opened."""
    import can

    options: dict[str, Any] = {"interface": args.interface, "channel": args.channel}
    if args.bitrate is not None:
        options["bitrate"] = args.bitrate
    try:
        return can.Bus(**options)
    except (can.CanError, OSError, ValueError, ImportError, NotImplementedError) as exc:
        raise CommandError(f"cannot open CAN interface {args.interface!r} channel {args.channel!r}: {exc}") from exc


def run(args: argparse.Namespace) -> int:
    from agv_protocol.zenoh_session import TransportError
    from edge_client.can_bridge import CanSource
    from edge_client.transport import open_session

    try:
        mapping, database, transport = _check(args)
        bus = open_bus(args)
    except CommandError as exc:
        return fail(exc)
    try:
        session = open_session(transport)
    except TransportError as exc:
        bus.shutdown()
        return fail(CommandError(str(exc)))
    print(textwrap.fill(f"bridging CAN {args.interface} {args.channel} to vehicle {args.vehicle}; zenoh "
                        f"{transport.describe()}", 100))  # fmt: skip

    def open_source(stack: contextlib.ExitStack[Any]) -> Any:
        stack.callback(bus.shutdown)
        return stack.enter_context(CanSource(bus, database, mapping, args.vehicle, dbc_name=args.dbc, wait_s=args.wait))

    return run_bridge(args, session, open_source)
