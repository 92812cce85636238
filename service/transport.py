"""Zenoh transport: the only module of the service that imports zenoh.

The service session is a router listening on one explicit endpoint (the
embedded default) or a client of a router. Multicast scouting is off and
only the given endpoint is used. Measurements arrive in bounded
``FifoChannel`` handlers, one per shard bucket, that the ingest loop drains:
no Python code runs in a Zenoh callback, and when the loop falls behind the
channel fills and back-pressure reaches the publishers instead of samples
being dropped.

Ground truth (the ``truth`` key a simulator publishes) is subscribed only
for the vehicles the dashboard follows (:meth:`Transport.follow_truth`),
each into a small ``RingChannel`` that keeps the newest samples, so a slow
dashboard never slows a simulator down. It is shown, never estimated from.
Ownership announcements (bucket leases) of every replica, this one
included, are kept the same way for the dashboard's fleet view
(:meth:`Transport.drain_ownership`).

Congestion control, chosen per stream: alarms ``BLOCK`` at
``INTERACTIVE_HIGH`` priority (they must not be lost); estimates ``DROP`` by
default so that a slow estimate subscriber can never stall ingest (setting
``zenoh.estimate_congestion``).

Security (docs/deployment.md): a session may start from a Zenoh JSON5
configuration file (setting ``zenoh.config_file``) carrying TLS, mutual TLS,
user/password authentication and, on a router, an access-control list.
:func:`session_config` reads it and lays the project's own choices on top:
mode and endpoints come from the settings as without a file (a file that sets
them too must agree, or the session is refused naming both), multicast and
gossip scouting off, the connect timeout and retry apply only where the file
leaves Zenoh's default, and the user and password come from a separate
file (``zenoh.credentials_file``) so that no secret sits in a configuration
file.
"""

from __future__ import annotations

import collections
import contextlib
import json
import time
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import zenoh

from service.protocol import (
    N_BUCKETS,
    all_buckets,
    bucket_selector,
    encode_fleet_estimates,
    fleet_estimates_key,
    fleet_selector,
    ownership_key,
    ownership_selector,
    parse_vehicle_key,
    service_liveliness_key,
    service_liveliness_selector,
    vehicle_key,
)
from service.settings import ZenohSettings

if TYPE_CHECKING:
    from service.protocol import EstimateBatch

#: Ground-truth samples kept per followed vehicle between two drains (newest kept).
TRUTH_RING_CAPACITY = 1024
#: Ownership announcements of the replicas kept between two drains (newest kept): a handful per change.
OWNERSHIP_RING_CAPACITY = 256
#: A new estimate publisher is taken as matched for this long, then its matching status is read once: a
#: client session learns of existing subscribers only after a round trip to its router, and reports "no
#: match" until then; afterwards its matching listener reports every change [s].
MATCH_SETTLE_S = 1.0


class TransportError(Exception):
    """The Zenoh session could not be opened or used; the text names the endpoint."""


@dataclass(frozen=True)
class ConfigValue:
    """A value the project sets in a session's Zenoh configuration.

    path : Zenoh's configuration path, such as 'connect/endpoints'; value : its JSON value; required : True
    when the value is the project's own (mode, endpoints): a configuration file may repeat it but not change
    it. False when it is only a default: a file that sets the path keeps its own value.
    """

    path: str
    value: Any
    required: bool = False


def read_credentials(credentials_file: str | Path) -> tuple[str, str]:
    """(user, password) from a file whose first line is ``USER:PASSWORD`` (a line of a Zenoh router's
    dictionary file); the error never shows the file's content."""
    try:
        lines = Path(credentials_file).read_text().splitlines()
    except OSError as exc:
        raise TransportError(f"zenoh credentials file {credentials_file}: cannot read: {exc.strerror}") from exc
    user, _, password = (lines[0].strip() if lines else "").partition(":")
    if not user or not password:
        raise TransportError(f"zenoh credentials file {credentials_file}: expected one line USER:PASSWORD")
    return user, password


def read_config_file(config_file: str | Path, credentials_file: str | Path | None = None) -> zenoh.Config:
    """A Zenoh configuration from a JSON5 file (Zenoh checks every key name), with the user and password of
    ``transport/auth/usrpwd`` from ``credentials_file`` when given (:func:`read_credentials`)."""
    try:
        config = zenoh.Config.from_file(str(config_file))
    except zenoh.ZError as exc:
        raise TransportError(f"zenoh configuration {config_file}: {_first_line(exc)}") from exc
    if credentials_file is not None:
        user, password = read_credentials(credentials_file)
        config.insert_json5("transport/auth/usrpwd", json.dumps({"user": user, "password": password}))
    return config


def apply_config_values(config: zenoh.Config, values: Sequence[ConfigValue], source: str) -> zenoh.Config:
    """Set each of ``values`` where ``config`` holds Zenoh's default; where it holds something else, keep
    it, unless the value is ``required`` and differs: then raise :class:`TransportError` naming both."""
    default = zenoh.Config()
    for item in values:
        current = json.loads(config.get_json(item.path))
        if current == json.loads(default.get_json(item.path)):
            try:
                config.insert_json5(item.path, json.dumps(item.value))
            except zenoh.ZError as exc:
                raise TransportError(f"invalid zenoh setting {item.path} = {item.value!r}: {_first_line(exc)}") from exc
        elif item.required and current != item.value:
            raise TransportError(
                f"{source} sets {item.path} = {json.dumps(current)}, but the settings say {json.dumps(item.value)}: "
                "set it in one place (mode and endpoints are settings; leave them out of the file)"
            )
    return config


def session_config(
    values: Sequence[ConfigValue], config_file: str | Path | None = None, credentials_file: str | Path | None = None
) -> zenoh.Config:
    """Zenoh's defaults (no file) or ``config_file``, with ``values`` applied (:func:`apply_config_values`)."""
    if config_file is None:
        if credentials_file is not None:
            raise TransportError("zenoh credentials need a configuration file (user/password goes over TLS)")
        config = zenoh.Config()
    else:
        config = read_config_file(config_file, credentials_file)
    return apply_config_values(config, values, f"zenoh configuration {config_file}")


def _first_line(exc: BaseException) -> str:
    text = str(exc)
    return text.split(" at /", 1)[0].splitlines()[0] if text else type(exc).__name__


def zenoh_config(
    mode: str,
    endpoint: str,
    connect_timeout_ms: int = 10_000,
    *,
    config_file: str | Path | None = None,
    credentials_file: str | Path | None = None,
) -> zenoh.Config:
    """A session config on one explicit endpoint: routers listen on it, clients and peers connect to it.

    Without ``config_file`` this is Zenoh's default configuration with only these values set; with one, see
    :func:`session_config`.
    """
    router = mode == "router"
    values = [
        ConfigValue("mode", mode, required=True),
        ConfigValue("listen/endpoints", [endpoint] if router else [], required=True),
        ConfigValue("scouting/multicast/enabled", False),
        ConfigValue("scouting/gossip/enabled", False),
    ]
    if not router:
        values += [
            ConfigValue("connect/endpoints", [endpoint], required=True),
            ConfigValue("connect/timeout_ms", connect_timeout_ms),
        ]
    return session_config(values, config_file, credentials_file)


def open_session(
    mode: str,
    endpoint: str,
    connect_timeout_ms: int = 10_000,
    *,
    config_file: str | Path | None = None,
    credentials_file: str | Path | None = None,
) -> zenoh.Session:
    """Open a session (see :func:`zenoh_config`); raise :class:`TransportError` naming the endpoint."""
    config = zenoh_config(
        mode, endpoint, connect_timeout_ms, config_file=config_file, credentials_file=credentials_file
    )
    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        verb = "listen on" if mode == "router" else "connect to"
        secured = f" with {config_file}" if config_file else ""
        raise TransportError(f"zenoh {mode}: cannot {verb} {endpoint}{secured}: {exc}") from exc


class Transport:
    """The service's Zenoh session: measurement and liveliness subscriptions, estimate and alarm publication."""

    def __init__(self, settings: ZenohSettings, buckets: list[str], replica_id: str, dynamic: bool = False) -> None:
        """``dynamic``: the buckets change while the service runs (bucket leases): one subscription per bucket,
        each declared and undeclared on its own (:meth:`add_buckets`, :meth:`remove_buckets`)."""
        self.settings = settings
        self.prefix = settings.prefix
        self.buckets = list(buckets)
        self.replica_id = replica_id
        self.dynamic = dynamic
        self._session: zenoh.Session | None = None
        # by bucket, or one entry '*' for the whole fleet
        self._meas: dict[str, Any] = {}
        self._alive: dict[str, Any] = {}
        self._ownership_pub: Any = None
        self._ownership_sub: Any = None
        self._token: Any = None
        self._estimate_pubs: dict[str, Any] = {}
        # with vehicle_estimates='subscribed': each estimate publisher's matching listener, the changes they
        # reported (appended from Zenoh's threads), the publishers still settling, and the keys nobody matches
        self._listeners: list[Any] = []
        self._match_events: collections.deque[tuple[str, bool]] = collections.deque()
        self._settling: dict[str, float] = {}
        self._unmatched: set[str] = set()
        self._fleet_pub: Any = None
        self._alarm_pubs: dict[str, Any] = {}
        self._truth: dict[str, Any] = {}
        self._estimate_cc = (
            zenoh.CongestionControl.BLOCK if settings.estimate_congestion == "block" else zenoh.CongestionControl.DROP
        )

    @property
    def session(self) -> zenoh.Session:
        if self._session is None:
            raise TransportError("the transport is not open")
        return self._session

    def selectors(self, kind: str) -> list[str]:
        """Key expressions of this replica's share of the fleet for ``kind`` (one per bucket, or one for all)."""
        return list(self._selectors(kind, self.buckets).values())

    def _selectors(self, kind: str, buckets: list[str]) -> dict[str, str]:
        if not self.dynamic and sorted(buckets) == all_buckets():
            return {"*": fleet_selector(kind, self.prefix)}  # type: ignore[arg-type]
        return {b: bucket_selector(b, kind, self.prefix) for b in buckets}  # type: ignore[arg-type]

    def _subscribe(self, buckets: list[str]) -> None:
        session = self.session
        meas = self._selectors("meas", buckets)
        # a bucket's share of the channel capacity (16 buckets with leases, whatever this replica serves)
        capacity = max(16, self.settings.channel_capacity // (N_BUCKETS if self.dynamic else len(meas)))
        for name, key in meas.items():
            self._meas[name] = session.declare_subscriber(key, zenoh.handlers.FifoChannel(capacity))
        for name, key in self._selectors("alive", buckets).items():
            self._alive[name] = session.liveliness().declare_subscriber(
                key, zenoh.handlers.FifoChannel(4096), history=True
            )

    def add_buckets(self, buckets: list[str]) -> None:
        """Serve ``buckets`` too: their measurements and their vehicles' liveliness (current tokens included)."""
        new = [b for b in buckets if b not in self._meas]
        try:
            self._subscribe(new)
        except zenoh.ZError as exc:
            raise TransportError(f"zenoh: cannot subscribe to buckets {new}: {exc}") from exc
        self.buckets = sorted({*self.buckets, *new})

    def remove_buckets(self, buckets: list[str]) -> None:
        """Stop serving ``buckets``: what their subscriptions still hold is dropped with them."""
        for bucket in buckets:
            for entities in (self._meas, self._alive):
                entity = entities.pop(bucket, None)
                if entity is not None:
                    with contextlib.suppress(zenoh.ZError):
                        entity.undeclare()
        self.buckets = [b for b in self.buckets if b not in buckets]

    def replicas(self, timeout_s: float = 1.0) -> list[str]:
        """The replicas whose liveliness token the Zenoh network holds now (this one included), by name; a replica
        that dies loses its token when its session ends (blocks up to ``timeout_s``: call it off the loop)."""
        names = set()
        for reply in self.session.liveliness().get(service_liveliness_selector(self.prefix), timeout=timeout_s):
            if reply.ok is not None:
                parts = str(reply.ok.key_expr).split("/")
                if len(parts) == 5:
                    names.add(parts[3])
        return sorted(names)

    def publish_ownership(self, payload: bytes) -> None:
        """Announce the buckets this replica gained or gave up (a JSON document, see ownership_key)."""
        if self._ownership_pub is None:
            self._ownership_pub = self.session.declare_publisher(
                ownership_key(self.replica_id, self.prefix),
                congestion_control=zenoh.CongestionControl.BLOCK,
                encoding=zenoh.Encoding.APPLICATION_JSON,
            )
        self._ownership_pub.put(payload)

    def drain_ownership(self) -> list[bytes]:
        """Ownership announcements of every replica (this one's too) received since the last call, oldest first."""
        out: list[bytes] = []
        if self._ownership_sub is not None:
            while (sample := self._ownership_sub.try_recv()) is not None:
                out.append(sample.payload.to_bytes())
        return out

    def open(self) -> None:
        s = self.settings
        self._session = open_session(
            s.mode, s.endpoint, s.connect_timeout_ms, config_file=s.config_file, credentials_file=s.credentials_file
        )
        try:
            session = self._session
            self._subscribe(self.buckets)
            self._token = session.liveliness().declare_token(service_liveliness_key(self.replica_id, self.prefix))
            self._ownership_sub = session.declare_subscriber(
                ownership_selector(self.prefix), zenoh.handlers.RingChannel(OWNERSHIP_RING_CAPACITY)
            )
            self._fleet_pub = session.declare_publisher(
                fleet_estimates_key(self.replica_id, self.prefix),
                congestion_control=self._estimate_cc,
                encoding=zenoh.Encoding.APPLICATION_JSON,
            )
        except zenoh.ZError as exc:
            self.close()
            raise TransportError(f"zenoh: cannot declare the service's subscriptions: {exc}") from exc

    def drain(self, max_samples: int) -> list[tuple[str, bytes]]:
        """Measurements waiting in the channels, (key expression, payload), at most ``max_samples``."""
        out: list[tuple[str, bytes]] = []
        append = out.append
        for sub in self._meas.values():
            try_recv = sub.try_recv
            while len(out) < max_samples:
                sample = try_recv()
                if sample is None:
                    break
                append((str(sample.key_expr), sample.payload.to_bytes()))
        return out

    def drain_liveliness(self) -> list[tuple[str, bool]]:
        """Vehicle liveliness changes since the last call: (vehicle id, alive)."""
        out: list[tuple[str, bool]] = []
        for sub in self._alive.values():
            while (sample := sub.try_recv()) is not None:
                try:
                    vehicle_id, _ = parse_vehicle_key(str(sample.key_expr))
                except ValueError:
                    continue
                out.append((vehicle_id, sample.kind == zenoh.SampleKind.PUT))
        return out

    def follow_truth(self, vehicle_ids: Collection[str]) -> None:
        """Subscribe to the ground truth of exactly ``vehicle_ids`` (for the dashboard only)."""
        wanted = set(vehicle_ids)
        for vehicle_id in [v for v in self._truth if v not in wanted]:
            with contextlib.suppress(zenoh.ZError):
                self._truth.pop(vehicle_id).undeclare()
        for vehicle_id in sorted(wanted - self._truth.keys()):
            self._truth[vehicle_id] = self.session.declare_subscriber(
                vehicle_key(vehicle_id, "truth", self.prefix), zenoh.handlers.RingChannel(TRUTH_RING_CAPACITY)
            )

    def drain_truth(self) -> list[tuple[str, bytes]]:
        """Ground-truth payloads received since the last call: (vehicle id, payload)."""
        out: list[tuple[str, bytes]] = []
        for vehicle_id, sub in self._truth.items():
            while (sample := sub.try_recv()) is not None:
                out.append((vehicle_id, sample.payload.to_bytes()))
        return out

    def publish_estimates(self, batches: Sequence[EstimateBatch]) -> tuple[int, int]:
        """Publish a tick's estimates; returns (per-vehicle messages, estimates in the fleet message).

        Each vehicle's estimate goes to its own key; with ``zenoh.vehicle_estimates='subscribed'``, not when
        no subscriber matched that key at the last :meth:`refresh_matching` (then its document is not even
        made). The whole tick goes as one :class:`~service.protocol.FleetEstimates` message when a
        subscriber matches the replica's fleet key.
        """
        pubs, unmatched = self._estimate_pubs, self._unmatched
        sent = 0
        for batch in batches:
            ids = batch.vehicle_ids
            if unmatched:  # only with vehicle_estimates='subscribed'
                rows = [j for j, vehicle_id in enumerate(ids) if vehicle_id not in unmatched]
                ids = [ids[j] for j in rows]
                documents = batch.documents(rows)
            else:
                documents = batch.documents()
            for vehicle_id, document in zip(ids, documents, strict=True):
                pub = pubs.get(vehicle_id)
                if pub is None:
                    pub = pubs[vehicle_id] = self._declare_estimate_publisher(vehicle_id)
                pub.put(document)
            sent += len(documents)
        in_fleet = 0
        if self._fleet_pub is not None and batches and self._fleet_pub.matching_status.matching:
            self._fleet_pub.put(encode_fleet_estimates(self.replica_id, batches))
            in_fleet = sum(len(b) for b in batches)
        return sent, in_fleet

    def _declare_estimate_publisher(self, vehicle_id: str) -> Any:
        pub = self.session.declare_publisher(
            vehicle_key(vehicle_id, "estimate", self.prefix),
            congestion_control=self._estimate_cc,
            encoding=zenoh.Encoding.APPLICATION_JSON,
        )
        if self.settings.vehicle_estimates == "subscribed":
            events = self._match_events  # a deque: appending from Zenoh's threads is safe
            # indirect=False: the append runs on Zenoh's own thread. The default runs every callback handler on a
            # Python thread of its own: one thread per vehicle (1,014 threads at 1,000 vehicles, soak benchmark)
            callback: zenoh.handlers.Callback[Any] = zenoh.handlers.Callback(
                lambda status: events.append((vehicle_id, status.matching)), indirect=False
            )
            self._listeners.append(pub.declare_matching_listener(callback))
            self._settling.pop(vehicle_id, None)  # keep the dict in declaration order
            self._settling[vehicle_id] = time.monotonic()
        return pub

    def refresh_matching(self, now: float | None = None) -> int:
        """Bring the set of vehicle estimate keys nobody subscribes to up to date; return its size.

        Each estimate publisher's matching listener reports every change, applied here in the order it came;
        a publisher whose first MATCH_SETTLE_S have passed has its status read once, since a listener
        reports changes only. The ingest loop calls this before every publication, so a new subscriber gets
        a vehicle's estimates from the next tick on; with nothing queued and nothing settling it costs two
        truth tests. Nothing is skipped when the setting ``zenoh.vehicle_estimates`` is 'always'."""
        events, unmatched, settling = self._match_events, self._unmatched, self._settling
        while events:
            vehicle_id, matched = events.popleft()
            if vehicle_id in settling:
                continue  # taken as matched until its status is read below
            if matched:
                unmatched.discard(vehicle_id)
            else:
                unmatched.add(vehicle_id)
        if not settling:
            return len(unmatched)
        now = time.monotonic() if now is None else now
        while settling:  # in the order the publishers were declared, so the oldest comes first
            vehicle_id, declared = next(iter(settling.items()))
            if now - declared < MATCH_SETTLE_S:
                break
            del settling[vehicle_id]
            try:
                matched = self._estimate_pubs[vehicle_id].matching_status.matching
            except zenoh.ZError:
                matched = True  # unknown: keep publishing
            if matched:
                unmatched.discard(vehicle_id)
            else:
                unmatched.add(vehicle_id)
        return len(unmatched)

    def router_connected(self) -> bool:
        """Whether the session is connected to a router now (a client's link; a router counts itself)."""
        if self.settings.mode == "router":
            return self._session is not None
        try:
            return any(True for _ in self.session.info.routers_zid())
        except zenoh.ZError:
            return False

    def publish_alarm(self, vehicle_id: str, payload: bytes) -> None:
        pub = self._alarm_pubs.get(vehicle_id)
        if pub is None:
            pub = self._alarm_pubs[vehicle_id] = self.session.declare_publisher(
                vehicle_key(vehicle_id, "alarm", self.prefix),
                congestion_control=zenoh.CongestionControl.BLOCK,
                priority=zenoh.Priority.INTERACTIVE_HIGH,
                encoding=zenoh.Encoding.APPLICATION_JSON,
            )
        pub.put(payload)

    def close(self) -> None:
        """Undeclare everything and close the session (an unclosed session can hang the process at exit)."""
        entities = [*self._meas.values(), *self._alive.values(), *self._truth.values()]
        fleet = [p for p in (self._fleet_pub, self._ownership_pub, self._ownership_sub) if p is not None]
        for entity in [*entities, *fleet, *self._listeners, *self._estimate_pubs.values(), *self._alarm_pubs.values()]:
            with contextlib.suppress(zenoh.ZError):
                entity.undeclare()
        if self._token is not None:
            with contextlib.suppress(zenoh.ZError):
                self._token.undeclare()
        self._meas, self._alive, self._token, self._ownership_pub, self._ownership_sub = {}, {}, None, None, None
        self._estimate_pubs, self._alarm_pubs, self._truth = {}, {}, {}
        self._listeners, self._settling, self._unmatched, self._fleet_pub = [], {}, set(), None
        self._match_events.clear()
        if self._session is not None:
            self._session.close()  # type: ignore[no-untyped-call]
            self._session = None
