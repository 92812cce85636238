"""`agv-fe zenoh-acl`: the secure Zenoh router's configuration (TLS, user/password, ACL) for a vehicle list."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from agv_fe.common import CommandError, fail

#: The first lines of a generated file.
HEADER = (
    "The secure Zenoh router (docker-compose.secure.yml, docs/deployment.md). GENERATED: do not edit; run",
    "  agv-fe zenoh-acl --vehicles {vehicles} --output {output}",
    "(make zenoh-acl) after changing the vehicle list. TLS only, mutual TLS, user/password from users.txt,",
    "access control: each vehicle puts only its own measurements and liveliness token and receives only its own",
    "estimates and alarms; only agv-service puts estimates, alarms and the fleet stream; agv-dashboard reads.",
)


def register(sub: Any) -> None:
    parser = sub.add_parser(
        "zenoh-acl",
        help="write the secure Zenoh router config (TLS, user/password, per-vehicle ACL) for a vehicle list",
        description="Write the Zenoh router configuration of the secure deployment: a TLS listener with mutual "
        "TLS, user/password authentication and an access-control list in which each vehicle may put only its "
        "own measurements and declare only its own liveliness token, and only the service may put estimates "
        "and alarms. Zenoh's rules name key expressions, not 'the caller's own key', so each vehicle gets "
        "rules of its own: regenerate after adding a vehicle. Certificates: make certs.",
    )
    parser.add_argument(
        "--vehicles",
        required=True,
        metavar="FILE",
        help="one vehicle id per line, optionally followed by the identity (certificate common name and user) "
        "that publishes for it, default the id itself; '#' comments",
    )
    parser.add_argument("--output", metavar="FILE.json5", help="where to write (default: standard output)")
    parser.add_argument("--prefix", default="agv", help="key-expression prefix of the protocol (default agv)")
    parser.add_argument("--listen", default="tls/0.0.0.0:7447", metavar="tls/HOST:PORT", help="the router's endpoint")
    parser.add_argument(
        "--certs-dir",
        default="/etc/zenoh/certs",
        metavar="DIR",
        help="where the router finds ca.pem, router.pem, router.key and users.txt (default /etc/zenoh/certs, "
        "the compose mount)",
    )
    parser.add_argument(
        "--identify-by",
        choices=("both", "cert", "user"),
        default="both",
        help="an identity is its certificate's common name and its user name on the same session (both, "
        "default), or only one of them",
    )
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from service.zenoh_acl import AclError, read_vehicle_list, render_json5, router_config

    try:
        if not args.listen.startswith("tls/"):
            raise CommandError(f"--listen: expected a tls/HOST:PORT endpoint, got {args.listen!r}")
        try:
            text = Path(args.vehicles).read_text()
        except OSError as exc:
            raise CommandError(f"{args.vehicles}: cannot read: {exc.strerror}") from exc
        try:
            grants = read_vehicle_list(text, args.vehicles)
        except AclError as exc:
            raise CommandError(str(exc)) from exc
        config = router_config(
            grants, prefix=args.prefix, listen=args.listen, certs_dir=args.certs_dir, identify_by=args.identify_by
        )
        header = [line.format(vehicles=args.vehicles, output=args.output or "FILE") for line in HEADER]
        rendered = render_json5(config, header)
        if args.output:
            Path(args.output).write_text(rendered)
            identities = len(config["access_control"]["policies"]) - 2
            print(f"{args.output}: {len(grants)} vehicles, {identities} vehicle identities", file=sys.stderr)
        else:
            sys.stdout.write(rendered)
    except CommandError as exc:
        return fail(exc)
    return 0
