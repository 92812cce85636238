"""`agv-fe can-bridge`: a vehicle's CAN bus (python-can, a DBC) to the service's measurements, live, at 100 Hz."""

from __future__ import annotations

import argparse
import contextlib
import textwrap
from pathlib import Path
from typing import Any

from agv_fe.common import CommandError, fail
from agv_fe.edge_args import (
    ProgressPrinter,
    add_bridge_arguments,
    add_transport_arguments,
    check_bridge_arguments,
    print_bridge_report,
    stop_on_interrupt,
    transport_options,
)


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
    add_transport_arguments(parser)
    parser.set_defaults(handler=run)


def _check(args: argparse.Namespace) -> tuple[Any, Any, Any]:
    """The mapping, the DBC database and the transport options, or a CommandError naming what is wrong."""
    check_bridge_arguments(args)
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
    return mapping, database, transport_options(args)


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
    from edge_client.can_bridge import CanSource
    from edge_client.publisher import FleetPublisher, PublisherOptions
    from edge_client.recording import RecordingError
    from edge_client.transport import TransportError, close_session, open_session

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
    options = PublisherOptions(truth_rate_hz=0.0, buffer_s=0.0, prefix=args.prefix, warmup_s=0.0)
    progress = ProgressPrinter()
    try:
        with contextlib.ExitStack() as stack:
            stack.callback(close_session, session)
            stack.callback(bus.shutdown)
            source = stack.enter_context(
                CanSource(bus, database, mapping, args.vehicle, dbc_name=args.dbc, wait_s=args.wait)
            )
            stack.callback(progress.finish)
            log = stack.enter_context(Path(args.log).open("w")) if args.log else None
            publisher = stack.enter_context(FleetPublisher(session, source, options, log=log))
            stop = stack.enter_context(stop_on_interrupt())
            report = publisher.run(
                args.duration, stop=stop, on_progress=progress, progress_period_s=args.progress, drain_s=1.0
            )
            lines = source.describe()
    except RecordingError as exc:
        return fail(CommandError(str(exc)))
    except OSError as exc:
        return fail(CommandError(f"{args.log}: cannot write: {exc.strerror}"))
    print_bridge_report(lines, report)
    return 0
