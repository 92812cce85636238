"""The running replica: settings -> storage, fleet engine, profile policy, Zenoh transport, ingest loop.

:class:`Service` owns every part and runs on one asyncio loop: the ingest
loop drains the Zenoh channels, steps the fleet and publishes; REST handlers
read and change the fleet between two ticks, so a gain activation is atomic
for every vehicle of a profile without locks. Which profiles run, their
designs and jobs are the :class:`~service.profile_policy.ProfilePolicy`'s; which
buckets the replica serves, and their hand-over between replicas, the
:class:`~service.bucket_handover.BucketHandover`'s; the
FastAPI application and its lifespan are service/main.py's. Heavy work stays off the loop:
LMI designs in worker processes, gain re-verification in a thread, database
writes on the storage writer's thread (queued in order, retried while the
database fails, so a locked or full database never stops ingest).

The ingest and housekeeping loops are supervised: one that raises is named by
``/ready`` and restarted with backoff; when it cannot be kept running the
service declares itself failed and, after a grace period, asks the server to
stop, so that `agv-fe serve` exits non-zero and an orchestrator restarts it.
"""

from __future__ import annotations

import asyncio
import gc
import logging
import os
import re
import secrets
import shutil
import socket
import tempfile
import time
from collections.abc import Callable, Coroutine
from concurrent.futures import Future
from contextlib import suppress
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

from agv_protocol.wire import PayloadReport, ProtocolError, bucket_of
from service import logs
from service.bucket_handover import BucketHandover
from service.databases import open_storage
from service.fleet import AlarmChange, AlarmRecord, EngineConfig, EventBus, FleetEngine
from service.history import EstimateHistory
from service.history_process import HistoryProcess
from service.jobs import SynthesisJobs
from service.metrics import ServiceMetrics, service_registry
from service.profile_policy import ProfilePolicy
from service.settings import Settings
from service.storage import Storage
from service.storage_writer import StorageState, StorageUnavailable, StorageWriter, Write
from service.transport import Transport
from service.web.hub import DashboardHub

if TYPE_CHECKING:  # psycopg is imported only by a replica that uses PostgreSQL
    from service.bucket_leases import LeaseState
    from service.vehicle_fanout import VehicleFanout

log = logging.getLogger("agv_fe.service")


#: A background task that ran this long without failing has its restart count reset [s].
TASK_RESTART_RESET_S = 60.0
#: How long the start waits for a child process's subscription (vehicle estimates, history) to reach the fleet
#: stream [s].
CHILD_MATCH_S = 10.0
#: Longest wait before a failed background task is restarted [s].
TASK_RESTART_MAX_DELAY_S = 10.0


class ServiceError(Exception):
    """The service cannot start; the text says what to fix."""


def load_or_create_token(settings: Settings) -> str:
    """The API token: from settings, else DATA_DIR/api-token, created (mode 0600) on first start."""
    if settings.auth.token is not None:
        return settings.auth.token.get_secret_value()
    path = settings.data_dir / "api-token"
    if path.exists():
        return path.read_text().strip()
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    token = secrets.token_urlsafe(32)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(token + "\n")
    log.warning("no auth token configured: generated one in %s", path)
    return token


class Service:
    """Every running part of one replica."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.replica_id = replica_name(settings)
        ingest = settings.ingest
        self.events = EventBus()
        self.engine = FleetEngine(
            EngineConfig(
                unknown_vehicles=ingest.unknown_vehicles,
                default_profile=ingest.default_profile,
                long_gap_s=ingest.long_gap_s,
                seq_jump_slack=ingest.seq_jump_slack,
                estimate_every_n=ingest.estimate_every_n,
                history_samples=ingest.history_samples,
                prefix=settings.zenoh.prefix,
            ),
            events=self.events,
        )
        self.metrics = ServiceMetrics()
        self.dashboard = DashboardHub(self.engine, settings.dashboard, self.replica_id)
        #: the buckets served, their locks in a shared database and their hand-over between replicas
        self.handover = BucketHandover(settings, self.replica_id, self.engine)
        #: with a shared database: the buckets without an owner, their vehicles and (as warden) their alarms
        self.ownership = self.handover.ownership
        self.storage: Storage | None = None
        self.writer: StorageWriter | None = None
        #: the estimate history: a thread of this process, or a process of its own (setting history.writer)
        self.history: EstimateHistory | HistoryProcess | None = None
        self.transport: Transport | None = None
        #: the directory of the Unix socket of the service's child processes (an embedded router's), while running
        self._children_dir: Path | None = None
        #: the process that puts each vehicle's estimates on its keys (setting zenoh.vehicle_publisher='process')
        self.vehicle_process: VehicleFanout | None = None
        #: the profiles, their designs and jobs
        self.policy = ProfilePolicy(settings, self.engine, self, self.metrics)
        self.token = ""
        self.started_mono = time.monotonic()
        self._tasks: dict[str, asyncio.Task[None]] = {}
        self._loops: dict[str, Callable[[], Coroutine[Any, Any, None]]] = {
            "ingest": self._ingest_loop,
            "housekeeping": self._housekeeping_loop,
        }
        #: failures of each background task since start (for /metrics)
        self.task_failures: dict[str, int] = dict.fromkeys(self._loops, 0)
        #: background tasks not running now, and why (restarting, or failed for good)
        self.down_tasks: dict[str, str] = {}
        self._restarts: dict[str, int] = dict.fromkeys(self._loops, 0)
        self._task_started: dict[str, float] = {}
        #: set when a background task cannot be kept running: the process is going to exit
        self.fatal: str | None = None
        #: called (on the event loop) when the service has failed for good; `agv-fe serve` stops the server
        self.on_fatal: Callable[[], None] | None = None
        #: time.monotonic() of the ingest loop's latest iteration
        self.ingest_heartbeat = time.monotonic()
        self._running = False
        self.transport_up = False
        #: what /metrics exposes: this service's series and the process's (a registry per service instance)
        self.registry = service_registry(self)

    # ------------------------------------------------------------------ life cycle

    async def start(self) -> None:
        self.token = load_or_create_token(self.settings)
        self.storage = self._open_storage()
        self.writer = StorageWriter(self._open_storage(), self.settings.storage)
        if self.settings.database_url is not None:
            await self.policy.open_shared(self.settings.database_url)
        await self._load_state()
        h = self.settings.history
        if h.enabled and h.writer == "thread":
            self.history = EstimateHistory(
                self.settings.history_directory, self.replica_id, h.retention_h * 3600.0, h.chunk_s, h.precision
            )
            await asyncio.to_thread(self.history.start)
        self.transport = Transport(
            self.settings.zenoh, self.buckets, self.replica_id, self.settings.bucket_leases, self._child_dir()
        )
        await asyncio.to_thread(self.transport.open)
        if self.settings.zenoh.vehicle_publisher == "process":
            await self._start_vehicle_process(self.transport)
        if h.enabled and h.writer == "process":
            await self._start_history_process(self.transport)
        self.metrics.vehicle_estimates = self.transport.vehicle_estimates  # its counters, read at each scrape
        self.transport_up = True
        await self.handover.start(self.transport, self)
        self._running = True
        self.ingest_heartbeat = time.monotonic()
        for name in self._loops:
            self._spawn(name)
        if self.settings.dashboard.enabled:
            self.dashboard.start(truth=self.transport, ownership=self.transport)
        self.policy.start_listening()
        if self.settings.ingest.gc_freeze:
            gc.collect()
            gc.freeze()
        log.info(
            "replica %s serving buckets %s on zenoh %s %s",
            self.replica_id,
            self.handover.serving(),
            self.settings.zenoh.mode,
            self.settings.zenoh.endpoint,
        )

    async def _start_vehicle_process(self, transport: Transport) -> None:
        """The process that puts each vehicle's estimates on its keys (service/vehicle_fanout.py), subscribed to
        this replica's fleet stream before the first tick."""
        from service.vehicle_fanout import VehicleFanout

        fanout = VehicleFanout(self.settings.zenoh, self.replica_id, self._child_link())
        self.vehicle_process = await asyncio.to_thread(fanout.start)
        transport.attach_vehicle_publisher(self.vehicle_process)
        await self._fleet_stream_matched(transport, "vehicle estimate")

    async def _start_history_process(self, transport: Transport) -> None:
        """The process that keeps the estimate history (service/history_process.py), subscribed to this replica's
        fleet stream before the first tick."""
        settings = self.settings
        self.history = HistoryProcess(
            settings.zenoh, settings.history, settings.history_directory, self.replica_id, self._child_link()
        )
        await asyncio.to_thread(self.history.start)
        await self._fleet_stream_matched(transport, "history")

    def _child_dir(self) -> Path | None:
        """The directory of the Unix socket on which an embedded router takes this service's child processes
        (transport.zenoh_config), made for this run, only this user can enter it; None without children or router."""
        z, h = self.settings.zenoh, self.settings.history
        children = z.vehicle_publisher == "process" or (h.enabled and h.writer == "process")
        if not children or z.mode != "router":
            return None
        if self._children_dir is None:
            self._children_dir = Path(tempfile.mkdtemp(prefix="agv-fe-children-"))
        return self._children_dir

    def _child_link(self) -> str | None:
        """What a child process is told of where to connect (fleet_child.child_session)."""
        path = self._child_dir()
        return None if path is None else str(path)

    @staticmethod
    async def _fleet_stream_matched(transport: Transport, what: str) -> None:
        """Wait until a subscriber matches the fleet stream (the child process ``what`` just subscribed)."""
        deadline = time.monotonic() + CHILD_MATCH_S
        while not transport.fleet_stream_matched():
            if time.monotonic() > deadline:
                raise ServiceError(
                    f"the {what} process's subscription did not reach the fleet stream within {CHILD_MATCH_S:g} s"
                )
            await asyncio.sleep(0.01)

    def _open_storage(self) -> Storage:
        """A connection to the database: PostgreSQL when a URL is set, else the SQLite file in the data directory."""
        settings = self.settings
        return open_storage(settings.database_url, settings.database_path, settings.storage.busy_timeout_s)

    async def stop(self) -> None:
        self._running = False
        await self.handover.halt()  # no more buckets taken or given; the locks stay until the writes are stored
        await self.policy.close_shared()  # its claims go: another replica designs what this one leaves unfinished
        tasks = list(self._tasks.values())
        for task in tasks:
            task.cancel()
        for task in tasks:
            with suppress(asyncio.CancelledError, Exception):  # a failed task was reported when it failed
                await task
        self._tasks = {}
        await self.dashboard.stop()
        await self.policy.jobs.close()
        if self.history is not None:  # the estimates not yet written are written now
            await asyncio.to_thread(self.history.close)
            self.history = None
        if self.transport is not None:
            await asyncio.to_thread(self.transport.close)
            self.transport = None
            self.transport_up = False
        if self._children_dir is not None:
            shutil.rmtree(self._children_dir, ignore_errors=True)
            self._children_dir = None
        if self.writer is not None:
            # the writes still queued get storage.shutdown_flush_s to land (off the loop), then are given up
            await asyncio.to_thread(self.writer.close)
            self.writer = None
        if self.storage is not None:
            self.storage.close()
            self.storage = None
        self.handover.close()  # the lock sessions end: every bucket lock is released for the other replicas

    async def _load_state(self) -> None:
        """Profiles, gains, vehicles and latched alarms from the database; seed profiles on first start."""
        await self.policy.load()
        storage = self.db
        served = set(self.buckets)  # a shared database holds the whole fleet: only this replica's share runs here
        for vehicle_id, profile_name, registered in storage.vehicles():
            if bucket_of(vehicle_id) not in served:
                continue
            if profile_name in self.engine.banks:
                self.engine.register(vehicle_id, profile_name, registered)
            elif profile_name in self.failed_profiles:  # kept for its profile, not moved to the default one
                self.engine.hold(vehicle_id, profile_name, registered)
        for problem in self.engine.load_payloads(storage.payloads()):
            log.warning(problem)
        latched = [AlarmRecord.from_dict(r) for r in storage.latched_alarms() if bucket_of(r["vehicle"]) in served]
        self.engine.alarms.load(latched)

    @property
    def db(self) -> Storage:
        if self.storage is None:
            raise ServiceError("the service is not started")
        return self.storage

    def _require_transport(self) -> Transport:
        if self.transport is None:
            raise ServiceError("the transport is not open")
        return self.transport

    @property
    def ready(self) -> bool:
        return not self.not_ready_causes()

    def not_ready_causes(self) -> list[str]:
        """Why the replica should not take traffic, other than missing gains (empty: ready)."""
        causes = [] if self.transport_up else ["the Zenoh transport is down"]
        if self.transport_up and self.router_connected() is False:
            causes.append(f"no Zenoh router: the client session lost {self.settings.zenoh.endpoint}")
        if self.fatal is not None:
            causes.append(self.fatal)
        if self.vehicle_process is not None and not self.vehicle_process.alive:
            causes.append("the process that puts each vehicle's estimates on its keys has exited")
        if isinstance(self.history, HistoryProcess) and not self.history.alive:
            causes.append("the process that keeps the estimate history has exited")
        for name, why in self.down_tasks.items():
            causes.append(f"background task {name!r} is not running: {why}")
        age_s = self.ingest_heartbeat_age_s()
        if self._running and age_s > self.settings.health.heartbeat_timeout_s:
            causes.append(f"the ingest loop has not run for {age_s:.1f} s")
        storage = self.storage_state()
        if storage.degraded:
            causes.append(f"storage degraded: {storage.reason} ({storage.pending} writes queued)")
        leases = self.lease_state()
        if leases is not None and leases.rounds == 0:
            causes.append("the bucket leases have not completed their first round: the buckets served are not known")
        if not self.engine.ready:
            causes.append("not every profile has active gains")
        return causes

    def router_connected(self) -> bool | None:
        """Client mode: whether the session has a router now; None in router mode or before start."""
        if self.transport is None or self.settings.zenoh.mode != "client":
            return None
        return self.transport.router_connected()

    def ingest_heartbeat_age_s(self) -> float:
        return time.monotonic() - self.ingest_heartbeat

    def storage_state(self) -> StorageState:
        if self.writer is None:
            return StorageState(False, None, 0, 0, 0, None)
        return self.writer.state

    # ------------------------------------------------------------------ writes

    def store(self, what: str, apply: Write) -> Future[None]:
        """Queue a database write (applied in order on the writer's thread); the future says when it is stored."""
        if self.writer is None:
            raise ServiceError("the service is not started")
        return self.writer.submit(what, apply)

    def require_storage(self) -> None:
        """Before a change the API must acknowledge: refuse it while the database fails (nothing changed yet)."""
        state = self.storage_state()
        if state.degraded:
            raise StorageUnavailable(
                f"storage degraded ({state.reason}; {state.pending} writes queued): nothing was changed, retry later"
            )

    async def stored(self, what: str) -> None:
        """Wait until every write queued so far is committed, at most ``storage.api_write_timeout_s``."""
        if self.writer is None:
            raise ServiceError("the service is not started")
        barrier = asyncio.wrap_future(self.writer.barrier())
        try:
            await asyncio.wait_for(asyncio.shield(barrier), self.settings.storage.api_write_timeout_s)
        except TimeoutError as exc:
            state = self.storage_state()
            raise StorageUnavailable(
                f"{what} is applied but not stored yet ({state.reason or 'the database is slow'}): it is queued "
                "and stored once the database accepts writes"
            ) from exc

    def _spawn(self, name: str) -> None:
        if not self._running:
            return
        task = asyncio.get_running_loop().create_task(self._loops[name](), name=name)
        self._tasks[name] = task
        self._task_started[name] = time.monotonic()
        self.down_tasks.pop(name, None)
        task.add_done_callback(self._task_ended)

    def _task_ended(self, task: asyncio.Task[None]) -> None:
        """A background task ended: restart it with backoff, or, past ``health.task_restarts``, fail for good."""
        if task.cancelled() or not self._running:
            return
        name = task.get_name()
        exc = task.exception()
        why = f"{type(exc).__name__}: {exc}" if exc is not None else "it returned"
        self.task_failures[name] += 1
        log.error("background task %s failed: %s", name, why, exc_info=exc)
        loop = asyncio.get_running_loop()
        if time.monotonic() - self._task_started[name] > TASK_RESTART_RESET_S:
            self._restarts[name] = 0
        done, limit = self._restarts[name], self.settings.health.task_restarts
        if done < limit:
            self._restarts[name] = done + 1
            delay_s = min(0.5 * 2**done, TASK_RESTART_MAX_DELAY_S)
            self.down_tasks[name] = f"failed ({why}); restart {done + 1} of {limit} in {delay_s:g} s"
            loop.call_later(delay_s, self._spawn, name)
            return
        grace_s = self.settings.health.fatal_exit_grace_s
        self.down_tasks[name] = f"failed ({why}) after {done} restarts"
        self.fatal = f"the service failed: background task {name!r} cannot be kept running; it stops in {grace_s:g} s"
        log.critical("%s (last failure: %s)", self.fatal, why)
        loop.call_later(grace_s, self._give_up)

    def _give_up(self) -> None:
        if self.on_fatal is not None:
            self.on_fatal()
        else:
            log.critical("nothing stops this process: it stays up and /ready answers 503")

    async def _ingest_loop(self) -> None:
        ingest = self.settings.ingest
        transport = self._require_transport()
        engine, metrics = self.engine, self.metrics
        interval = ingest.tick_interval_s
        next_tick = time.perf_counter()
        while self._running:
            # a tick starts at most once per interval; a late one starts at once, after the event loop's other work
            wait = next_tick - time.perf_counter()
            await asyncio.sleep(wait if wait > 0 else 0)
            self.ingest_heartbeat = time.monotonic()
            started = time.perf_counter()
            next_tick = started + interval
            batch = transport.drain(ingest.max_batch)
            if not batch:
                continue
            result = engine.process(batch)
            if result.new_vehicles:
                rows = [(v.id, v.profile, v.registered_t_ns) for v in result.new_vehicles]
                self.store(f"the registration of {len(rows)} vehicles", partial(Storage.put_vehicles, rows=rows))
            if result.alarms:
                self.commit_alarms(result.alarms)
            if result.estimate_batches:
                metrics.fleet_estimates_out += transport.publish_estimates(result.estimate_batches)
                metrics.observe_end_to_end([b.t_ns for b in result.estimate_batches], time.time_ns())
                if self.history is not None:
                    self.history.append(result.estimate_batches)
            metrics.tick_seconds.observe(time.perf_counter() - started)
            metrics.tick_batch.observe(len(batch))
            metrics.last_batch = len(batch)
            if len(batch) >= ingest.max_batch:
                metrics.full_batches += 1

    async def _housekeeping_loop(self) -> None:
        transport = self._require_transport()
        while self._running:
            await asyncio.sleep(self.settings.ingest.housekeeping_interval_s)
            changes: list[AlarmChange] = []
            for vehicle_id, alive in transport.drain_liveliness():
                changes.extend(self.engine.liveliness(vehicle_id, alive))
            for vehicle_id, payload in transport.drain_payloads():
                self.report_payload(vehicle_id, payload)
            changes.extend(self.engine.housekeeping())
            changes.extend(await self.ownership.check())
            if changes:
                self.commit_alarms(changes)

    def report_payload(self, vehicle_id: str, payload: bytes) -> None:
        """A vehicle's own payload report (its ``payload`` key, agv_protocol.wire.PayloadReport): applied and stored
        as PUT /vehicles/{id}/payload does, or counted and logged by why not (malformed, unknown_vehicle,
        out_of_range: heavier than the profile's vehicle). A vehicle not yet registered is registered as its
        first measurement would register it (``ingest.unknown_vehicles``)."""
        counts = self.metrics.payload_reports
        try:
            report = PayloadReport.decode(payload)
        except ProtocolError as exc:
            counts["malformed"] += 1
            log.warning("payload report of %s refused: %s", vehicle_id, exc)
            return
        if vehicle_id not in self.engine.vehicles and not self._register_reporting(vehicle_id):
            counts["unknown_vehicle"] += 1
            log.warning("payload report of unknown vehicle %s refused", vehicle_id)
            return
        try:
            vehicle = self.engine.set_payload(vehicle_id, report.payload_kg)
        except ValueError as exc:
            counts["out_of_range"] += 1
            log.warning("payload report of %s refused: %s", vehicle_id, exc)
            return
        counts["applied"] += 1
        write = partial(Storage.put_payload, vehicle_id=vehicle.id, payload_kg=vehicle.payload_kg, t_ns=time.time_ns())
        self.store(f"the payload of {vehicle.id}", write)

    def _register_reporting(self, vehicle_id: str) -> bool:
        """Register a vehicle that reports before it measures, where unknown vehicles are registered."""
        engine = self.engine
        config = engine.config
        refused = config.unknown_vehicles == "reject" or config.default_profile not in engine.banks
        if refused or vehicle_id in engine.held:
            return False
        vehicle = engine.register(vehicle_id, config.default_profile, announced=True)
        rows = [(vehicle.id, vehicle.profile, vehicle.registered_t_ns)]
        self.store(f"the registration of {vehicle.id}", partial(Storage.put_vehicles, rows=rows))
        return True

    def commit_alarms(self, changes: list[AlarmChange]) -> Future[None]:
        """Queue the alarm changes for storage (one transaction) and publish them at once.

        The records are copied now: they change again before the writer stores them. Publication does not wait
        for the database, so a locked or full database delays no alarm; the future says when they are stored."""
        rows = [(c.record.to_dict(), c.event.model_dump()) for c in changes]
        done = self.store(f"{len(rows)} alarm changes", partial(Storage.record_alarm_changes, changes=rows))
        for change in changes:
            alarm = change.event
            raised_high = alarm.state == "raised" and alarm.level in ("FAULT", "STALE")
            logs.event(
                "alarm",
                logging.WARNING if raised_high else logging.INFO,
                state=alarm.state,
                vehicle=alarm.vehicle,
                profile=change.record.profile,
                kind=alarm.kind,
                level=alarm.level,
                id=alarm.id,
                value=alarm.value,
                threshold=alarm.threshold,
                t_ns=alarm.t_ns,
                detail=alarm.message or None,
            )
        if self.transport is not None:
            for change in changes:
                self.transport.publish_alarm(change.record.vehicle, change.event.encode())
        self.metrics.alarms_out += len(changes)
        return done

    @property
    def jobs(self) -> SynthesisJobs:
        """The synthesis jobs (the policy's)."""
        return self.policy.jobs

    @property
    def failed_profiles(self) -> dict[str, str]:
        """Stored profiles that could not be loaded, and why (the policy's); they do not run."""
        return self.policy.failed_profiles

    def status(self) -> dict[str, Any]:
        return {
            "replica": self.replica_id,
            "buckets": self.buckets,
            "uptime_s": round(time.monotonic() - self.started_mono, 3),
        }

    @property
    def buckets(self) -> list[str]:
        """The buckets this replica serves now (the hand-over's)."""
        return self.handover.buckets

    def lease_state(self) -> LeaseState | None:
        """The leases' view (owned buckets, live replicas, hand-overs), None with a static shard."""
        return self.handover.lease_state()


def replica_name(settings: Settings) -> str:
    """The replica's name: the setting, else replica-INDEX (static shard), else HOST-PID (bucket leases, where
    replicas have no index and each name must differ)."""
    shard = settings.shard
    if shard.replica_id is not None or not settings.bucket_leases:
        return shard.name
    host = re.sub(r"[^A-Za-z0-9_-]", "-", socket.gethostname())[:40] or "host"
    return f"{host}-{os.getpid()}"
