"""What the edge commands (fleet, dashboard, publish-csv) share: zenoh flags, progress lines, Ctrl-C."""

from __future__ import annotations

import argparse
import contextlib
import math
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from agv_fe.common import CommandError

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
#: A live bridge waits at most this long for a subscriber of its measurements before its first sample [s]: it keeps
#: no buffer, so a sample sent before Zenoh has learned the service's subscription from the router is lost.
BRIDGE_LINK_WAIT_S = 2.0


def add_transport_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("zenoh")
    group.add_argument(
        "--connect",
        action="append",
        metavar="ENDPOINT",
        help=f"endpoint to connect to, repeatable (default in client mode: {DEFAULT_ENDPOINT})",
    )
    group.add_argument("--listen", action="append", metavar="ENDPOINT", help="endpoint to listen on (peer mode)")
    group.add_argument(
        "--mode", choices=("client", "peer"), default="client", help="client of a router (default) or peer"
    )
    group.add_argument(
        "--connect-timeout",
        type=float,
        default=10.0,
        metavar="S",
        help="how long to wait for the router at start, -1 = for ever (default 10); "
        "after that, lost connections are retried for ever",
    )
    group.add_argument("--prefix", default="agv", help="key-expression prefix of the protocol (default agv)")
    group.add_argument(
        "--zenoh-config",
        metavar="FILE.json5",
        help="Zenoh configuration file to start from: TLS, mutual TLS, user/password (deploy/zenoh/secure/"
        "vehicle.json5, docs/deployment.md); endpoints and mode stay these flags",
    )
    group.add_argument(
        "--zenoh-credentials",
        metavar="FILE",
        help="USER:PASSWORD for Zenoh's user/password authentication (make certs writes one per identity)",
    )


def add_estimates_argument(parser: argparse.ArgumentParser) -> None:
    """--estimates: which of its estimate keys a vehicle reads back (docs/protocol.md)."""
    parser.add_argument(
        "--estimates",
        choices=("json", "binary"),
        default="json",
        help="read the estimates back as JSON (.../estimate, default) or in the binary encoding (.../estimate.bin)",
    )


def transport_options(args: argparse.Namespace) -> Any:
    """The TransportOptions the flags describe; a CommandError for impossible combinations."""
    from edge_client.transport import TransportOptions

    connect = tuple(args.connect or ())
    listen = tuple(args.listen or ())
    if args.mode == "client" and not connect:
        connect = (DEFAULT_ENDPOINT,)
    if args.mode == "peer" and not (connect or listen):
        raise CommandError("--mode peer needs --connect or --listen: multicast scouting is off")
    if not math.isfinite(args.connect_timeout) or (args.connect_timeout < 0 and args.connect_timeout != -1):
        raise CommandError(f"--connect-timeout: expected seconds >= 0 or -1, got {args.connect_timeout}")
    if not args.prefix or "/" in args.prefix or "*" in args.prefix:
        raise CommandError(f"--prefix: expected one key chunk without '/' or '*', got {args.prefix!r}")
    if args.zenoh_credentials and not args.zenoh_config:
        raise CommandError("--zenoh-credentials needs --zenoh-config (user/password goes over TLS)")
    return TransportOptions(
        mode=args.mode,
        connect=connect,
        listen=listen,
        connect_timeout_s=args.connect_timeout,
        prefix=args.prefix,
        config_file=Path(args.zenoh_config) if args.zenoh_config else None,
        credentials_file=Path(args.zenoh_credentials) if args.zenoh_credentials else None,
    )


@contextlib.contextmanager
def stop_on_interrupt() -> Iterator[threading.Event]:
    """An event that Ctrl-C sets instead of raising, so a run can end cleanly and report."""
    stop = threading.Event()
    previous = signal.signal(signal.SIGINT, lambda *_: stop.set())
    try:
        yield stop
    finally:
        signal.signal(signal.SIGINT, previous)


class ProgressPrinter:
    """Progress lines: rewritten in place on a terminal, one per line otherwise."""

    def __init__(self) -> None:
        self.tty = sys.stdout.isatty()
        self.printed = False

    def __call__(self, progress: Any) -> None:
        line: str = progress.line()
        if self.tty:
            print("\r" + line.ljust(80), end="", flush=True)
        else:
            print(line, flush=True)
        self.printed = True

    def finish(self) -> None:
        if self.tty and self.printed:
            print()


# ---------------------------------------------------------------------------------------------- live bridges


def add_bridge_arguments(parser: argparse.ArgumentParser) -> None:
    """The flags every live bridge (ros2-bridge, can-bridge) has besides its own, the zenoh ones included."""
    parser.add_argument("--vehicle", required=True, metavar="ID", help="vehicle id (1-64 of A-Z a-z 0-9 _ . -)")
    parser.add_argument(
        "--duration", type=float, default=None, metavar="S", help="stop after S seconds (default: until Ctrl-C)"
    )
    parser.add_argument(
        "--wait", type=float, default=30.0, metavar="S", help="how long to wait for every signal at start (default 30)"
    )
    parser.add_argument("--log", metavar="FILE.jsonl", help="write every estimate and alarm received, one JSON a line")
    parser.add_argument(
        "--progress", type=float, default=5.0, metavar="S", help="seconds between progress lines (default 5)"
    )
    add_estimates_argument(parser)
    add_transport_arguments(parser)


def check_bridge_arguments(args: argparse.Namespace) -> Any:
    """The transport options of a live bridge's flags (:func:`add_bridge_arguments`), or a CommandError naming the
    flag at fault."""
    from agv_protocol.wire import ProtocolError, check_vehicle_id

    try:
        check_vehicle_id(args.vehicle)
    except ProtocolError as exc:
        raise CommandError(f"--vehicle: {exc}") from exc
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise CommandError(f"--duration: expected seconds > 0, got {args.duration}")
    if not (math.isfinite(args.wait) and args.wait >= 0):
        raise CommandError(f"--wait: expected seconds >= 0, got {args.wait}")
    if not (math.isfinite(args.progress) and args.progress > 0):
        raise CommandError(f"--progress: expected seconds > 0, got {args.progress}")
    return transport_options(args)


def run_bridge(
    args: argparse.Namespace,
    session: Any,
    open_source: Callable[[contextlib.ExitStack[Any]], Any],
    extra_lines: Callable[[], list[str]] = list,
) -> int:
    """Run a live bridge: the source ``open_source`` enters on the stack (with whatever else it needs closed) fed
    to the 100 Hz publisher until --duration or Ctrl-C, then what it read and what came back printed; the session
    is closed at the end. Returns the command's exit status."""
    from agv_fe.common import fail
    from edge_client.publisher import FleetPublisher, PublisherOptions
    from edge_client.recording import RecordingError
    from edge_client.transport import close_session

    options = PublisherOptions(
        truth_rate_hz=0.0,
        buffer_s=0.0,
        prefix=args.prefix,
        warmup_s=0.0,
        estimate_encoding=args.estimates,
        link_wait_s=BRIDGE_LINK_WAIT_S,
    )
    progress = ProgressPrinter()
    try:
        with contextlib.ExitStack() as stack:
            stack.callback(close_session, session)
            source = open_source(stack)
            stack.callback(progress.finish)
            log = stack.enter_context(Path(args.log).open("w")) if args.log else None
            publisher = stack.enter_context(FleetPublisher(session, source, options, log=log))
            stop = stack.enter_context(stop_on_interrupt())
            report = publisher.run(
                args.duration, stop=stop, on_progress=progress, progress_period_s=args.progress, drain_s=1.0
            )
            lines = [*source.describe(), *extra_lines()]
    except RecordingError as exc:
        return fail(CommandError(str(exc)))
    except OSError as exc:
        return fail(CommandError(f"{args.log}: cannot write: {exc.strerror}"))
    print_bridge_report(lines, report)
    return 0


def print_bridge_report(lines: list[str], report: Any) -> None:
    """What a bridge read and refused (``lines``), then what it sent and what came back (the publisher's report)."""
    print("\n".join(lines))
    print(
        f"sent {report.sent} measurements in {report.elapsed_s:.2f} s; estimates received {report.estimates}, "
        f"alarms {report.alarms}; round trip p50 {report.rtt_p50_ms:.2f} ms, p99 {report.rtt_p99_ms:.2f} ms"
    )
    if report.lost:
        print(f"lost {report.lost} measurements at ticks when no subscriber was reachable")
    last = report.vehicles[0].last_estimate
    if last is not None:
        print(
            f"last estimate (seq {last.seq}): v_y {last.vy:.3f} m/s, T_f {last.torque_fault:.1f} N m, "
            f"delta_f {last.steer_fault:.4f} rad, level {last.level}"
        )
    if report.estimates == 0:
        print("no estimate came back: is the service running and connected to the same router?")
