"""`agv-fe publish-csv`: stream a recorded 100 Hz CSV to the service as one vehicle."""

from __future__ import annotations

import argparse
import contextlib
import math
import textwrap
from pathlib import Path
from typing import Any

from agv_fe.common import CommandError, add_bag_argument, fail, read_input
from agv_fe.edge_args import (
    ProgressPrinter,
    add_estimates_argument,
    add_transport_arguments,
    stop_on_interrupt,
    transport_options,
)


def register(sub: Any) -> None:
    parser = sub.add_parser(
        "publish-csv",
        help="stream a recorded CSV to the service at 100 Hz",
        description="Publish a recording (columns t, vx, r, torque, steer, as for `agv-fe replay`) as one "
        "vehicle's measurements at 100 Hz, with sequence numbers (the row index), timestamps (start time + "
        "k * 10 ms) and a liveliness token, and collect the estimates and alarms the service sends back. "
        "This is how a real vehicle's log reaches the service.",
    )
    parser.add_argument("input", metavar="FILE.csv", help="recorded stream (a ROS 2 bag with --map)")
    add_bag_argument(parser)
    parser.add_argument("--vehicle", required=True, metavar="ID", help="vehicle id (1-64 of A-Z a-z 0-9 _ . -)")
    parser.add_argument(
        "--buffer", type=float, default=2.0, metavar="S", help="buffer while undeliverable (default 2 s)"
    )
    parser.add_argument("--log", metavar="FILE.jsonl", help="write every estimate and alarm received, one JSON a line")
    parser.add_argument(
        "--progress", type=float, default=1.0, metavar="S", help="seconds between progress lines (default 1)"
    )
    parser.add_argument(
        "--payload-kg",
        type=float,
        default=None,
        metavar="KG",
        help="report this payload on the vehicle's payload key before streaming (the load the recording was "
        "driven with): the service models the vehicle with it, as `replay --payload-kg` does",
    )
    add_estimates_argument(parser)
    add_transport_arguments(parser)
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from agv_protocol.wire import ProtocolError, check_vehicle_id
    from agv_protocol.zenoh_session import TransportError
    from edge_client.publisher import FleetPublisher, PublisherOptions
    from edge_client.sources import RecordingSource
    from edge_client.transport import close_session, open_session, report_payload

    try:
        try:
            check_vehicle_id(args.vehicle)
        except ProtocolError as exc:
            raise CommandError(f"--vehicle: {exc}") from exc
        if not (math.isfinite(args.buffer) and 0 <= args.buffer <= 600):
            raise CommandError(f"--buffer: expected seconds in [0, 600], got {args.buffer}")
        if not (math.isfinite(args.progress) and args.progress > 0):
            raise CommandError(f"--progress: expected seconds > 0, got {args.progress}")
        if args.payload_kg is not None and not (math.isfinite(args.payload_kg) and args.payload_kg >= 0):
            raise CommandError(f"--payload-kg: expected kg >= 0, got {args.payload_kg}")
        transport = transport_options(args)
        recording = read_input(args.input, args.map)
    except CommandError as exc:
        return fail(exc)
    source = RecordingSource(args.vehicle, recording)
    seconds = len(recording) * source.sample_period_s
    print(textwrap.fill(f"publishing {len(recording)} samples ({seconds:.2f} s) of {args.input} as {args.vehicle}", 80))
    print(textwrap.fill(f"zenoh {transport.describe()}", width=80))
    try:
        session = open_session(transport)
    except TransportError as exc:
        return fail(CommandError(str(exc)))
    progress = ProgressPrinter()
    options = PublisherOptions(
        truth_rate_hz=0.0, buffer_s=args.buffer, prefix=args.prefix, warmup_s=0.0, estimate_encoding=args.estimates
    )
    if args.payload_kg is not None:
        reached = report_payload(session, args.vehicle, args.payload_kg, args.prefix)
        print(f"payload {args.payload_kg:g} kg reported" + ("" if reached else " (no service subscribed yet)"))
    try:
        with contextlib.ExitStack() as stack:
            stack.callback(close_session, session)
            stack.callback(progress.finish)
            log = stack.enter_context(Path(args.log).open("w")) if args.log else None
            publisher = stack.enter_context(FleetPublisher(session, source, options, log=log))
            stop = stack.enter_context(stop_on_interrupt())
            report = publisher.run(stop=stop, on_progress=progress, progress_period_s=args.progress)
    except OSError as exc:
        return fail(CommandError(f"{args.log}: cannot write: {exc.strerror}"))
    record = report.vehicles[0]
    last = record.last_estimate
    print(
        f"sent {report.sent} of {len(recording)} samples in {report.elapsed_s:.2f} s ({report.sample_rate_hz:.2f} Hz, "
        f"late ticks {report.pacing.late}); lost {report.lost}, unsent at end {report.unsent_at_end}"
    )
    print(
        f"estimates received {report.estimates}; alarms {report.alarms}; round trip p50 {report.rtt_p50_ms:.2f} ms, "
        f"p99 {report.rtt_p99_ms:.2f} ms"
    )
    if last is not None:
        print(
            f"last estimate (seq {last.seq}): v_y {last.vy:.3f} m/s, T_f {last.torque_fault:.1f} N m, "
            f"delta_f {last.steer_fault:.4f} rad, level {last.level}"
        )
    for event in record.alarm_events:
        print(f"alarm {event.alarm.state}: {event.alarm.kind} ({event.alarm.level}) {event.alarm.message}".rstrip())
    if report.estimates == 0:
        print("no estimate came back: is the service running and connected to the same router?")
    return 0
