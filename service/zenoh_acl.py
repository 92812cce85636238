"""The secure Zenoh router's configuration: TLS, user/password and an access-control list for the protocol.

Zenoh's access control (the router's ``access_control`` section) allows a *subject* (a certificate common
name, a user name) to send or receive a *message* (put, declare_subscriber, liveliness_token...) on the key
expressions a *rule* names. A rule cannot say "the connecting vehicle's own key", so every vehicle gets rules
of its own, naming its keys exactly (bucket included), bound to the identity that publishes for it:

* a vehicle may put its measurements and its payload reports and declare its liveliness token, nothing else;
  it may declare subscribers on the fleet's estimate and alarm keys (the edge client does), but the router
  forwards it only its own estimates and alarms;
* the service (identity :data:`SERVICE_IDENTITY`, every replica) may subscribe to every measurement, payload
  report, truth stream and liveliness token, to the replicas' ownership announcements and to the fleet stream (its own
  processes read it, service/fleet_child.py), and is the only one that may put
  estimates, alarms, the fleet stream and ownership announcements;
* a monitor (identity :data:`MONITOR_IDENTITY`: the terminal dashboard) may read estimates, alarms, the fleet
  stream, ownership announcements and liveliness, and publish nothing;
* everything else is denied (``default_permission: deny``), and a client whose certificate or password the
  router does not accept never gets a session.

A vehicle list file has one vehicle id per line, optionally followed by the identity that publishes for it
(default: the vehicle id itself); a simulator or a gateway that publishes for several vehicles is one
identity named on each of their lines. ``#`` starts a comment. ``agv-fe zenoh-acl`` writes the router's
configuration from such a file (docs/deployment.md).

Nothing here imports zenoh: this builds plain data, which Zenoh checks when a router opens with it.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

from agv_protocol.wire import (
    BINARY_ESTIMATE_KIND,
    ProtocolError,
    check_vehicle_id,
    fleet_estimates_selector,
    fleet_selector,
    ownership_selector,
    service_liveliness_selector,
    vehicle_key,
)

#: The certificate common name and user name of the service (all replicas).
SERVICE_IDENTITY = "agv-service"
#: The certificate common name and user name of read-only consumers (the terminal dashboard).
MONITOR_IDENTITY = "agv-dashboard"
#: How the router recognises an identity: certificate common name (mutual TLS), user name (user/password),
#: or both at once on the same session.
IdentifyBy = Literal["cert", "user", "both"]


class AclError(ValueError):
    """A vehicle list that cannot be turned into an access-control list; the text names the line."""


@dataclass(frozen=True)
class VehicleGrant:
    """``identity`` (a certificate common name and user name) may publish as vehicle ``vehicle_id``."""

    vehicle_id: str
    identity: str


def read_vehicle_list(text: str, source: str = "vehicle list") -> list[VehicleGrant]:
    """Parse a vehicle list (module docstring); raise :class:`AclError` naming the line."""
    grants: list[VehicleGrant] = []
    seen: dict[str, int] = {}
    for number, raw in enumerate(text.splitlines(), start=1):
        fields = raw.split("#", 1)[0].split()
        if not fields:
            continue
        if len(fields) > 2:
            raise AclError(f"{source}, line {number}: expected VEHICLE_ID [IDENTITY], got {raw.strip()!r}")
        vehicle_id, identity = fields[0], fields[-1]
        try:
            check_vehicle_id(vehicle_id)
            check_vehicle_id(identity)
        except ProtocolError as exc:
            raise AclError(f"{source}, line {number}: {exc}") from exc
        if identity in (SERVICE_IDENTITY, MONITOR_IDENTITY):
            raise AclError(f"{source}, line {number}: {identity!r} is reserved for the service and the dashboard")
        if vehicle_id in seen:
            raise AclError(f"{source}, line {number}: vehicle {vehicle_id!r} already listed on line {seen[vehicle_id]}")
        seen[vehicle_id] = number
        grants.append(VehicleGrant(vehicle_id, identity))
    if not grants:
        raise AclError(f"{source}: no vehicle listed")
    return grants


def _rule(rule_id: str, messages: Sequence[str], flow: str, key_exprs: Iterable[str]) -> dict[str, Any]:
    return {
        "id": rule_id,
        "messages": list(messages),
        "flows": [flow],
        "permission": "allow",
        "key_exprs": list(key_exprs),
    }


def _subject(identity: str, identify_by: IdentifyBy) -> dict[str, Any]:
    subject: dict[str, Any] = {"id": identity}
    if identify_by in ("cert", "both"):
        subject["cert_common_names"] = [identity]
    if identify_by in ("user", "both"):
        subject["usernames"] = [identity]
    return subject


def access_control(
    grants: Sequence[VehicleGrant], prefix: str = "agv", identify_by: IdentifyBy = "both"
) -> dict[str, Any]:
    """The router's ``access_control`` section for ``grants``: deny by default, allow what the protocol needs."""
    measurements, truth, alive, payloads = (
        fleet_selector("meas", prefix),
        fleet_selector("truth", prefix),
        fleet_selector("alive", prefix),
        fleet_selector("payload", prefix),
    )
    estimates, alarms = fleet_selector("estimate", prefix), fleet_selector("alarm", prefix)
    binary_estimates = fleet_selector(BINARY_ESTIMATE_KIND, prefix)  # the same estimates in the binary encoding
    fleet_stream = fleet_estimates_selector(prefix)
    ownership = ownership_selector(prefix)  # replicas announce the buckets they take and give up (bucket leases)
    rules = [
        # the service: reads measurements, truth and liveliness; the only publisher of answers; its own processes
        # (the vehicle-estimate and history processes, service/fleet_child.py) read its fleet stream
        _rule(
            "service-subscribe",
            ["declare_subscriber"],
            "ingress",
            [measurements, payloads, truth, ownership, fleet_stream],
        ),
        _rule("service-receive", ["put"], "egress", [measurements, payloads, truth, ownership, fleet_stream]),
        _rule("service-follow-liveliness", ["declare_liveliness_subscriber", "liveliness_query"], "ingress", [alive]),
        _rule("service-receive-liveliness", ["liveliness_token"], "egress", [alive]),
        _rule("service-publish", ["put"], "ingress", [estimates, binary_estimates, alarms, fleet_stream, ownership]),
        _rule("service-liveliness", ["liveliness_token"], "ingress", [service_liveliness_selector(prefix)]),
        # its estimate publishers' matching listeners learn of the subscribers
        _rule(
            "service-see-subscribers",
            ["declare_subscriber"],
            "egress",
            [estimates, binary_estimates, alarms, fleet_stream, ownership],
        ),
        # a monitor: reads answers, ownership changes and liveliness, publishes nothing
        _rule(
            "monitor-subscribe",
            ["declare_subscriber"],
            "ingress",
            [estimates, binary_estimates, alarms, fleet_stream, ownership],
        ),
        _rule("monitor-receive", ["put"], "egress", [estimates, binary_estimates, alarms, fleet_stream, ownership]),
        _rule("monitor-follow-liveliness", ["declare_liveliness_subscriber", "liveliness_query"], "ingress", [alive]),
        _rule("monitor-receive-liveliness", ["liveliness_token"], "egress", [alive]),
        # every vehicle: may declare subscribers on the fleet's answers (delivery is per vehicle, below), and
        # learns of the service's measurement and payload subscribers (a client only sends what some subscriber
        # wants)
        _rule("vehicle-subscribe", ["declare_subscriber"], "ingress", [estimates, binary_estimates, alarms]),
        _rule("vehicle-see-subscribers", ["declare_subscriber"], "egress", [measurements, payloads]),
    ]
    own_rules, vehicle_rules = _vehicle_rules(grants, prefix)
    rules += own_rules
    identities = [SERVICE_IDENTITY, MONITOR_IDENTITY, *vehicle_rules]
    policies = [
        {
            "id": SERVICE_IDENTITY,
            "rules": [r["id"] for r in rules if r["id"].startswith("service-")],
            "subjects": [SERVICE_IDENTITY],
        },
        {
            "id": MONITOR_IDENTITY,
            "rules": [r["id"] for r in rules if r["id"].startswith("monitor-")],
            "subjects": [MONITOR_IDENTITY],
        },
    ]
    policies += [
        {"id": identity, "rules": ["vehicle-subscribe", "vehicle-see-subscribers", *own], "subjects": [identity]}
        for identity, own in vehicle_rules.items()
    ]
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": [_subject(identity, identify_by) for identity in identities],
        "policies": policies,
    }


def _vehicle_rules(grants: Sequence[VehicleGrant], prefix: str) -> tuple[list[dict[str, Any]], dict[str, list[str]]]:
    """Each vehicle's own rules (it puts its measurements, payload reports and liveliness token, and receives its
    own answers), in
    the order of ``grants``, and the ids of those rules by identity."""
    rules: list[dict[str, Any]] = []
    by_identity: dict[str, list[str]] = {}
    for grant in grants:
        vid = grant.vehicle_id
        rules += [
            _rule(
                f"{vid}/meas",
                ["put"],
                "ingress",
                [vehicle_key(vid, "meas", prefix), vehicle_key(vid, "payload", prefix)],
            ),
            _rule(f"{vid}/alive", ["liveliness_token"], "ingress", [vehicle_key(vid, "alive", prefix)]),
            _rule(
                f"{vid}/answers",
                ["put"],
                "egress",
                [
                    vehicle_key(vid, "estimate", prefix),
                    vehicle_key(vid, BINARY_ESTIMATE_KIND, prefix),
                    vehicle_key(vid, "alarm", prefix),
                ],
            ),
        ]
        by_identity.setdefault(grant.identity, []).extend([f"{vid}/meas", f"{vid}/alive", f"{vid}/answers"])
    return rules, by_identity


def router_config(
    grants: Sequence[VehicleGrant],
    *,
    prefix: str = "agv",
    listen: str = "tls/0.0.0.0:7447",
    certs_dir: str = "/etc/zenoh/certs",
    identify_by: IdentifyBy = "both",
) -> dict[str, Any]:
    """The whole router configuration: ``listen`` over TLS only, mutual TLS with the CA in ``certs_dir``,
    user/password against ``certs_dir``/users.txt (unless identities are certificates only), the ACL."""
    tls = {
        "root_ca_certificate": f"{certs_dir}/ca.pem",
        "listen_certificate": f"{certs_dir}/router.pem",
        "listen_private_key": f"{certs_dir}/router.key",
        "enable_mtls": identify_by != "user",
        "close_link_on_expiration": identify_by != "user",
    }
    transport: dict[str, Any] = {"link": {"protocols": ["tls"], "tls": tls}}
    if identify_by != "cert":
        transport["auth"] = {"usrpwd": {"dictionary_file": f"{certs_dir}/users.txt"}}
    return {
        "mode": "router",
        "listen": {"endpoints": [listen]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": transport,
        "access_control": access_control(grants, prefix, identify_by),
    }


def render_json5(config: dict[str, Any], header: Sequence[str], width: int = 116) -> str:
    """``config`` as JSON (valid JSON5) under ``//`` comment lines: a value that fits in ``width`` columns on
    its line is written on one line (a rule, a subject), larger ones one member per line."""
    comments = "".join(f"// {line}".rstrip() + "\n" for line in header)
    return f"{comments}{_compact(config, 0, width)}\n"


def _compact(value: Any, indent: int, width: int, used: int = 0) -> str:
    """``value`` as JSON starting ``used`` columns into a line indented by ``indent``."""
    flat = json.dumps(value, separators=(", ", ": "))
    if indent + used + len(flat) < width or not isinstance(value, dict | list) or not value:
        return flat
    inner = " " * (indent + 2)
    if isinstance(value, dict):
        items = [
            f"{inner}{json.dumps(k)}: {_compact(v, indent + 2, width, len(json.dumps(k)) + 2)}"
            for k, v in value.items()
        ]
        return "{\n" + ",\n".join(items) + "\n" + " " * indent + "}"
    if not any(isinstance(v, dict | list) for v in value):
        # scalars: as many on a line as fit
        lines, line = [], ""
        for text in (json.dumps(v) for v in value):
            if line and len(inner) + len(line) + len(text) + 2 > width:
                lines.append(line)
                line = ""
            line = f"{line} {text}," if line else f"{text},"
        lines.append(line.rstrip(","))
        return "[\n" + "\n".join(inner + x for x in lines) + "\n" + " " * indent + "]"
    items = [inner + _compact(v, indent + 2, width) for v in value]
    return "[\n" + ",\n".join(items) + "\n" + " " * indent + "]"
