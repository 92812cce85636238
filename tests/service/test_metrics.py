"""/metrics: the histograms, the collector's figures against the fleet engine, and a real service's scrape."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

import numpy as np
import pytest
from prometheus_client import CollectorRegistry

from agv_protocol.wire import Alarm, Measurement, all_buckets, shard_buckets
from edge_client.library import paper_1
from service.affinity import format_cpu_list
from service.app import Service
from service.fleet import EngineConfig, FleetEngine, FleetEvent
from service.history import EstimateHistory
from service.jobs import SynthesisJobs
from service.metrics import END_TO_END_BUCKETS_S, Histogram, ServiceCollector, ServiceMetrics, exposition
from service.ownership import OwnershipWatch
from service.settings import Settings
from service.storage_writer import StorageState
from tests.service.helpers import (
    PERIOD_NS,
    T0_NS,
    constant_measurement,
    make_settings,
    parse_metrics,
    probe,
    running,
    wait_for,
)
from tests.service.test_fleet_engine import FAULT_ALARMS, FakeClock, make_engine, pairs, run_scenario

#: Every series /metrics had before it used prometheus_client: dashboards, alerts, benchmarks and docs use them.
SERIES_BEFORE = (
    "agv_fe_measurements_received_total",
    "agv_fe_measurements_accepted_total",
    "agv_fe_measurements_rejected_total",
    "agv_fe_samples_missing_total",
    "agv_fe_observer_restarts_total",
    "agv_fe_estimates_total",
    "agv_fe_estimates_published_total",
    "agv_fe_fleet_estimates_published_total",
    "agv_fe_estimate_keys_unmatched",
    "agv_fe_alarm_events_published_total",
    "agv_fe_vehicles",
    "agv_fe_ingest_last_batch",
    "agv_fe_ingest_full_batches_total",
    "agv_fe_tick_seconds_count",
    "agv_fe_tick_batch_measurements_count",
    "agv_fe_synthesis_seconds_count",
    "agv_fe_synthesis_jobs_total",
    "agv_fe_profiles_failed",
    "agv_fe_storage_degraded",
    "agv_fe_storage_writes_pending",
    "agv_fe_storage_write_failures_total",
    "agv_fe_storage_writes_lost_total",
    "agv_fe_background_task_failures_total",
    "agv_fe_ingest_heartbeat_age_seconds",
    "agv_fe_ready",
)


def test_a_ticks_values_added_at_once_fill_the_buckets_as_one_by_one():
    rng = np.random.default_rng(0)
    bounds = END_TO_END_BUCKETS_S
    # log-uniform over the buckets, plus every bound itself (le: a value on a bound is in that bound's bucket)
    values = np.concatenate([10.0 ** rng.uniform(-4, 2, 5000), np.array(bounds), [0.0, 1e9]])
    one_by_one, at_once = Histogram(bounds), Histogram(bounds)
    for v in values.tolist():
        one_by_one.observe(v)
    at_once.observe_many(values[:1000])
    at_once.observe_many(values[1000:])
    assert one_by_one.counts.tolist() == at_once.counts.tolist()
    assert at_once.count == one_by_one.count == values.size
    assert at_once.sum == pytest.approx(one_by_one.sum, rel=1e-12)
    on_bounds = Histogram(bounds)
    on_bounds.observe_many(np.array(bounds))
    assert on_bounds.counts.tolist() == [1] * len(bounds) + [0]


def test_end_to_end_delay_is_taken_from_the_sample_stamp_and_a_clock_ahead_counts_as_zero():
    m = ServiceMetrics()
    published_ns = 10_000_000_000
    stamps = [np.array([published_ns - 3_000_000, published_ns - 30_000_000]), np.array([published_ns + 5_000_000])]
    m.observe_end_to_end(stamps, published_ns)
    m.observe_end_to_end([], published_ns)  # a tick without estimates observes nothing
    h = m.end_to_end_seconds
    assert h.count == 3 and h.sum == pytest.approx(0.033)
    bucket_of = {b: i for i, b in enumerate(END_TO_END_BUCKETS_S)}
    expected = np.zeros(len(END_TO_END_BUCKETS_S) + 1, dtype=int)
    expected[0] += 1  # the vehicle clock 5 ms ahead: 0 s
    expected[bucket_of[0.005]] += 1  # 3 ms
    expected[bucket_of[0.05]] += 1  # 30 ms
    assert h.counts.tolist() == expected.tolist()


@dataclass
class _Source:
    """The parts of a service the collector reads, around a real fleet engine."""

    engine: FleetEngine
    settings: Settings = field(default_factory=Settings)
    replica_id: str = "replica-0"
    metrics: ServiceMetrics = field(default_factory=ServiceMetrics)
    jobs: SynthesisJobs = field(default_factory=lambda: SynthesisJobs(1, _never, _ignore))
    failed_profiles: dict[str, str] = field(default_factory=dict)
    task_failures: dict[str, int] = field(default_factory=dict)
    buckets: list[str] = field(default_factory=list)
    history: EstimateHistory | None = None
    ready: bool = True
    ownership: OwnershipWatch = field(init=False)

    def __post_init__(self) -> None:
        self.ownership = OwnershipWatch(self.engine, unserved_after_s=2.0)  # no shared database: knows nothing

    def storage_state(self) -> StorageState:
        return StorageState(False, None, 0, 0, 0, None)

    def ingest_heartbeat_age_s(self) -> float:
        return 0.0

    def router_connected(self) -> bool | None:
        return None

    def lease_state(self) -> None:
        return None


async def _never(*_args: object) -> None:
    raise AssertionError("no job runs here")


def _ignore(*_args: object) -> None:
    return None


def test_vehicles_by_level_and_latched_alarms_by_kind_level_and_profile(fast_gains):
    """A faulty vehicle latches a torque FAULT, a healthy one stays OK, a silent one goes STALE: the scrape counts
    each, and an acknowledgement moves the FAULT alarm to acknowledged="true"."""
    clock = FakeClock()
    engine = make_engine(fast_gains, clock=clock, alarms={**FAULT_ALARMS, "stale_after_s": 1.0})
    run_scenario(engine, paper_1(), 900, vehicle="faulty")
    run_scenario(engine, paper_1().model_copy(update={"faults": ()}), 900, vehicle="healthy")
    engine.process(pairs([constant_measurement("silent", 0)]))
    clock.mono += 2.0
    engine.housekeeping()  # every vehicle is silent now: all three STALE
    for k in range(1, 3):  # the healthy and the faulty vehicle speak again
        engine.process(pairs([constant_measurement("healthy", 900 + k, torque=60.0)]))
    registry = CollectorRegistry(auto_describe=False)
    registry.register(ServiceCollector(_Source(engine)))

    scrape = parse_metrics(exposition(registry).decode())
    level = {lv: scrape.value("agv_fe_vehicles_by_level", profile="default", level=lv) for lv in ("OK", "WARN")}
    assert level == {"OK": 1, "WARN": 0}
    assert scrape.value("agv_fe_vehicles_by_level", profile="default", level="FAULT") == 0  # it is stale now
    assert scrape.value("agv_fe_vehicles_by_level", profile="default", level="STALE") == 2
    assert scrape.value("agv_fe_vehicles", profile="default") == 3
    fault = {"kind": "torque_fault", "level": "FAULT", "profile": "default"}
    assert scrape.value("agv_fe_alarms_latched", **fault, acknowledged="false") == 1
    stale = {"kind": "stale", "level": "STALE", "profile": "default", "acknowledged": "false"}
    # the silent and the faulty vehicle's are raised, the healthy vehicle's cleared but not acknowledged yet
    assert scrape.value("agv_fe_alarms_latched", **stale) == 3
    latched = sum(v for (n, _), v in scrape.samples.items() if n == "agv_fe_alarms_latched")
    assert latched == len(engine.alarms.latched())

    fault_alarm = engine.alarms.current("faulty", "torque_fault")
    assert fault_alarm is not None
    engine.acknowledge(fault_alarm.id, by="op")
    scrape = parse_metrics(exposition(registry).decode())
    assert scrape.value("agv_fe_alarms_latched", **fault, acknowledged="true") == 1
    assert ("agv_fe_alarms_latched", frozenset({**fault, "acknowledged": "false"}.items())) not in scrape.samples


def test_events_a_slow_subscriber_loses_are_counted_by_kind_and_stay_counted_after_it_closes():
    """A subscription with room for two events loses its oldest to each new one: the scrape counts each lost
    event under its own kind (not the kind of the event that pushed it out), a subscription with room loses
    nothing, and the counter keeps what a closed subscription lost."""
    engine = FleetEngine(EngineConfig())
    registry = CollectorRegistry(auto_describe=False)
    registry.register(ServiceCollector(_Source(engine)))

    def dropped() -> dict[str, float]:
        scrape = parse_metrics(exposition(registry).decode())
        assert scrape.types["agv_fe_events_dropped_total"] == "counter"
        return {
            kind: scrape.value("agv_fe_events_dropped_total", kind=kind) for kind in ("estimate", "alarm", "vehicle")
        }

    def alarm(n: int) -> FleetEvent:
        data = Alarm(vehicle="v", id=f"al-{n}", kind="stale", level="STALE", state="raised", t_ns=n, message="")
        return FleetEvent("alarm", "v", data)

    assert dropped() == {"estimate": 0, "alarm": 0, "vehicle": 0}
    with (
        engine.events.subscribe(maxsize=2, kinds=("alarm", "vehicle")) as slow,
        engine.events.subscribe(maxsize=10, kinds=("alarm",)) as roomy,
    ):
        for n in range(3):  # the third pushes out the first
            engine.events.publish(FleetEvent("vehicle", f"v{n}", {"state": "registered"}))
        engine.events.publish(alarm(0))  # pushes out the second vehicle event
        assert dropped() == {"estimate": 0, "alarm": 0, "vehicle": 2}
        engine.events.publish(alarm(1))  # pushes out the third vehicle event
        engine.events.publish(alarm(2))  # pushes out alarm 0
        assert [e.data for e in (slow.get_nowait(), slow.get_nowait())] == [alarm(1).data, alarm(2).data]
        assert len([roomy.get_nowait() for _ in range(3)]) == 3 and roomy.get_nowait() is None
    engine.events.publish(alarm(3))  # nobody listens: nothing is queued, nothing lost
    assert dropped() == {"estimate": 0, "alarm": 1, "vehicle": 3}


def test_a_real_service_exposes_its_series_the_process_and_the_end_to_end_delay(tmp_path):
    """The scrape of a running service: the content type Prometheus reads, every series of before, build_info,
    process_* and python_*; each estimate's delay from its sample's time stamp observed once (samples stamped
    in 2023 land in +Inf, one stamped an hour ahead of the service's clock in the first bucket); and a second
    service in the same process has a registry of its own."""
    settings = make_settings(tmp_path / "a")
    n = 20
    with running(settings) as srv, probe(settings.zenoh.endpoint) as p:
        for k in range(n):
            p.put(constant_measurement("old-clock", k))
        ahead_ns = time.time_ns() + 3600 * 10**9
        p.put(Measurement("clock-ahead", 0, ahead_ns, 10.0, 0.0, 60.0, 0.0))
        wait_for(lambda: len(p.estimates_of("old-clock")) >= n and p.estimates_of("clock-ahead"), what="estimates")

        def settled() -> object:
            m = parse_metrics(srv.get("/metrics").text)
            observed = [m.value(f"agv_fe_{s}estimate_latency_seconds_count") for s in ("", "vehicle_")]
            return m if observed == [n + 1, n + 1] else None

        scrape = wait_for(settled, what="every estimate's delay observed")
        response = srv.get("/metrics")
        assert response.headers["content-type"] == "text/plain; version=0.0.4; charset=utf-8"
        for name in SERIES_BEFORE:
            assert any(sample == name for sample, _ in scrape.samples), name
        build = [dict(labels) for name, labels in scrape.samples if name == "agv_fe_build_info"]
        assert len(build) == 1 and build[0]["replica"] == "replica-0" and build[0]["shard"] == "0/1"
        assert build[0]["cpus"] == format_cpu_list(os.sched_getaffinity(0))  # this process's: no cpus setting
        assert scrape.value("process_resident_memory_bytes") > 0 and scrape.value("process_cpu_seconds_total") > 0
        assert scrape.types["python_gc_collections_total"] == "counter"
        assert scrape.value("agv_fe_estimates_total") == n + 1
        assert scrape.value("agv_fe_vehicles_by_level", profile="default", level="OK") == 2
        # one replica serves every bucket: each of the 16 at 1 (the alerts sum them over the replicas)
        assert [scrape.value("agv_fe_bucket_served", bucket=b) for b in all_buckets()] == [1] * 16

        other = Service(make_settings(tmp_path / "b", shard={"replicas": 2, "index": 1}))  # built, not started
        served = parse_metrics(exposition(other.registry).decode())
        assert [served.value("agv_fe_bucket_served", bucket=b) for b in all_buckets()] == [
            int(b in shard_buckets(1, 2)) for b in all_buckets()
        ]
        age_s = (time.time_ns() - T0_NS - n * PERIOD_NS) / 1e9
        # at the tick, and at the end of the puts on each vehicle's own key (the probe subscribes to them)
        for name in ("agv_fe_estimate_latency_seconds", "agv_fe_vehicle_estimate_latency_seconds"):
            buckets = scrape.buckets(name)
            assert buckets[0] == (END_TO_END_BUCKETS_S[0], 1), name  # the vehicle clock ahead
            assert buckets[-2][1] == 1 and buckets[-1] == (float("inf"), n + 1), name  # the others are years old
            assert scrape.value(f"{name}_sum") >= n * age_s * 0.99, name
        assert 0 <= scrape.value("agv_fe_vehicle_estimate_backlog_seconds") < 2.0

        other = Service(make_settings(tmp_path / "c"))  # built, not started: its registry is its own
        other_scrape = parse_metrics(exposition(other.registry).decode())
        assert other_scrape.value("agv_fe_measurements_received_total") == 0
        assert other_scrape.value("agv_fe_estimate_latency_seconds_count") == 0
        assert other_scrape.value("process_resident_memory_bytes") > 0
        assert parse_metrics(srv.get("/metrics").text).value("agv_fe_measurements_received_total") == n + 1


def test_samples_beyond_the_grip_limit_are_counted_per_vehicle_sample_and_scraped(fast_gains):
    """A vehicle in a 0.92 g turn (10 m/s at 0.9 rad/s) is beyond the default 0.8 g cornering limit from its
    first sample (the filter starts at the sample's v_x r); one driving straight beside it never is; a profile
    without the gate counts nothing."""
    engine = make_engine(fast_gains)
    for k in range(40):
        engine.process(pairs([constant_measurement("turning", k, r=0.9), constant_measurement("straight", k)]))
    assert engine.stats["beyond_grip"] == 40
    registry = CollectorRegistry(auto_describe=False)
    registry.register(ServiceCollector(_Source(engine)))
    scrape = parse_metrics(exposition(registry).decode())
    assert scrape.types["agv_fe_samples_beyond_grip_total"] == "counter"
    assert scrape.value("agv_fe_samples_beyond_grip_total") == 40
    ungated = make_engine(fast_gains, alarms={"grip_limit_g": None})
    for k in range(40):
        ungated.process(pairs([constant_measurement("turning", k, r=0.9)]))
    assert ungated.stats["beyond_grip"] == 0
