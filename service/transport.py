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
:func:`agv_protocol.zenoh_session.session_config` reads it and lays the
project's own choices on top: mode and endpoints come from the settings as
without a file (a file that sets them too must agree, or the session is
refused naming both), multicast and gossip scouting off, the connect timeout
and retry apply only where the file leaves Zenoh's default, and the user and
password come from a separate file (``zenoh.credentials_file``) so that no
secret sits in a configuration file.
"""

from __future__ import annotations

import collections
import contextlib
import json
import logging
import os
import secrets
import threading
import time
from collections.abc import Callable, Collection, Iterable, MutableMapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, TypedDict, TypeVar

import numpy as np
import zenoh

from agv_protocol.wire import (
    BINARY_ESTIMATE_KIND,
    N_BUCKETS,
    Kind,
    all_buckets,
    bucket_selector,
    encode_binary_estimates,
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
from agv_protocol.zenoh_session import ConfigValue, TransportError, session_config
from service.metrics import END_TO_END_BUCKETS_S, Histogram
from service.settings import ZenohSettings

if TYPE_CHECKING:
    from typing_extensions import Unpack

    from agv_protocol.wire import EstimateBatch

#: Ground-truth samples kept per followed vehicle between two drains (newest kept).
TRUTH_RING_CAPACITY = 1024
#: Payload reports kept per bucket between two housekeeping passes (a vehicle reports when its load changes).
PAYLOAD_CAPACITY = 1024
#: Ownership announcements of the replicas kept between two drains (newest kept): a handful per change.
OWNERSHIP_RING_CAPACITY = 256
#: A new estimate publisher is taken as matched for this long, then its matching status is read once: a
#: client session learns of existing subscribers only after a round trip to its router, and reports "no
#: match" until then; afterwards its matching listener reports every change [s].
MATCH_SETTLE_S = 1.0
#: How far the publisher thread may fall behind the ingest loop [s]: a tick's per-vehicle estimates still queued
#: this long after the tick are dropped (counted), so the ingest loop never waits for a vehicle's subscriber. A
#: burst of new vehicles (two publishers and listeners each, declared by the thread) takes a good part of a
#: second at 1,000 vehicles; a queue bounded by a count of 1 ms ticks dropped estimates there.
VEHICLE_QUEUE_MAX_AGE_S = 2.0
#: How often the publisher thread looks at the subscribers that came or went while no estimate is due [s].
VEHICLE_IDLE_REFRESH_S = 0.5

log = logging.getLogger(__name__)


#: A Zenoh session, for the modules that hold one without importing Zenoh (the layering test keeps it here).
Session = zenoh.Session


class SessionFiles(TypedDict, total=False):
    """What a session takes beside its mode and endpoint (:func:`zenoh_config`, :func:`open_session`)."""

    config_file: str | Path | None
    credentials_file: str | Path | None
    child_dir: Path | None


def zenoh_config(
    mode: str, endpoint: str, connect_timeout_ms: int = 10_000, **files: Unpack[SessionFiles]
) -> zenoh.Config:
    """A session config on one explicit endpoint: routers listen on it, clients and peers connect to it.

    Without ``config_file`` this is Zenoh's default configuration with only these values set; with one, see
    :func:`session_config`. ``child_dir`` (a router only): also listen on a Unix socket there for the service's
    own child processes (:func:`child_endpoint`), which the router's user dictionary and access-control list, if
    it has them, let in.
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
    config = session_config(values, files.get("config_file"), files.get("credentials_file"))
    child_dir = files.get("child_dir")
    if router and child_dir is not None:
        _let_children_in(config, child_dir)
    return config


#: The environment variable Zenoh reads its runtimes' threads from, once, when the process first needs them.
ZENOH_RUNTIME_VAR = "ZENOH_RUNTIME"


def runtime_threads_value(threads: int) -> str:
    """The ZENOH_RUNTIME value that runs Zenoh's receiving (rx), sending (tx) and accepting (acc) work on the
    ``threads`` worker threads of its application runtime (Zenoh's ``handover``), instead of runtimes of their
    own: fewer threads to wake per sample on a small machine."""
    return f"(app: (worker_threads: {threads}), rx: (handover: app), tx: (handover: app), acc: (handover: app))"


def apply_runtime_threads(threads: int, environ: MutableMapping[str, str] = os.environ) -> str | None:
    """Set ZENOH_RUNTIME for ``threads`` (setting ``zenoh.runtime_threads``; 0: Zenoh's own threads) unless the
    operator set it: call it before the process opens its first Zenoh session. Returns the value in effect (None:
    Zenoh's defaults)."""
    if ZENOH_RUNTIME_VAR in environ:
        return environ[ZENOH_RUNTIME_VAR]
    if threads == 0:
        return None
    environ[ZENOH_RUNTIME_VAR] = runtime_threads_value(threads)
    return environ[ZENOH_RUNTIME_VAR]


def child_endpoint(child_dir: Path) -> str:
    """The endpoint of the Unix socket on which an embedded router takes the service's own child processes (the
    vehicle-estimate and history processes, service/fleet_child.py), in ``child_dir``, a directory only the
    service's user can enter: the children connect as clients without TLS, whatever TLS the router's
    configuration file sets for the network."""
    return f"unixsock-stream/{child_dir / 'zenoh.sock'}"


def child_files(child_dir: Path) -> tuple[Path, Path | None]:
    """The children's configuration file in ``child_dir`` (their link: the Unix socket only), and their user and
    password file if the router asks for one (:func:`zenoh_config` writes both)."""
    credentials = child_dir / "credentials"
    return child_dir / "client.json5", credentials if credentials.exists() else None


#: The user name, access-control subject, rule and policy id of the service's children on their Unix socket.
CHILDREN_ID = "agv-fe-children"
_CHILD_MESSAGES = ["put", "delete", "declare_subscriber", "liveliness_token", "declare_liveliness_subscriber"]


def _let_children_in(config: zenoh.Config, child_dir: Path) -> None:
    """Listen on the children's socket too (:func:`child_endpoint`), with its link protocol where the file allows
    only some (the secure router's: TLS); where the router asks a user and password (a dictionary file), give the
    children a fresh one of their own in ``child_dir``; where access control is on (``default_permission:
    deny``, service/zenoh_acl.py), allow what arrives on a Unix-socket link (only the service's children can reach
    its socket) everything on every key: the children subscribe to the fleet stream and put the vehicles'
    estimates."""
    listen = json.loads(config.get_json("listen/endpoints"))
    config.insert_json5("listen/endpoints", json.dumps([*listen, child_endpoint(child_dir)]))
    _write_private(child_dir / "client.json5", json.dumps({"transport": {"link": {"protocols": ["unixsock-stream"]}}}))
    protocols = json.loads(config.get_json("transport/link/protocols"))
    if protocols is not None and "unixsock-stream" not in protocols:
        config.insert_json5("transport/link/protocols", json.dumps([*protocols, "unixsock-stream"]))
    dictionary = json.loads(config.get_json("transport/auth/usrpwd")).get("dictionary_file")
    if dictionary:
        line = f"{CHILDREN_ID}:{secrets.token_urlsafe(24)}\n"
        try:
            users = Path(dictionary).read_text()
        except OSError as exc:
            raise TransportError(f"zenoh user dictionary {dictionary}: cannot read: {exc.strerror}") from exc
        _write_private(child_dir / "users.txt", users.rstrip("\n") + "\n" + line)
        _write_private(child_dir / "credentials", line)
        config.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(child_dir / "users.txt")))
    acl = json.loads(config.get_json("access_control"))
    if acl.get("enabled"):
        rule = {"id": CHILDREN_ID, "messages": _CHILD_MESSAGES, "flows": ["ingress", "egress"], "permission": "allow",
                "key_exprs": ["**"]}  # fmt: skip
        subject = {"id": CHILDREN_ID, "link_protocols": ["unixsock-stream"]}
        policy = {"id": CHILDREN_ID, "rules": [CHILDREN_ID], "subjects": [CHILDREN_ID]}
        for key, item in (("rules", rule), ("subjects", subject), ("policies", policy)):
            config.insert_json5(f"access_control/{key}", json.dumps([*(acl.get(key) or []), item]))


def _write_private(path: Path, text: str) -> None:
    """``text`` into a new file only its owner can read."""
    with os.fdopen(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600), "w") as f:
        f.write(text)


def estimate_congestion(name: str) -> Any:
    """Zenoh's congestion control of the setting ``zenoh.estimate_congestion`` ('block' or 'drop')."""
    return zenoh.CongestionControl.BLOCK if name == "block" else zenoh.CongestionControl.DROP


def subscribe_payloads(session: zenoh.Session, key: str, callback: Callable[[bytes], None]) -> Any:
    """A subscriber that hands each sample's payload to ``callback`` on Zenoh's receiving thread (no Python thread
    of its own: keep the callback short). Undeclare it with ``.undeclare()``."""
    handler: zenoh.handlers.Callback[Any] = zenoh.handlers.Callback(
        lambda sample: callback(sample.payload.to_bytes()), indirect=False
    )
    return session.declare_subscriber(key, handler)


def open_session(
    mode: str, endpoint: str, connect_timeout_ms: int = 10_000, **files: Unpack[SessionFiles]
) -> zenoh.Session:
    """Open a session (see :func:`zenoh_config`); raise :class:`TransportError` naming the endpoint."""
    config = zenoh_config(mode, endpoint, connect_timeout_ms, **files)
    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        verb = "listen on" if mode == "router" else "connect to"
        config_file = files.get("config_file")
        secured = f" with {config_file}" if config_file else ""
        raise TransportError(f"zenoh {mode}: cannot {verb} {endpoint}{secured}: {exc}") from exc


def _json_documents(batch: EstimateBatch, rows: Sequence[int] | None) -> list[bytes]:
    return batch.documents(rows)


#: The encodings of a vehicle's own estimates: key kind -> (encoder of a batch's rows, Zenoh encoding). A
#: subscriber picks one by the key it subscribes to (docs/protocol.md).
VEHICLE_ENCODINGS: dict[Kind, tuple[Callable[[EstimateBatch, Sequence[int] | None], list[bytes]], zenoh.Encoding]] = {
    "estimate": (_json_documents, zenoh.Encoding.APPLICATION_JSON),
    BINARY_ESTIMATE_KIND: (encode_binary_estimates, zenoh.Encoding.APPLICATION_OCTET_STREAM),
}
#: The name of each encoding on /metrics.
ENCODING_NAMES: dict[Kind, str] = {"estimate": "json", BINARY_ESTIMATE_KIND: "binary"}


class VehiclePublisher(Protocol):
    """What the transport hands each tick's estimates to for the vehicles' own keys, and what /metrics reads of it:
    :class:`VehicleEstimates` (a thread of the service) or service.vehicle_fanout.VehicleFanout (a process)."""

    @property
    def sent(self) -> dict[str, int]: ...

    @property
    def dropped(self) -> int: ...

    @property
    def errors(self) -> int: ...

    @property
    def unmatched(self) -> int: ...

    @property
    def delay(self) -> Histogram: ...

    @property
    def backlog_s(self) -> float: ...

    def submit(self, batches: Sequence[EstimateBatch]) -> None: ...

    def close(self, timeout_s: float = 5.0) -> None: ...


class VehicleEstimates:
    """Each vehicle's estimates on its own keys, JSON and binary, put by a thread of their own.

    The ingest loop hands over a tick's batches (:meth:`submit`) and goes on: encoding and one ``put`` per
    vehicle and encoding (100,000 a second at 1,000 vehicles) run on this thread, and Zenoh's ``put`` releases
    the GIL while it sends. With ``subscribed_only`` (setting ``zenoh.vehicle_estimates='subscribed'``), a
    vehicle's estimate is encoded and sent only in the encodings someone subscribes to: each publisher has a
    matching listener, whose reports this thread applies before every publication. If the thread falls
    ``VEHICLE_QUEUE_MAX_AGE_S`` behind (a subscriber slower than the fleet with congestion control BLOCK), the
    oldest ticks' estimates are dropped and counted in :attr:`dropped`.

    Counters (written by one thread each, read by any): :attr:`sent` messages put by encoding name
    (:data:`ENCODING_NAMES`), :attr:`dropped` estimates dropped, :attr:`errors` publications that failed,
    :attr:`unmatched` vehicles nobody listens to in any encoding. Where the time goes: :attr:`delay`, each
    estimate put, from its sample's time stamp (vehicle clock) to the end of its tick's puts, and
    :attr:`backlog_s`, how long the oldest tick waiting has waited.

    While nobody subscribes to any vehicle's key in any encoding (:attr:`quiet`: every publisher settled, every
    key unmatched) a tick of vehicles that all have their publishers is not handed over at all: the ingest loop
    neither wakes this thread nor gives it the interpreter lock for a tick with nothing to put (:attr:`handed_over`
    counts the ticks that were). A matching report not yet applied, or a vehicle without its publishers, hands the
    tick over as before.
    """

    def __init__(self, session: zenoh.Session, prefix: str, congestion: Any, subscribed_only: bool) -> None:
        self.session = session
        self.prefix = prefix
        self.congestion = congestion
        self.subscribed_only = subscribed_only
        self.pubs: dict[tuple[str, Kind], Any] = {}
        self.listeners: list[Any] = []
        # matching reports appended from Zenoh's threads; publishers still settling; keys nobody matches
        self.match_events: collections.deque[tuple[tuple[str, Kind], bool]] = collections.deque()
        self.settling: dict[tuple[str, Kind], float] = {}
        self.unmatched_keys: dict[Kind, set[str]] = {kind: set() for kind in VEHICLE_ENCODINGS}
        self.sent: dict[str, int] = dict.fromkeys(ENCODING_NAMES.values(), 0)
        self.dropped = 0
        self.errors = 0
        self.unmatched = 0
        #: vehicles with a publisher in every encoding (this thread adds them; the ingest loop reads)
        self.declared: set[str] = set()
        #: nothing to put for a declared vehicle: every publisher settled and unmatched (set by this thread)
        self.quiet = False
        #: ticks the ingest loop handed to this thread
        self.handed_over = 0
        #: [s] per estimate put in some encoding (written by this thread only; a vehicle clock ahead counts as 0)
        self.delay = Histogram(END_TO_END_BUCKETS_S)
        self._queue: collections.deque[tuple[float, Sequence[EstimateBatch]]] = collections.deque()
        self._wake = threading.Event()
        self._take = threading.Lock()  # taking the oldest tick: the thread to publish it, submit() to drop it
        self._stopping = False
        self._thread = threading.Thread(target=self._run, name="vehicle-estimates", daemon=True)
        self._thread.start()

    def submit(self, batches: Sequence[EstimateBatch]) -> None:
        """Queue a tick's batches for publication (returns at once)."""
        if self.quiet and not self.match_events and all(self.declared.issuperset(b.vehicle_ids) for b in batches):
            return  # nobody would get any of these estimates: the thread stays asleep
        now = time.monotonic()
        queue = self._queue
        if queue and now - queue[0][0] > VEHICLE_QUEUE_MAX_AGE_S:
            with self._take:  # the thread takes from the same end
                while queue and now - queue[0][0] > VEHICLE_QUEUE_MAX_AGE_S:
                    self.dropped += sum(len(b) for b in queue.popleft()[1])
        queue.append((now, batches))
        self.handed_over += 1
        self._wake.set()

    @property
    def backlog_s(self) -> float:
        """How long the oldest tick waiting for publication has waited [s] (0: none waits)."""
        try:
            return max(0.0, time.monotonic() - self._queue[0][0])
        except IndexError:  # none waits, or the thread took the last one meanwhile
            return 0.0

    def close(self, timeout_s: float = 5.0) -> None:
        """Publish what is queued, stop the thread, undeclare the publishers and their listeners."""
        self._stopping = True
        self._wake.set()
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            log.warning("the vehicle estimate publisher did not stop within %g s", timeout_s)
        for entity in [*self.listeners, *self.pubs.values()]:
            with contextlib.suppress(zenoh.ZError):
                entity.undeclare()
        self.listeners, self.pubs, self.settling = [], {}, {}
        self.declared, self.quiet = set(), False

    def _run(self) -> None:
        while True:
            self._wake.wait(VEHICLE_IDLE_REFRESH_S)
            self._wake.clear()
            idle = not self._queue
            while self._queue:
                with self._take:
                    if not self._queue:
                        break
                    _, batches = self._queue.popleft()
                self._publish_counted(batches)
            if self._stopping:
                return
            if idle and self.subscribed_only:
                with contextlib.suppress(Exception):
                    self.refresh_matching()

    def _publish_counted(self, batches: Sequence[EstimateBatch]) -> None:
        """:meth:`publish`, its delays observed; a failure counted and logged (the publisher goes on)."""
        try:
            stamps = self.publish(batches)
        except Exception:  # a failed put or declaration
            self.errors += 1
            log.exception("publishing %d vehicles' estimates failed", sum(len(b) for b in batches))
            return
        self.delay.observe_since(stamps, time.time_ns())

    def publish(self, batches: Sequence[EstimateBatch]) -> list[np.ndarray]:
        """Encode and put ``batches`` on the vehicles' keys, in every encoding someone subscribes to; return the
        sample time stamps of the estimates put (in one encoding at least), an array per batch that had some."""
        if self.subscribed_only:
            self.refresh_matching()
        pubs = self.pubs
        stamps = []
        for batch in batches:
            put: set[int] | None = set()  # the rows put in some encoding (None: every row)
            for kind, (encode, _) in VEHICLE_ENCODINGS.items():
                unmatched = self.unmatched_keys[kind]
                ids = batch.vehicle_ids
                if unmatched:
                    rows = [j for j, vehicle_id in enumerate(ids) if vehicle_id not in unmatched]
                    if not rows:
                        continue
                    ids = [ids[j] for j in rows]
                    documents = encode(batch, rows)
                    if put is not None:
                        put.update(rows)
                else:
                    documents = encode(batch, None)
                    put = None
                for vehicle_id, document in zip(ids, documents, strict=True):
                    pub = pubs.get((vehicle_id, kind))
                    if pub is None:
                        pub = pubs[vehicle_id, kind] = self.declare(vehicle_id, kind)
                    pub.put(document)
                self.sent[ENCODING_NAMES[kind]] += len(documents)
            self.declared.update(batch.vehicle_ids)
            if put is None:
                stamps.append(batch.t_ns)
            elif put:
                stamps.append(batch.t_ns[sorted(put)])
        return stamps

    def declare(self, vehicle_id: str, kind: Kind) -> Any:
        """The publisher of ``vehicle_id``'s estimates in the encoding of key ``kind`` (with its matching listener
        when only subscribed keys get estimates)."""
        pub = self.session.declare_publisher(
            vehicle_key(vehicle_id, kind, self.prefix),
            congestion_control=self.congestion,
            encoding=VEHICLE_ENCODINGS[kind][1],
        )
        if self.subscribed_only:
            self.quiet = False  # a new publisher settles first, taken as matched
            events, key = self.match_events, (vehicle_id, kind)  # a deque: appending from Zenoh's threads is safe
            # indirect=False: the append runs on Zenoh's own thread. The default runs every callback handler on a
            # Python thread of its own: one thread per vehicle (1,014 threads at 1,000 vehicles, soak benchmark)
            callback: zenoh.handlers.Callback[Any] = zenoh.handlers.Callback(
                lambda status: events.append((key, status.matching)), indirect=False
            )
            self.listeners.append(pub.declare_matching_listener(callback))
            self.settling.pop(key, None)  # keep the dict in declaration order
            self.settling[key] = time.monotonic()
        return pub

    def refresh_matching(self, now: float | None = None) -> int:
        """Bring the keys nobody subscribes to up to date; return how many vehicles have no subscriber at all.

        Each publisher's matching listener reports every change, applied here in the order it came; a publisher
        whose first MATCH_SETTLE_S have passed has its status read once, since a listener reports changes only.
        A publisher still settling is taken as matched."""
        events, unmatched, settling = self.match_events, self.unmatched_keys, self.settling
        if events:  # before taking them: submit() must not skip a tick on the state before them
            self.quiet = False
        while events:
            (vehicle_id, kind), matched = events.popleft()
            if (vehicle_id, kind) in settling:
                continue  # taken as matched until its status is read below
            (unmatched[kind].discard if matched else unmatched[kind].add)(vehicle_id)
        if settling:
            now = time.monotonic() if now is None else now
            while settling:  # in the order the publishers were declared, so the oldest comes first
                key, declared = next(iter(settling.items()))
                if now - declared < MATCH_SETTLE_S:
                    break
                del settling[key]
                try:
                    matched = self.pubs[key].matching_status.matching
                except (KeyError, zenoh.ZError):
                    matched = True  # unknown: keep publishing
                (unmatched[key[1]].discard if matched else unmatched[key[1]].add)(key[0])
        sets = list(unmatched.values())
        self.unmatched = len(set.intersection(*sets)) if sets else 0
        declared = len(self.declared)
        self.quiet = not settling and not events and all(len(keys) == declared for keys in sets)
        return self.unmatched


_T = TypeVar("_T")


def _drain_by_vehicle(subscribers: Iterable[Any], value: Callable[[Any], _T]) -> list[tuple[str, _T]]:
    """What the subscribers on vehicle keys hold now, as (vehicle id, ``value(sample)``); a sample on a key that is
    not a vehicle's is skipped."""
    out: list[tuple[str, _T]] = []
    for sub in subscribers:
        while (sample := sub.try_recv()) is not None:
            try:
                vehicle_id, _ = parse_vehicle_key(str(sample.key_expr))
            except ValueError:
                continue
            out.append((vehicle_id, value(sample)))
    return out


class Transport:
    """The service's Zenoh session: measurement and liveliness subscriptions, estimate and alarm publication."""

    def __init__(
        self,
        settings: ZenohSettings,
        buckets: list[str],
        replica_id: str,
        dynamic: bool = False,
        child_dir: Path | None = None,
    ) -> None:
        """``dynamic``: the buckets change while the service runs (bucket leases): one subscription per bucket,
        each declared and undeclared on its own (:meth:`add_buckets`, :meth:`remove_buckets`). ``child_dir``:
        an embedded router also takes the service's child processes on a Unix socket there (:func:`zenoh_config`)."""
        self.settings = settings
        self.child_dir = child_dir
        self.prefix = settings.prefix
        self.buckets = list(buckets)
        self.replica_id = replica_id
        self.dynamic = dynamic
        self._session: zenoh.Session | None = None
        # by bucket, or one entry '*' for the whole fleet
        self._meas: dict[str, Any] = {}
        self._alive: dict[str, Any] = {}
        self._payloads: dict[str, Any] = {}  # the vehicles' own payload reports
        self._ownership_pub: Any = None
        self._ownership_sub: Any = None
        self._token: Any = None
        self._vehicle: VehiclePublisher | None = None  # each vehicle's own estimate keys, from open() on
        self._fleet_pub: Any = None
        self._alarm_pubs: dict[str, Any] = {}
        self._truth: dict[str, Any] = {}
        self._estimate_cc = estimate_congestion(settings.estimate_congestion)

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
        for name, key in self._selectors("payload", buckets).items():
            self._payloads[name] = session.declare_subscriber(key, zenoh.handlers.FifoChannel(PAYLOAD_CAPACITY))

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
            for entities in (self._meas, self._alive, self._payloads):
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
            s.mode,
            s.endpoint,
            s.connect_timeout_ms,
            config_file=s.config_file,
            credentials_file=s.credentials_file,
            child_dir=self.child_dir,
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
            if self.settings.vehicle_publisher == "thread":  # else the service attaches its process
                self._vehicle = VehicleEstimates(
                    session, self.prefix, self._estimate_cc, self.settings.vehicle_estimates == "subscribed"
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
        return _drain_by_vehicle(self._alive.values(), lambda sample: sample.kind == zenoh.SampleKind.PUT)

    def drain_payloads(self) -> list[tuple[str, bytes]]:
        """The vehicles' payload reports since the last call: (vehicle id, payload); at most PAYLOAD_CAPACITY a
        bucket between two calls are kept (a vehicle reports when its load changes)."""
        return _drain_by_vehicle(self._payloads.values(), lambda sample: sample.payload.to_bytes())

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

    def publish_estimates(self, batches: Sequence[EstimateBatch]) -> int:
        """Publish a tick's estimates; return how many went into the fleet message.

        Each vehicle's estimate goes to its own keys, JSON and binary, from the :class:`VehicleEstimates` thread
        (this call only queues them); with ``zenoh.vehicle_estimates='subscribed'``, only in the encodings a
        subscriber matches (a document nobody reads is not even made). The whole tick goes as one
        :class:`~agv_protocol.wire.FleetEstimates` message, here, when a subscriber matches the replica's fleet key.
        """
        self._require_vehicle().submit(batches)
        if self._fleet_pub is not None and batches and self._fleet_pub.matching_status.matching:
            self._fleet_pub.put(encode_fleet_estimates(self.replica_id, batches))
            return sum(len(b) for b in batches)
        return 0

    @property
    def vehicle_estimates(self) -> VehiclePublisher:
        """The publisher of each vehicle's own estimates (its counters: sent, dropped, errors, unmatched)."""
        return self._require_vehicle()

    def attach_vehicle_publisher(self, publisher: VehiclePublisher) -> None:
        """Hand each vehicle's estimates to ``publisher`` (setting ``zenoh.vehicle_publisher='process'``)."""
        if self._vehicle is not None:
            self._vehicle.close()
        self._vehicle = publisher

    def fleet_stream_matched(self) -> bool:
        """Whether a subscriber matches the replica's fleet stream now."""
        return self._fleet_pub is not None and bool(self._fleet_pub.matching_status.matching)

    def _require_vehicle(self) -> VehiclePublisher:
        if self._vehicle is None:
            raise TransportError("the transport is not open")
        return self._vehicle

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
        entities = [*self._meas.values(), *self._alive.values(), *self._payloads.values(), *self._truth.values()]
        fleet = [p for p in (self._fleet_pub, self._ownership_pub, self._ownership_sub) if p is not None]
        if self._vehicle is not None:  # first: it publishes what is queued on the open session
            self._vehicle.close()
            self._vehicle = None
        for entity in [*entities, *fleet, *self._alarm_pubs.values()]:
            with contextlib.suppress(zenoh.ZError):
                entity.undeclare()
        if self._token is not None:
            with contextlib.suppress(zenoh.ZError):
                self._token.undeclare()
        self._meas, self._alive, self._token, self._ownership_pub, self._ownership_sub = {}, {}, None, None, None
        self._payloads = {}
        self._alarm_pubs, self._truth, self._fleet_pub = {}, {}, None
        if self._session is not None:
            self._session.close()  # type: ignore[no-untyped-call]
            self._session = None
