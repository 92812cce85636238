"""`agv-fe fleet`: a simulated fleet of healthy and faulty vehicles publishing to the service at 100 Hz."""

from __future__ import annotations

import argparse
import math
import textwrap
from pathlib import Path
from typing import Any

from agv_fe.common import CommandError, fail
from agv_fe.edge_args import (
    ProgressPrinter,
    add_estimates_argument,
    add_transport_arguments,
    stop_on_interrupt,
    transport_options,
)

#: Mirrors edge_client.fleet_mix (MIX_KINDS, DEFAULT_MIX) without importing it at start-up; a test keeps them equal.
MIX_KINDS_HELP = "healthy, torque_bias, torque_loe, steer_bias, steer_sinusoidal, intermittent"
DEFAULT_MIX = "healthy=0.5,torque_bias=0.1,torque_loe=0.1,steer_bias=0.1,steer_sinusoidal=0.1,intermittent=0.1"


def register(sub: Any) -> None:
    parser = sub.add_parser(
        "fleet",
        help="simulate a fleet and publish it to the service",
        description="Simulate N vehicles (RK4 plant at 1 ms, random drives inside the operating bounds, "
        "injected faults) and publish their measurements at 100 Hz through one zenoh session. Prints a "
        "progress line (rate, sent, lost, estimates, alarms, link, round trip) and, at the end, per vehicle: "
        "the injected fault, the estimated fault peaks, the alarms and how soon after the onset they came.",
    )
    parser.add_argument("--vehicles", type=int, default=10, metavar="N", help="number of vehicles (default 10)")
    parser.add_argument("--duration", type=float, default=60.0, metavar="S", help="seconds to run (default 60)")
    parser.add_argument(
        "--scenario-mix",
        default=DEFAULT_MIX,
        metavar="MIX",
        help=f"KIND=WEIGHT,... with kinds {MIX_KINDS_HELP} (weights are normalised), or a .json/.yaml "
        f"file holding a scenario or a list of scenarios to cycle through (default {DEFAULT_MIX})",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the drives, faults and noise (default 0)")
    parser.add_argument(
        "--noise",
        default="realistic",
        help="sensor noise: 'realistic' (default: sigma v_x 0.05 m/s, r 0.005 rad/s), 'none' or 'SIGMA_VX,SIGMA_R'",
    )
    parser.add_argument(
        "--gusts", action="store_true", help="random lateral wind gusts of 300-800 N on every vehicle (a disturbance)"
    )
    parser.add_argument(
        "--loads",
        action="store_true",
        help="every vehicle carries a random payload of 0-25 %% of its mass, reported to the service at the start",
    )
    parser.add_argument(
        "--hills",
        action="store_true",
        help="every vehicle drives a road that climbs and descends (grades within 2-6 %%), reporting the grade "
        "with each sample",
    )
    parser.add_argument("--id-prefix", default="veh", help="vehicle ids are PREFIX-000, PREFIX-001, ...")
    parser.add_argument(
        "--truth-hz", type=float, default=10.0, metavar="HZ", help="ground-truth rate, 0 = off (default 10)"
    )
    parser.add_argument(
        "--buffer", type=float, default=2.0, metavar="S", help="per-vehicle buffer while undeliverable (default 2 s)"
    )
    parser.add_argument("--log", metavar="FILE.jsonl", help="write every estimate and alarm received, one JSON a line")
    parser.add_argument("--summary-json", metavar="FILE.json", help="also write the summary as JSON")
    parser.add_argument(
        "--progress", type=float, default=1.0, metavar="S", help="seconds between progress lines (default 1)"
    )
    add_estimates_argument(parser)
    add_transport_arguments(parser)
    parser.set_defaults(handler=run)


def _check(args: argparse.Namespace) -> None:
    if not 1 <= args.vehicles <= 10_000:
        raise CommandError(f"--vehicles: expected 1 to 10000, got {args.vehicles}")
    if not (math.isfinite(args.duration) and 0 < args.duration <= 86_400):
        raise CommandError(f"--duration: expected seconds in (0, 86400], got {args.duration}")
    if not (math.isfinite(args.truth_hz) and 0 <= args.truth_hz <= 100):
        raise CommandError(f"--truth-hz: expected 0 to 100, got {args.truth_hz}")
    if not (math.isfinite(args.buffer) and 0 <= args.buffer <= 600):
        raise CommandError(f"--buffer: expected seconds in [0, 600], got {args.buffer}")
    if not (math.isfinite(args.progress) and args.progress > 0):
        raise CommandError(f"--progress: expected seconds > 0, got {args.progress}")


def run(args: argparse.Namespace) -> int:
    from agv_fe.commands.simulate import parse_noise
    from agv_protocol.zenoh_session import TransportError
    from edge_client.fleet import FleetConfig, run_fleet, write_summary_json
    from edge_client.fleet_mix import MixError
    from edge_client.publisher import PublisherOptions
    from edge_client.scenario import ScenarioError

    try:
        _check(args)
        config = FleetConfig(
            n_vehicles=args.vehicles,
            duration_s=args.duration,
            mix=args.scenario_mix,
            seed=args.seed,
            noise=parse_noise(args.noise),
            gusts=args.gusts,
            loads=args.loads,
            hills=args.hills,
            id_prefix=args.id_prefix,
            transport=transport_options(args),
            publisher=PublisherOptions(
                truth_rate_hz=args.truth_hz, buffer_s=args.buffer, prefix=args.prefix, estimate_encoding=args.estimates
            ),
            log_path=Path(args.log) if args.log else None,
        )
        try:
            members = config.members()
        except (MixError, ScenarioError, ValueError) as exc:
            raise CommandError(f"--scenario-mix: {exc}") from exc
    except CommandError as exc:
        return fail(exc)
    kinds: dict[str, int] = {}
    for member in members:
        kinds[member.kind] = kinds.get(member.kind, 0) + 1
    mix_text = ", ".join(f"{n} {kind}" for kind, n in kinds.items())
    print(textwrap.fill(f"fleet of {len(members)} vehicles for {args.duration:g} s: {mix_text}", width=80))
    print(textwrap.fill(f"zenoh {config.transport.describe()}", width=80))
    progress = ProgressPrinter()
    try:
        with stop_on_interrupt() as stop:  # Ctrl-C ends the run early, with its summary
            summary = run_fleet(
                config, members=members, on_progress=progress, progress_period_s=args.progress, stop=stop
            )
    except TransportError as exc:
        return fail(CommandError(str(exc)))
    except OSError as exc:
        return fail(CommandError(f"{args.log}: cannot write: {exc.strerror}"))
    finally:
        progress.finish()
    print(summary.render_text(width=80), end="")
    if args.summary_json:
        try:
            write_summary_json(Path(args.summary_json), summary)
        except OSError as exc:
            return fail(CommandError(f"{args.summary_json}: cannot write: {exc.strerror}"))
    return 0
