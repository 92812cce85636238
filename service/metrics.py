"""The service's Prometheus metrics: one ``prometheus_client`` registry per service instance.

The figures live where they are counted (the fleet engine, the job queue, the
storage writer, the ingest loop's :class:`ServiceMetrics`); :class:`ServiceCollector`
reads them at scrape time, so the ingest loop never calls into
``prometheus_client``, and values such as the vehicles by level or the latched
alarms are computed only when Prometheus asks. The registry also carries the
client's process (``process_*``), platform and garbage-collector (``python_*``)
collectors. Several services in one process (the tests) each have their own.
"""

from __future__ import annotations

import bisect
import os
import sys
import threading
from collections import Counter
from collections.abc import Iterator, Sequence
from importlib import metadata
from typing import TYPE_CHECKING, Protocol

import numpy as np
from prometheus_client import CollectorRegistry, GCCollector, PlatformCollector, ProcessCollector, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.registry import Collector

from agv_protocol.wire import all_buckets
from service.affinity import format_cpu_list
from service.fleet.vehicle import REJECT_REASONS
from service.thread_cpu import ThreadCpu

if TYPE_CHECKING:
    from service.bucket_leases import LeaseState
    from service.fleet import FleetEngine
    from service.history import EstimateHistory
    from service.history_process import HistoryProcess
    from service.jobs import SynthesisJobs
    from service.ownership import OwnershipWatch
    from service.settings import Settings
    from service.storage_writer import StorageState
    from service.transport import VehiclePublisher

#: The exposition format /metrics answers in: Prometheus' text format 0.0.4.
CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"

LATENCY_BUCKETS_S = (0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 1.0)
BATCH_BUCKETS = (1, 10, 100, 500, 1000, 2000, 5000, 10000, 20000)
SYNTHESIS_BUCKETS_S = (0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 60.0, 120.0, 300.0)
#: Sample time stamp (vehicle clock) to estimate published [s]: the network, the queue, the tick, and clock skew.
END_TO_END_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)
#: The vehicle levels counted by agv_fe_vehicles_by_level.
VEHICLE_LEVELS = ("OK", "WARN", "FAULT", "STALE")


class Histogram:
    """Cumulative-bucket histogram: one value at a time (:meth:`observe`) or a whole tick's (:meth:`observe_many`).

    counts : (len(buckets) + 1,) int64, the last entry the values above the highest bound (le="+Inf").
    """

    def __init__(self, buckets: Sequence[float]) -> None:
        self.bounds = [float(b) for b in buckets]
        self._bounds = np.array(self.bounds)
        self.counts = np.zeros(len(self.bounds) + 1, dtype=np.int64)
        self.sum = 0.0
        self.count = 0

    def observe(self, value: float) -> None:
        # a value equal to a bound belongs to that bound's bucket (le: less than or equal)
        self.counts[bisect.bisect_left(self.bounds, value)] += 1
        self.sum += value
        self.count += 1

    def observe_many(self, values: np.ndarray) -> None:
        """Add every value of ``values`` (n,) at once: one searchsorted and one bincount, whatever n is."""
        at = np.searchsorted(self._bounds, values, side="left")
        self.counts += np.bincount(at, minlength=self.counts.size)
        self.sum += float(values.sum())
        self.count += int(values.size)

    def observe_since(self, t_ns: Sequence[np.ndarray], now_ns: int) -> None:
        """Add the delays [s] from the time stamps ``t_ns`` [ns] (one array per batch) to ``now_ns``, in one
        vectorised step; a time stamp ahead of ``now_ns`` (a clock ahead) counts as 0."""
        if t_ns:
            stamps = t_ns[0] if len(t_ns) == 1 else np.concatenate(t_ns)
            self.observe_many(np.maximum(now_ns - stamps, 0) * 1e-9)

    def family(self, name: str, documentation: str) -> HistogramMetricFamily:
        cumulative = np.cumsum(self.counts).tolist()
        buckets = [(repr(b), n) for b, n in zip(self.bounds, cumulative, strict=False)]
        buckets.append(("+Inf", cumulative[-1]))
        return HistogramMetricFamily(name, documentation, buckets=buckets, sum_value=self.sum)


#: What became of a vehicle's payload report on its Zenoh key (service.app.Service.report_payload).
PAYLOAD_OUTCOMES = ("applied", "malformed", "unknown_vehicle", "out_of_range")


class ServiceMetrics:
    """The histograms and counters kept outside the fleet engine."""

    def __init__(self) -> None:
        self.tick_seconds = Histogram(LATENCY_BUCKETS_S)
        self.tick_batch = Histogram(BATCH_BUCKETS)
        self.synthesis_seconds = Histogram(SYNTHESIS_BUCKETS_S)
        self.end_to_end_seconds = Histogram(END_TO_END_BUCKETS_S)
        self.fleet_estimates_out = 0
        #: the publisher of each vehicle's own estimates (service.transport.VehicleEstimates), from the transport's
        #: start: its counters are read at each scrape
        self.vehicle_estimates: VehiclePublisher | None = None
        self.alarms_out = 0
        self.last_batch = 0
        self.full_batches = 0
        #: the vehicles' own payload reports by outcome (PAYLOAD_OUTCOMES)
        self.payload_reports: dict[str, int] = dict.fromkeys(PAYLOAD_OUTCOMES, 0)

    def observe_end_to_end(self, t_ns: Sequence[np.ndarray], published_ns: int) -> None:
        """Sample time stamps ``t_ns`` (vehicle clock [ns], one array per estimate batch) to ``published_ns``
        (service clock [ns]), added to the end-to-end histogram in one vectorised step. A vehicle clock ahead
        of the service's would give a negative delay: it counts as 0."""
        self.end_to_end_seconds.observe_since(t_ns, published_ns)


class MetricsSource(Protocol):
    """What :class:`ServiceCollector` reads: the service (service.app.Service) as seen from here."""

    replica_id: str
    settings: Settings
    engine: FleetEngine
    metrics: ServiceMetrics
    task_failures: dict[str, int]
    history: EstimateHistory | HistoryProcess | None
    ownership: OwnershipWatch

    @property
    def buckets(self) -> list[str]: ...

    @property
    def jobs(self) -> SynthesisJobs: ...

    @property
    def failed_profiles(self) -> dict[str, str]: ...

    @property
    def ready(self) -> bool: ...

    def storage_state(self) -> StorageState: ...

    def ingest_heartbeat_age_s(self) -> float: ...

    def router_connected(self) -> bool | None: ...

    def lease_state(self) -> LeaseState | None: ...


def _version(distribution: str) -> str:
    try:
        return metadata.version(distribution)
    except metadata.PackageNotFoundError:
        return "unknown"


def _one(family: GaugeMetricFamily | CounterMetricFamily, value: float) -> Metric:
    family.add_metric([], value)
    return family


class ServiceCollector(Collector):
    """Every agv_fe_* series, read from the service when Prometheus scrapes (on the event loop, between ticks)."""

    def __init__(self, source: MetricsSource) -> None:
        self.source = source
        shard = source.settings.shard
        self.build_labels = {
            "version": _version("agv-fault-estimator"),
            "python": ".".join(map(str, sys.version_info[:3])),
            "numpy": np.__version__,
            "zenoh": _version("eclipse-zenoh"),
            "replica": source.replica_id,
            "shard": f"{shard.index}/{shard.replicas}",
            # the CPUs the process runs on (setting cpus, or all it may use; '' where the system does not say)
            "cpus": format_cpu_list(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else "",
        }
        self._thread_cpu = ThreadCpu()

    def collect(self) -> Iterator[Metric]:
        yield from self._build_and_state()
        yield from self._ingest()
        yield from self._fleet()
        yield from self._jobs_and_storage()
        yield from self._leases()
        yield from self._threads()

    def _threads(self) -> Iterator[Metric]:
        """The process's CPU by thread group (service/thread_cpu.py); nothing where /proc has no task list."""
        seconds = self._thread_cpu.sample(threading.get_native_id())  # collect() runs on the event loop
        if not seconds:
            return
        family = CounterMetricFamily(
            "agv_fe_thread_cpu_seconds",
            "CPU time (user + system) of the process's threads by group: event_loop (the ingest loop, the API; near "
            "one core it limits the replica), the service's named threads, executor, zenoh, python_other, "
            "native_other",
            labels=["thread"],
        )
        for group in sorted(seconds):
            family.add_metric([group], round(seconds[group], 3))
        yield family

    def _leases(self) -> Iterator[Metric]:
        """Bucket ownership: what this replica serves (static shard or leases) and, with leases, the hand-overs."""
        yield _one(
            GaugeMetricFamily("agv_fe_buckets_owned", "key-expression buckets this replica serves now"),
            len(self.source.buckets),
        )
        served = GaugeMetricFamily(
            "agv_fe_bucket_served",
            "1 for each key-expression bucket this replica serves now, 0 for the others: summed over the replicas, "
            "a bucket at 0 has no owner (its vehicles get no estimates) and one above 1 has two",
            labels=["bucket"],
        )
        mine = set(self.source.buckets)
        for bucket in all_buckets():
            served.add_metric([bucket], int(bucket in mine))
        yield served
        yield from self._unowned()
        state = self.source.lease_state()
        if state is None:
            return
        changes = CounterMetricFamily(
            "agv_fe_bucket_ownership_changes",
            "buckets this replica took (gained) or handed over (lost) through the leases",
            labels=["change"],
        )
        changes.add_metric(["gained"], state.gained)
        changes.add_metric(["lost"], state.lost)
        yield changes
        yield _one(
            GaugeMetricFamily("agv_fe_lease_replicas", "live replicas sharing the buckets (members in the database)"),
            state.members,
        )
        yield _one(
            GaugeMetricFamily(
                "agv_fe_lease_connected",
                "1 while the lease connection to the database works (0: the buckets held are kept, none change)",
            ),
            int(state.connected),
        )

    def _unowned(self) -> Iterator[Metric]:
        """With a shared database: the fleet's buckets without an owner, as the lock table has them, and their
        registered vehicles (service/ownership.py); absent while not known."""
        watch = self.source.ownership
        if watch.unowned is None:
            return
        yield _one(
            GaugeMetricFamily(
                "agv_fe_buckets_unowned",
                "key-expression buckets no replica of the shared database holds now: their vehicles get no estimates",
            ),
            len(watch.unowned),
        )
        yield _one(
            GaugeMetricFamily(
                "agv_fe_vehicles_unserved", "registered vehicles of the buckets no replica holds now (GET /vehicles)"
            ),
            len(watch.statuses()),
        )
        yield _one(
            GaugeMetricFamily(
                "agv_fe_ownership_warden",
                "1 on the one replica of the shared database that raises the alarms of vehicles without an owner",
            ),
            int(watch.warden),
        )

    def _build_and_state(self) -> Iterator[Metric]:
        labels = self.build_labels
        build = GaugeMetricFamily(
            "agv_fe_build_info",
            "the running build: package, Python, numpy and Zenoh versions, replica, shard, the CPUs it runs on",
            labels=list(labels),
        )
        build.add_metric(list(labels.values()), 1)
        yield build
        src = self.source
        yield _one(
            GaugeMetricFamily(
                "agv_fe_ready", "1 when /ready answers 200: gains, Zenoh, ingest, background tasks and storage are fine"
            ),
            int(src.ready),
        )
        yield _one(
            GaugeMetricFamily("agv_fe_ingest_heartbeat_age_seconds", "time since the ingest loop's latest iteration"),
            round(src.ingest_heartbeat_age_s(), 6),
        )
        router = src.router_connected()
        if router is not None:
            yield _one(
                GaugeMetricFamily("agv_fe_zenoh_router_connected", "client mode: 1 while connected to a router"),
                int(router),
            )
        failures = CounterMetricFamily(
            "agv_fe_background_task_failures", "failures of the supervised background tasks, by task", labels=["task"]
        )
        for name, n in src.task_failures.items():
            failures.add_metric([name], n)
        yield failures

    def _ingest(self) -> Iterator[Metric]:
        engine, m = self.source.engine, self.source.metrics
        stats = engine.stats
        yield _one(
            CounterMetricFamily("agv_fe_measurements_received", "measurements taken from Zenoh"), stats["received"]
        )
        yield _one(
            CounterMetricFamily("agv_fe_measurements_accepted", "measurements that reached an observer"),
            stats["accepted"],
        )
        rejected = CounterMetricFamily(
            "agv_fe_measurements_rejected", "measurements rejected or dropped, by reason", labels=["reason"]
        )
        for reason in REJECT_REASONS:
            rejected.add_metric([reason], engine.rejected[reason])
        yield rejected
        yield _one(CounterMetricFamily("agv_fe_samples_missing", "samples missing in sequence gaps"), stats["missing"])
        yield _one(
            CounterMetricFamily("agv_fe_observer_restarts", "observer re-initialisations after long gaps"),
            stats["restarts"],
        )
        yield _one(CounterMetricFamily("agv_fe_estimates", "estimates computed"), stats["estimates"])
        yield _one(
            CounterMetricFamily(
                "agv_fe_samples_beyond_grip",
                "estimates whose vehicle was beyond its profile's grip limit (fault levels held unjudged)",
            ),
            stats["beyond_grip"],
        )
        yield from self._vehicle_keys()
        yield _one(
            CounterMetricFamily(
                "agv_fe_fleet_estimates_published",
                "estimates published on Zenoh in the replica's one-message-per-tick fleet stream",
            ),
            m.fleet_estimates_out,
        )
        yield _one(
            GaugeMetricFamily(
                "agv_fe_estimate_keys_unmatched",
                "vehicles whose estimate key no subscriber matched at the last check (their estimates are not sent)",
            ),
            0 if m.vehicle_estimates is None else m.vehicle_estimates.unmatched,
        )
        yield _one(
            GaugeMetricFamily(
                "agv_fe_ingest_last_batch",
                "measurements drained in the last tick (the queue depth seen by the ingest loop)",
            ),
            m.last_batch,
        )
        yield _one(
            CounterMetricFamily("agv_fe_ingest_full_batches", "ticks that hit ingest.max_batch (backlog)"),
            m.full_batches,
        )
        yield m.tick_seconds.family("agv_fe_tick_seconds", "time to drain, validate, step, alarm and publish one tick")
        yield m.tick_batch.family("agv_fe_tick_batch_measurements", "measurements per tick")
        yield m.end_to_end_seconds.family(
            "agv_fe_estimate_latency_seconds",
            "end-to-end delay of each estimate: from its sample's time stamp (vehicle clock) to its publication",
        )

    def _vehicle_keys(self) -> Iterator[Metric]:
        """Each vehicle's estimates on its own keys: how many, lost, failed, and how late."""
        vehicle = self.source.metrics.vehicle_estimates
        published = CounterMetricFamily(
            "agv_fe_estimates_published",
            "estimates published on Zenoh on their vehicle's key, by encoding (json on .../estimate, binary on "
            ".../estimate.bin)",
            labels=["encoding"],
        )
        for encoding, n in ({"json": 0, "binary": 0} if vehicle is None else vehicle.sent).items():
            published.add_metric([encoding], n)
        yield published
        yield _one(
            CounterMetricFamily(
                "agv_fe_vehicle_estimates_dropped",
                "estimates not put on their vehicle's keys: the publisher thread fell too many ticks behind",
            ),
            0 if vehicle is None else vehicle.dropped,
        )
        yield _one(
            CounterMetricFamily(
                "agv_fe_vehicle_estimate_errors", "publications of a tick's estimates on vehicle keys that failed"
            ),
            0 if vehicle is None else vehicle.errors,
        )
        yield (Histogram(END_TO_END_BUCKETS_S) if vehicle is None else vehicle.delay).family(
            "agv_fe_vehicle_estimate_latency_seconds",
            "each estimate put on its vehicle's own keys: from its sample's time stamp (vehicle clock) to the end of "
            "its tick's puts",
        )
        yield _one(
            GaugeMetricFamily(
                "agv_fe_vehicle_estimate_backlog_seconds",
                "how long the oldest tick waiting for publication on the vehicle keys has waited (0: none waits)",
            ),
            0.0 if vehicle is None else vehicle.backlog_s,
        )

    def _fleet(self) -> Iterator[Metric]:
        engine, m = self.source.engine, self.source.metrics
        vehicles = GaugeMetricFamily("agv_fe_vehicles", "registered vehicles by profile", labels=["profile"])
        by_level = GaugeMetricFamily(
            "agv_fe_vehicles_by_level", "registered vehicles by profile and level", labels=["profile", "level"]
        )
        for profile, counts in engine.vehicles_by_level().items():
            vehicles.add_metric([profile], sum(counts.values()))
            for level in VEHICLE_LEVELS:
                by_level.add_metric([profile, level], counts[level])
        yield vehicles
        yield by_level
        latched = GaugeMetricFamily(
            "agv_fe_alarms_latched",
            "latched alarms (raised, or cleared but not acknowledged) by kind, level, profile and acknowledgement",
            labels=["kind", "level", "profile", "acknowledged"],
        )
        latched_by: Counter[tuple[str, str, str, str]] = Counter(
            (r.kind, r.level, r.profile, "true" if r.acknowledged else "false") for r in engine.alarms.latched()
        )
        for key, n in sorted(latched_by.items()):
            latched.add_metric(list(key), n)
        yield latched
        yield _one(
            CounterMetricFamily("agv_fe_alarm_events_published", "alarm events stored and published"), m.alarms_out
        )
        payloads = CounterMetricFamily(
            "agv_fe_payload_reports", "the vehicles' own payload reports, by outcome", labels=["outcome"]
        )
        for outcome, n in m.payload_reports.items():
            payloads.add_metric([outcome], n)
        yield payloads
        dropped = CounterMetricFamily(
            "agv_fe_events_dropped",
            "fleet events an in-process subscriber (the dashboards' hub) fell behind on and lost, by kind",
            labels=["kind"],
        )
        for kind, n in engine.events.dropped.items():
            dropped.add_metric([kind], n)
        yield dropped

    def _jobs_and_storage(self) -> Iterator[Metric]:
        src = self.source
        yield src.metrics.synthesis_seconds.family("agv_fe_synthesis_seconds", "duration of finished synthesis jobs")
        jobs = CounterMetricFamily("agv_fe_synthesis_jobs", "finished synthesis jobs by outcome", labels=["status"])
        for status, n in src.jobs.finished.items():
            jobs.add_metric([status], n)
        yield jobs
        yield _one(
            GaugeMetricFamily(
                "agv_fe_profiles_failed",
                "stored profiles that could not be loaded at start-up and do not run (GET /profiles says why)",
            ),
            len(src.failed_profiles),
        )
        storage = src.storage_state()
        yield _one(
            GaugeMetricFamily(
                "agv_fe_storage_degraded",
                "1 while the database refuses writes (locked, full, failing): they are queued and retried",
            ),
            int(storage.degraded),
        )
        yield _one(
            GaugeMetricFamily("agv_fe_storage_writes_pending", "writes queued for the database"), storage.pending
        )
        yield _one(
            CounterMetricFamily("agv_fe_storage_write_failures", "failed database write attempts"), storage.failures
        )
        yield _one(
            CounterMetricFamily(
                "agv_fe_storage_writes_lost",
                "database writes given up (queue full, a write that cannot succeed, or pending at shutdown)",
            ),
            storage.lost,
        )
        yield from self._history()

    def _history(self) -> Iterator[Metric]:
        history = self.source.history
        if history is None:
            return
        h = history.stats
        yield _one(
            CounterMetricFamily("agv_fe_history_rows_written", "estimates written to the history"), h.rows_written
        )
        yield _one(
            CounterMetricFamily("agv_fe_history_write_failures", "history files that could not be written"),
            h.write_failures,
        )
        yield _one(
            CounterMetricFamily("agv_fe_history_rows_lost", "estimates of history files that could not be written"),
            h.rows_lost,
        )
        yield _one(GaugeMetricFamily("agv_fe_history_bytes", "bytes of the history files kept"), h.bytes_on_disk)


def service_registry(source: MetricsSource) -> CollectorRegistry:
    """A registry of its own for one service: its agv_fe_* series and the process, platform and GC collectors."""
    registry = CollectorRegistry(auto_describe=False)
    ProcessCollector(registry=registry)
    PlatformCollector(registry=registry)
    GCCollector(registry=registry)
    registry.register(ServiceCollector(source))
    return registry


def exposition(registry: CollectorRegistry) -> bytes:
    """One scrape, in the text format of :data:`CONTENT_TYPE`."""
    return generate_latest(registry)
