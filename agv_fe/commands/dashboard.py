"""`agv-fe dashboard`: a live terminal table of every vehicle the service estimates, over zenoh only."""

from __future__ import annotations

import argparse
import math
from typing import Any

from agv_fe.common import CommandError, fail
from agv_fe.edge_args import add_transport_arguments, stop_on_interrupt, transport_options


def register(sub: Any) -> None:
    parser = sub.add_parser(
        "dashboard",
        help="live table of all vehicles' estimates and alarms",
        description="Subscribe over zenoh to every vehicle's estimates, alarms and liveliness, and show a "
        "table (level, v_x, estimated v_y, torque and steering fault estimates, active alarms) redrawn a few "
        "times a second. Needs only a zenoh router, no REST access. Ctrl-C to quit. When the output is not a "
        "terminal, the table is printed once at the end (use --duration).",
    )
    parser.add_argument("--refresh", type=float, default=4.0, metavar="HZ", help="redraws per second (default 4)")
    parser.add_argument(
        "--duration", type=float, default=None, metavar="S", help="quit after S seconds (default: run until Ctrl-C)"
    )
    add_transport_arguments(parser)
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from agv_protocol.zenoh_session import TransportError
    from edge_client.dashboard import run_dashboard
    from edge_client.transport import close_session, open_session

    try:
        if not (math.isfinite(args.refresh) and 0.5 <= args.refresh <= 50):
            raise CommandError(f"--refresh: expected 0.5 to 50 redraws per second, got {args.refresh}")
        if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
            raise CommandError(f"--duration: expected seconds > 0, got {args.duration}")
        transport = transport_options(args)
        try:
            session = open_session(transport)
        except TransportError as exc:
            raise CommandError(str(exc)) from exc
    except CommandError as exc:
        return fail(exc)
    try:
        with stop_on_interrupt() as stop:
            run_dashboard(session, transport.prefix, refresh_hz=args.refresh, duration_s=args.duration, stop=stop)
    finally:
        close_session(session)
    return 0
