"""The benchmarks' Zenoh link over TLS, as the secure deployment runs it (docs/deployment.md), on loopback.

The service is the router, as in every service benchmark, but listens on ``tls/127.0.0.1:PORT`` only, with the
router certificate `make certs` issues (deploy/zenoh/make-certs.sh, into a temporary directory), mutual TLS,
user/password against the router's dictionary and the access-control list that ``agv-fe zenoh-acl`` would
generate for the bench fleet (service/zenoh_acl.py): one simulator identity, :data:`FLEET_IDENTITY`, listed for
every vehicle (three rules each, 4,513 rules for 1,500 vehicles), as the compose fleet's ``agv-fleet-sim`` is. The
load generator connects as that identity, the receiver as the read-only monitor ``agv-dashboard``; both use the
committed client configuration (deploy/zenoh/secure/client.json5) with its certificate paths pointed at their
directories.
"""

from __future__ import annotations

import subprocess
from dataclasses import dataclass
from pathlib import Path

from agv_fe.benchmarks.harness import free_port
from agv_fe.benchmarks.service_load import SecureClients, vehicle_ids
from agv_protocol.zenoh_session import TransportError
from service.transport import open_session
from service.zenoh_acl import MONITOR_IDENTITY, VehicleGrant, render_json5, router_config

ROOT = Path(__file__).resolve().parents[2]
MAKE_CERTS = ROOT / "deploy" / "zenoh" / "make-certs.sh"
CLIENT_CONFIG = ROOT / "deploy" / "zenoh" / "secure" / "client.json5"
#: Where the committed client configuration expects an identity's certificates (the docker compose mount).
MOUNT = "/etc/zenoh/certs"
#: The identity that publishes for every vehicle of the bench fleet.
FLEET_IDENTITY = "bench-fleet-sim"
#: How long a plain-TCP probe of a TLS endpoint keeps trying before it counts as refused [ms].
PROBE_TIMEOUT_MS = 1500


def issue_certificates(out: Path) -> Path:
    """The CA, the router's certificate and dictionary, and the certificates and credentials of the service, the
    monitor and :data:`FLEET_IDENTITY`, issued into ``out`` by make-certs.sh (openssl); ``out``."""
    done = subprocess.run(
        [str(MAKE_CERTS), str(out), FLEET_IDENTITY], capture_output=True, text=True, timeout=120, check=False
    )
    if done.returncode != 0:
        raise RuntimeError(f"{MAKE_CERTS} failed ({done.returncode}): {done.stdout}{done.stderr}")
    return out


@dataclass(frozen=True)
class SecureLink:
    """A service's TLS endpoint: the settings that make ``agv-fe serve`` the TLS router there (``env``), the
    clients' files, and the number of rules of the router's access-control list (0: the ACL is off)."""

    endpoint: str
    env: dict[str, str]
    clients: SecureClients
    acl_rules: int


def secure_link(certs: Path, workdir: Path, vehicles: int, acl: bool = True) -> SecureLink:
    """A TLS endpoint on a free loopback port for a service holding ``vehicles`` bench vehicles: the router's
    configuration written to ``workdir`` (with the ACL of those vehicles unless ``acl`` is False) and the two
    clients' configurations beside it. ``certs``: a directory of :func:`issue_certificates`."""
    endpoint = f"tls/127.0.0.1:{free_port()}"  # the router's certificate names 127.0.0.1
    grants = [VehicleGrant(vehicle_id, FLEET_IDENTITY) for vehicle_id in vehicle_ids(vehicles)]
    config = router_config(grants, listen=endpoint, certs_dir=str(certs / "router"))
    if not acl:
        del config["access_control"]
    router = workdir / "router.json5"
    router.write_text(render_json5(config, [f"the service-load benchmark's TLS router, {vehicles} vehicles"]))
    clients = SecureClients(
        generator=_client_files(certs, FLEET_IDENTITY, workdir),
        receiver=_client_files(certs, MONITOR_IDENTITY, workdir),
    )
    env = {"AGV_FE_ZENOH__ENDPOINT": endpoint, "AGV_FE_ZENOH__CONFIG_FILE": str(router)}
    return SecureLink(endpoint, env, clients, len(config["access_control"]["rules"]) if acl else 0)


def _client_files(certs: Path, identity: str, workdir: Path) -> tuple[Path, Path]:
    """(client configuration, credentials) of ``identity``: client.json5 pointed at its certificate directory."""
    config = workdir / f"{identity}.json5"
    config.write_text(CLIENT_CONFIG.read_text().replace(MOUNT, str(certs / identity)))
    return config, certs / identity / "credentials"


def plain_tcp_refused(endpoint: str) -> bool:
    """Whether a plain-TCP client (no TLS, no certificate, no password) gets no session at ``endpoint``'s host and
    port: True for a TLS-only listener."""
    tcp = "tcp/" + endpoint.split("/", 1)[1]
    try:
        session = open_session("client", tcp, PROBE_TIMEOUT_MS)
    except TransportError:
        return True
    session.close()  # type: ignore[no-untyped-call]
    return False
