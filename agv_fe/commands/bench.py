"""`agv-fe bench`: run the benchmarks and write their reports under docs/benchmarks/."""

from __future__ import annotations

import argparse
import importlib
from pathlib import Path
from typing import Any

#: Benchmark name -> module with ``run(out_dir) -> Path``.
BENCHMARKS = {
    "synthesis": "agv_fe.benchmarks.synthesis",
    "accuracy": "agv_fe.benchmarks.accuracy",
    "service_load": "agv_fe.benchmarks.service_load",
    "publisher": "agv_fe.benchmarks.publisher",
    "soak": "agv_fe.benchmarks.soak",
    "real_vehicle": "agv_fe.benchmarks.real_vehicle",
    "vehicle_variants": "agv_fe.benchmarks.vehicle_variants",
    "detection": "agv_fe.benchmarks.detection",
    "ros2_bridge": "agv_fe.benchmarks.ros2_bridge",
    "can_bridge": "agv_fe.benchmarks.can_bridge",
    "failover": "agv_fe.benchmarks.failover",
    "storage_capacity": "agv_fe.benchmarks.storage_capacity",
    "service_config": "agv_fe.benchmarks.service_config",
}


def register(sub: Any) -> None:
    parser = sub.add_parser(
        "bench",
        help="run the benchmarks, write docs/benchmarks/*.md",
        description="Speed, accuracy and capacity benchmarks. Figures are ratios or medians measured in one run. "
        "Run them from a checkout nobody edits meanwhile (a git worktree): their worker processes import the "
        "project's code as they start, and a report records the commit it ran at.",
    )
    parser.add_argument("--only", default=None, help=f"comma-separated subset of: {', '.join(BENCHMARKS)}")
    parser.add_argument("--out", default="docs/benchmarks", metavar="DIR", help="where to write the reports")
    parser.add_argument(
        "--soak-minutes",
        type=float,
        default=None,
        metavar="M",
        help="how long the soak benchmark holds its fleet (default 10; run it alone for hours: --only soak)",
    )
    parser.add_argument(
        "--detection-part",
        choices=("all", "effectiveness"),
        default="all",
        help="detection: 'effectiveness' runs only the effectiveness alarm rule (healthy fleet without the EKF, "
        "the losses of effectiveness) and writes detection_effectiveness.md instead of detection.md",
    )
    parser.add_argument(
        "--detection-hours",
        type=float,
        default=None,
        metavar="H",
        help="with --detection-part effectiveness: healthy vehicle-hours (default 100)",
    )
    parser.add_argument(
        "--detection-runs",
        type=int,
        default=None,
        metavar="N",
        help="with --detection-part effectiveness: runs per loss of effectiveness (default 120)",
    )
    parser.add_argument(
        "--detection-confidence-k",
        type=float,
        default=None,
        metavar="K",
        help="with --detection-part effectiveness: the effectiveness rule's k instead of the profile's "
        "(0: alpha_hat itself, the rule before the confidence bound)",
    )
    parser.set_defaults(handler=run)


def _options(name: str, args: argparse.Namespace) -> tuple[str, dict[str, Any]]:
    """The entry point of benchmark ``name`` and its options from the command line."""
    if name == "soak" and args.soak_minutes is not None:
        return "run", {"minutes": args.soak_minutes}
    if name == "detection" and args.detection_part == "effectiveness":
        options: dict[str, Any] = {}
        if args.detection_hours is not None:
            options["vehicle_hours"] = args.detection_hours
        if args.detection_runs is not None:
            options["vehicles_per_case"] = args.detection_runs
        if args.detection_confidence_k is not None:
            options["confidence_k"] = args.detection_confidence_k
        return "run_effectiveness", options
    return "run", {}


def run(args: argparse.Namespace) -> int:
    names = list(BENCHMARKS) if args.only is None else [n.strip() for n in args.only.split(",") if n.strip()]
    unknown = [n for n in names if n not in BENCHMARKS]
    if unknown:
        print(f"agv-fe: error: unknown benchmark(s) {', '.join(unknown)}; known: {', '.join(BENCHMARKS)}")
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for name in names:
        print(f"benchmark {name} ...", flush=True)
        entry, options = _options(name, args)
        path = getattr(importlib.import_module(BENCHMARKS[name]), entry)(out, **options)
        print(f"  written {path}")
    return 0
