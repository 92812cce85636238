"""Zenoh for the vehicle side: sessions, per-vehicle publishers, subscriptions.

The only module of ``edge_client`` that imports zenoh; the publisher and the
dashboard use it through the small classes below, so the simulator, the
scenarios and the statistics stay transport-free.

Choices (see /work/shared/NOTES-zenoh.md for the measurements behind them):

* explicit endpoints, multicast scouting off, client mode by default;
* security: ``TransportOptions.config_file`` names a Zenoh JSON5 file with
  TLS, mutual TLS and user/password (deploy/zenoh/secure/vehicle.json5), read
  and merged as the service does (:func:`agv_protocol.zenoh_session.session_config`):
  mode and endpoints stay these options, user and password come from a file;
* ``connect/timeout_ms``: how long ``open`` waits for the first router (-1 =
  for ever); once open, a client reconnects by itself after a router restart,
  with retries every 250 ms growing to 1 s;
* measurements are published with congestion control BLOCK and priority
  DATA_HIGH: the observer needs every sample, and the default DROP lost half
  the messages under overload with no error. If the network cannot keep up the
  publisher's loop slows down, and that shows as late ticks in its statistics
  instead of silent loss. Ground truth, for validation only, is DROP and
  DATA_LOW so it can never hold measurements back;
* a measurement publisher's *matching status* (is any subscriber reachable
  for this key?) tells the publisher whether a sample can be delivered: it
  turns false within milliseconds when the router goes away and true again
  once the router is back and the service has re-declared its subscription.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, TypeVar

import numpy as np
import zenoh

from agv_protocol.wire import DEFAULT_PREFIX, PayloadReport, ProtocolError, vehicle_key
from agv_protocol.zenoh_session import ConfigValue, TransportError, session_config

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"


@dataclass(frozen=True)
class TransportOptions:
    """How to join the Zenoh network.

    mode : 'client' (through a router) or 'peer'; connect / listen : endpoints such as
    'tcp/127.0.0.1:7447'; connect_timeout_s : how long opening waits for a connect
    endpoint, -1 = wait for ever; prefix : key-expression prefix of the protocol;
    config_file : a Zenoh JSON5 configuration to start from (TLS, user/password), None
    for Zenoh's defaults; credentials_file : a USER:PASSWORD file for user/password authentication.
    """

    mode: Literal["client", "peer"] = "client"
    connect: tuple[str, ...] = (DEFAULT_ENDPOINT,)
    listen: tuple[str, ...] = ()
    connect_timeout_s: float = 10.0
    prefix: str = DEFAULT_PREFIX
    config_file: Path | None = None
    credentials_file: Path | None = None

    def describe(self) -> str:
        parts: list[str] = [self.mode]
        if self.connect:
            parts.append("connect " + ", ".join(self.connect))
        if self.listen:
            parts.append("listen " + ", ".join(self.listen))
        if self.config_file is not None:
            parts.append(f"config {self.config_file}")
        return "; ".join(parts)

    def config_values(self) -> list[ConfigValue]:
        """The vehicle side's values of a session's Zenoh configuration, for :func:`session_config` to lay on
        Zenoh's defaults or ``config_file``; raise TransportError on a missing endpoint."""
        if self.mode == "client" and not self.connect:
            raise TransportError("client mode needs at least one connect endpoint, e.g. tcp/127.0.0.1:7447")
        if self.mode == "peer" and not (self.connect or self.listen):
            raise TransportError("peer mode needs a connect or a listen endpoint (multicast scouting is off)")
        timeout_ms = -1 if self.connect_timeout_s < 0 else round(self.connect_timeout_s * 1000)
        return [
            ConfigValue("mode", self.mode, required=True),
            ConfigValue("connect/endpoints", list(self.connect), required=True),
            ConfigValue("listen/endpoints", list(self.listen), required=True),
            ConfigValue("scouting/multicast/enabled", False),
            ConfigValue("connect/timeout_ms", timeout_ms),
            ConfigValue("connect/retry", {"period_init_ms": 250, "period_max_ms": 1000, "period_increase_factor": 2}),
        ]


def open_session(options: TransportOptions) -> zenoh.Session:
    """Open a session; a router that cannot be reached in time, or a malformed endpoint, option or configuration
    file, is a TransportError naming it."""
    config = session_config(options.config_values(), options.config_file, options.credentials_file)
    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        hint = ""
        if options.mode == "client" and options.config_file is not None:
            hint = (
                "; is a zenoh router listening there, and does it accept this configuration's certificate and "
                "user? (a refused TLS handshake or password shows as a timeout)"
            )
        elif options.mode == "client":
            hint = (
                "; is a zenoh router listening there? (for example: docker run -p 7447:7447 eclipse/zenoh, "
                "or a longer --connect-timeout)"
            )
        raise TransportError(f"cannot open a zenoh session ({options.describe()}): {_first_line(exc)}{hint}") from exc


def close_session(session: zenoh.Session) -> None:
    """Close a session explicitly: an unclosed one with subscribers can hang the process at exit."""
    session.close()  # type: ignore[no-untyped-call]  # the stubs leave close() untyped


def _first_line(exc: BaseException) -> str:
    text = str(exc)
    return text.split(" at /", 1)[0].splitlines()[0] if text else type(exc).__name__


def connected_nodes(session: zenoh.Session) -> int:
    """Routers plus peers this session is connected to now."""
    info = session.info
    return len(info.routers_zid()) + len(info.peers_zid())


_Message = TypeVar("_Message")


#: How often :func:`report_payload` looks whether the service's subscriber is known yet [s].
_MATCH_POLL_S = 0.01


def report_payload(
    session: zenoh.Session, vehicle_id: str, payload_kg: float, prefix: str = DEFAULT_PREFIX, wait_s: float = 5.0
) -> bool:
    """Report what ``vehicle_id`` carries now on its ``payload`` key (agv_protocol.wire.PayloadReport): the
    service models the vehicle with it from then on (docs/math.md 12.5). A vehicle reports when its load
    changes. Waits at most ``wait_s`` until a subscriber (the service) is known, since a client sends only what
    some subscriber wants; returns whether one was, the report then sent reliably.

    Raises ProtocolError for a payload the protocol does not take (negative, not finite).
    """
    try:
        message = PayloadReport(payload_kg=payload_kg).encode()
    except ValueError as exc:
        raise ProtocolError(f"payload_kg: {exc}") from exc
    publisher: Any = session.declare_publisher(
        vehicle_key(vehicle_id, "payload", prefix),
        congestion_control=zenoh.CongestionControl.BLOCK,
        reliability=zenoh.Reliability.RELIABLE,
    )
    try:
        deadline = time.monotonic() + wait_s
        while not publisher.matching_status.matching and time.monotonic() < deadline:
            time.sleep(_MATCH_POLL_S)
        matched = bool(publisher.matching_status.matching)
        publisher.put(message)
        return matched
    finally:
        publisher.undeclare()


@dataclass(frozen=True)
class Received:
    """A received sample: its key, payload, receipt time (time.monotonic_ns) and whether it was a PUT."""

    key: str
    payload: bytes
    received_ns: int
    put: bool = True

    def decode(self, message: Callable[[bytes], _Message]) -> _Message | None:
        """The payload as ``message`` decodes it (a protocol class's ``decode``), or None when it is not one."""
        try:
            return message(self.payload)
        except ProtocolError:
            return None


class Subscription:
    """A subscriber on one key expression; ``callback`` runs on zenoh's thread for each sample."""

    def __init__(self, session: zenoh.Session, key_expr: str, callback: Callable[[Received], None]) -> None:
        def on_sample(sample: zenoh.Sample) -> None:
            now = time.monotonic_ns()
            callback(Received(str(sample.key_expr), sample.payload.to_bytes(), now))

        self._subscriber: Any = session.declare_subscriber(key_expr, on_sample)

    def close(self) -> None:
        self._subscriber.undeclare()


class Publication:
    """A publisher on one key expression, with liveliness tokens that announce it (e.g. to a ROS 2 graph)."""

    def __init__(self, session: zenoh.Session, key_expr: str, token_keys: Sequence[str] = ()) -> None:
        self._publisher: Any = session.declare_publisher(key_expr, reliability=zenoh.Reliability.RELIABLE)
        self._tokens: list[Any] = []
        try:
            self._tokens.extend(session.liveliness().declare_token(key) for key in token_keys)
        except BaseException:
            self.close()
            raise

    def put(self, payload: bytes, attachment: bytes | None = None) -> None:
        self._publisher.put(payload, attachment=attachment)

    def close(self) -> None:
        for item in (self._publisher, *self._tokens):
            with contextlib.suppress(zenoh.ZError):
                item.undeclare()
        self._tokens.clear()


class ChannelSubscription:
    """A subscriber whose samples wait in a bounded channel until :meth:`drain`.

    ``ring`` True: when full, the oldest samples are dropped (for streams where
    only the latest matters); False: a FIFO that makes zenoh wait (for events).
    ``liveliness`` True subscribes to liveliness tokens instead of samples
    (``put`` False means the token disappeared), with the tokens present at
    declaration reported first.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key_expr: str,
        capacity: int = 10_000,
        *,
        ring: bool = False,
        liveliness: bool = False,
    ) -> None:
        handler: Any = zenoh.handlers.RingChannel(capacity) if ring else zenoh.handlers.FifoChannel(capacity)
        self._subscriber: Any
        if liveliness:
            self._subscriber = session.liveliness().declare_subscriber(key_expr, handler, history=True)
        else:
            self._subscriber = session.declare_subscriber(key_expr, handler)

    def drain(self, limit: int = 1_000_000) -> list[Received]:
        """Every sample waiting now (at most ``limit``), oldest first, without blocking."""
        out: list[Received] = []
        now = time.monotonic_ns()
        while len(out) < limit:
            sample = self._subscriber.handler.try_recv()
            if sample is None:
                break
            out.append(
                Received(
                    str(sample.key_expr),
                    sample.payload.to_bytes(),
                    now,
                    put=sample.kind == zenoh.SampleKind.PUT,
                )
            )
        return out

    def close(self) -> None:
        self._subscriber.undeclare()


@dataclass
class VehicleLinks:
    """Per-vehicle publishers (measurements, ground truth), liveliness tokens and matching state.

    ``matched[i]`` is True while some subscriber can receive vehicle i's
    measurements; zenoh updates it from its own thread through a matching
    listener per vehicle.
    """

    session: zenoh.Session
    vehicle_ids: Sequence[str]
    prefix: str = DEFAULT_PREFIX
    truth: bool = True
    matched: np.ndarray = field(init=False)
    _meas: list[Any] = field(init=False, default_factory=list)
    _truth: list[Any] = field(init=False, default_factory=list)
    _tokens: list[Any] = field(init=False, default_factory=list)
    _listeners: list[Any] = field(init=False, default_factory=list)
    _lock: threading.Lock = field(init=False, default_factory=threading.Lock)
    _reports: list[int] = field(init=False, default_factory=list)  # matching reports per vehicle, so far
    match_changes: int = field(init=False, default=0)

    def __post_init__(self) -> None:
        self.matched = np.zeros(len(self.vehicle_ids), dtype=bool)
        self._reports = [0] * len(self.vehicle_ids)
        try:
            for i, vehicle_id in enumerate(self.vehicle_ids):
                # typed Any: the stubs say matching_status is a bool, it is a MatchingStatus
                publisher: Any = self.session.declare_publisher(
                    vehicle_key(vehicle_id, "meas", self.prefix),
                    congestion_control=zenoh.CongestionControl.BLOCK,
                    priority=zenoh.Priority.DATA_HIGH,
                    reliability=zenoh.Reliability.RELIABLE,
                )
                self._meas.append(publisher)
                self._listeners.append(
                    publisher.declare_matching_listener(
                        zenoh.handlers.Callback(self._matching_callback(i), indirect=False)
                    )
                )
                reports = self._reports[i]
                status = bool(publisher.matching_status.matching)
                with self._lock:  # a report that came while the status was read is newer than what was read
                    if self._reports[i] == reports:
                        self.matched[i] = status
                if self.truth:
                    self._truth.append(
                        self.session.declare_publisher(
                            vehicle_key(vehicle_id, "truth", self.prefix),
                            congestion_control=zenoh.CongestionControl.DROP,
                            priority=zenoh.Priority.DATA_LOW,
                        )
                    )
                self._tokens.append(
                    self.session.liveliness().declare_token(vehicle_key(vehicle_id, "alive", self.prefix))
                )
        except BaseException:
            self.close()
            raise

    def _matching_callback(self, i: int) -> Callable[[zenoh.MatchingStatus], None]:
        def on_change(status: zenoh.MatchingStatus) -> None:
            with self._lock:
                if bool(self.matched[i]) != status.matching:
                    self.match_changes += 1
                self.matched[i] = status.matching
                self._reports[i] += 1

        return on_change

    def measurement_putters(self) -> list[Callable[[bytes], None]]:
        """``put`` of each vehicle's measurement publisher, for a hot loop that calls them directly."""
        return [publisher.put for publisher in self._meas]

    def put_truth(self, i: int, payload: bytes) -> None:
        if self.truth:
            self._truth[i].put(payload)

    def close(self) -> None:
        """Undeclare everything (tokens last, so the vehicles disappear after their last sample)."""
        for item in (*self._listeners, *self._meas, *self._truth, *self._tokens):
            # the session may already be closed: then there is nothing left to release
            with contextlib.suppress(zenoh.ZError):
                item.undeclare()
        self._listeners.clear()
        self._meas.clear()
        self._truth.clear()
        self._tokens.clear()
