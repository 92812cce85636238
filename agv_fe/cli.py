"""`agv-fe`: the product's command line."""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

#: Subcommand name -> module with ``register(subparsers)``. Order is the help order.
COMMANDS = {
    "synth": "agv_fe.commands.synth",
    "simulate": "agv_fe.commands.simulate",
    "replay": "agv_fe.commands.replay",
    "calibrate": "agv_fe.commands.calibrate",
    "can2csv": "agv_fe.commands.can2csv",
    "compare": "agv_fe.commands.compare",
    "serve": "agv_fe.commands.serve",
    "fleet": "agv_fe.commands.fleet",
    "dashboard": "agv_fe.commands.dashboard",
    "publish-csv": "agv_fe.commands.publish_csv",
    "ros2-bridge": "agv_fe.commands.ros2_bridge",
    "can-bridge": "agv_fe.commands.can_bridge",
    "zenoh-acl": "agv_fe.commands.zenoh_acl",
    "demo": "agv_fe.commands.demo",
    "bench": "agv_fe.commands.bench",
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="agv-fe",
        description="Certified actuator fault estimation for autonomous ground vehicles.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {package_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in COMMANDS.values():
        importlib.import_module(module).register(sub)
    return parser


def package_version() -> str:
    """The installed distribution's version (pyproject.toml), or 'unknown' when run from a bare source tree."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("agv-fault-estimator")
    except PackageNotFoundError:
        return "unknown"


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.handler(args))
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
