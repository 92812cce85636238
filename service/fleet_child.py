"""A process of the service's own fed by the replica's fleet stream: what the vehicle-estimate process
(service/vehicle_fanout.py) and the estimate-history process (service/history_process.py) share.

The child is a Zenoh client of the service's router (a Unix socket of its own when the service embeds the router,
transport.child_endpoint) that subscribes to the replica's fleet stream
(:func:`~agv_protocol.wire.fleet_estimates_key`, one message per tick, which the service publishes while a
subscriber matches). Its counters and two flags (it subscribed; the service asks it to stop) are plain shared
integers without a lock: a child killed while holding a lock (of a multiprocessing Event) would hang the
service's close. The child stops when the service closes it, and on its own when the service process is gone.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import orjson

from agv_protocol.wire import EstimateBatch, ProtocolError, fleet_estimates_key
from agv_protocol.zenoh_session import TransportError
from service.settings import ZenohSettings
from service.transport import Session, child_endpoint, child_files, open_session, subscribe_payloads

log = logging.getLogger("agv_fe.service.fleet_child")

#: How long the service waits for a child to subscribe to its fleet stream [s] (a spawned interpreter's imports).
START_TIMEOUT_S = 60.0
#: How often a child looks for the stop flag and copies its counters to the shared memory [s].
POLL_S = 0.2


def fleet_batches(payload: bytes) -> list[EstimateBatch]:
    """The batches of a fleet-stream message (:class:`~agv_protocol.wire.FleetEstimates`) of this service."""
    try:
        message = orjson.loads(payload)
        if message.get("v") != 1:
            raise ProtocolError(f"fleet estimates of version {message.get('v')!r}: this side reads version 1")
        return [EstimateBatch.from_group(group) for group in message["groups"]]
    except (orjson.JSONDecodeError, KeyError, TypeError, ValueError, AttributeError) as exc:
        raise ProtocolError(f"not a fleet estimates message: {exc}") from exc


def child_session(zenoh_settings: dict[str, Any], child_dir: str | None) -> tuple[ZenohSettings, Session]:
    """The child's client session: with ``child_dir``, on the Unix socket of the service's embedded router there
    (transport.child_endpoint), without TLS, with the children's own user and password if the router asks for
    them; without, on the service's endpoint with the service's Zenoh settings (a service that is itself a client
    of a router)."""
    settings = ZenohSettings.model_validate(zenoh_settings)
    if child_dir is not None:
        config, credentials = child_files(Path(child_dir))
        session = open_session(
            "client",
            child_endpoint(Path(child_dir)),
            settings.connect_timeout_ms,
            config_file=config,
            credentials_file=credentials,
        )
        return settings, session
    session = open_session(
        "client",
        settings.endpoint,
        settings.connect_timeout_ms,
        config_file=settings.config_file,
        credentials_file=settings.credentials_file,
    )
    return settings, session


def serve_fleet_stream(
    session: Session,
    key: str,
    shared: Any,
    on_batches: Callable[[list[EstimateBatch]], None],
    every_poll: Callable[[int], None],
) -> None:
    """Subscribe to the fleet stream ``key``, hand each message's batches to ``on_batches`` (on Zenoh's receiving
    thread), say so in ``shared``, and call ``every_poll(unreadable)`` about every :data:`POLL_S` until the service
    asks the child to stop or is gone; then undeclare the subscription (the caller closes what it holds)."""
    parent = os.getppid()
    unreadable = [0]

    def arrived(payload: bytes) -> None:
        try:
            on_batches(fleet_batches(payload))
        except ProtocolError as exc:
            unreadable[0] += 1
            log.error("fleet stream: %s", exc)

    sub = subscribe_payloads(session, key, arrived)
    shared[len(shared) - 2] = 1
    try:
        while not shared[len(shared) - 1] and os.getppid() == parent:
            every_poll(unreadable[0])
    finally:
        sub.undeclare()


class FleetStreamChild:
    """The service's side of such a child: start it and wait until it subscribed, whether it lives, close it.

    ``target(*args, shared)`` runs in the child (a spawned interpreter); ``shared`` holds ``counters`` integers
    for the child to fill, then the two flags."""

    def __init__(self, target: Callable[..., None], args: tuple[Any, ...], counters: int, name: str) -> None:
        ctx = multiprocessing.get_context("spawn")
        self.shared = ctx.Array("q", counters + 2, lock=False)
        self.name = name
        self._process = ctx.Process(target=target, args=(*args, self.shared), name=name, daemon=True)

    def start_child(self, timeout_s: float = START_TIMEOUT_S) -> None:
        """Start the child and wait until it subscribes; raise :class:`TransportError` if it cannot."""
        self._process.start()
        deadline = time.monotonic() + timeout_s
        while not self.shared[len(self.shared) - 2]:
            time.sleep(0.05)
            if not self._process.is_alive() or time.monotonic() > deadline:
                self.close()
                raise TransportError(
                    f"the {self.name} process did not subscribe to the fleet stream within {timeout_s:g} s "
                    f"(exit code {self._process.exitcode})"
                )

    @property
    def alive(self) -> bool:
        return self._process.is_alive()

    @property
    def pid(self) -> int | None:
        """The child's process id (None: not started)."""
        return self._process.pid

    def close(self, timeout_s: float = 5.0) -> None:
        """Ask the child to stop and wait for it (it finishes what it holds); terminate it if it does not."""
        self.shared[len(self.shared) - 1] = 1
        if self._process.pid is None:
            return
        self._process.join(timeout_s)
        if self._process.is_alive():
            log.warning("the %s process did not stop within %g s: terminated", self.name, timeout_s)
            self._process.terminate()
            self._process.join(timeout_s)


def fleet_key(replica_id: str, settings: ZenohSettings) -> str:
    """The replica's fleet-stream key under the settings' prefix."""
    return fleet_estimates_key(replica_id, settings.prefix)
