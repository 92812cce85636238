"""The publisher on real zenoh sessions through a router process on 127.0.0.1."""

import threading
import time
from collections import defaultdict

import numpy as np
import pytest

from agv_protocol.wire import (
    FLAG_SEQUENCE_RESTART,
    GroundTruth,
    Measurement,
    fleet_selector,
    parse_vehicle_key,
    vehicle_key,
)
from edge_client.fleet_mix import DEFAULT_MIX, build_fleet
from edge_client.publisher import FleetPublisher, PublisherOptions, VehicleRecord, answered
from edge_client.sources import SimulatedSource
from edge_client.transport import ChannelSubscription, Subscription, TransportOptions, close_session, open_session
from tests.edge_client.conftest import free_port

pytestmark = pytest.mark.network


#: The vehicle of :meth:`Counter.routed`'s probe: ground truth only, which the service does not subscribe to.
ROUTE_PROBE = "route-probe"


class Counter:
    """Decodes every measurement and ground truth it receives, per vehicle."""

    def __init__(self, session):
        self.meas = defaultdict(list)
        self.truth = defaultdict(list)
        self.lock = threading.Lock()
        self.subs = [
            Subscription(session, fleet_selector("meas"), self.on_meas),
            Subscription(session, fleet_selector("truth"), self.on_truth),
        ]

    def on_meas(self, rx):
        m = Measurement.decode(rx.payload)
        with self.lock:
            self.meas[m.vehicle_id].append(m)

    def on_truth(self, rx):
        t = GroundTruth.decode(rx.payload)
        with self.lock:
            self.truth[t.vehicle].append(t)

    def routed(self, router, timeout_s=10.0):
        """Wait until the router routes to this counter: a ground truth put from another session on a probe
        vehicle's key arrives (the measurement subscription, declared first on the same link, is in place then),
        so that a test that starts a sender right after sees its first sample."""
        sender = open_session(router.client())
        try:
            put = sender.declare_publisher(vehicle_key(ROUTE_PROBE, "truth"))
            truth = GroundTruth(vehicle=ROUTE_PROBE, seq=0, t_ns=0, vx=0.0, vy=0.0, r=0.0, torque_fault=0.0,
                                steer_fault=0.0).encode()  # fmt: skip
            deadline = time.monotonic() + timeout_s
            while not self.truth[ROUTE_PROBE]:
                assert time.monotonic() < deadline, "the router did not route to the counter"
                put.put(truth)
                time.sleep(0.05)
            put.undeclare()
        finally:
            close_session(sender)

    def close(self):
        for sub in self.subs:
            sub.close()


def fleet_source(n, duration_s, seed=0):
    members = build_fleet(DEFAULT_MIX, n, duration_s, seed=seed)
    return SimulatedSource([m.vehicle_id for m in members], [m.scenario for m in members])


def test_50_vehicles_at_100_hz_for_10_s(router):
    """One process, one session, 50 vehicles for 1,000 ticks of 10 ms: every sample sent and received in order,
    time stamped on the 10 ms schedule, nothing lost. The achieved rate and the pacing lateness are figures of
    the host at that moment: printed here, reported by `make bench` (docs/benchmarks/publisher.md), not asserted."""
    listener = open_session(router.client())
    counter = Counter(listener)
    alive = ChannelSubscription(listener, fleet_selector("alive"), 1000, liveliness=True)
    session = open_session(router.client())
    try:
        source = fleet_source(50, 10.0)
        time.sleep(0.3)
        # the first tick waits until the listener is matched on every vehicle's key (at most 10 s): on a busy
        # machine one vehicle's matching status had not arrived when the 10 s run ended, and its samples were
        # buffered and lost instead of sent (CI of stop 52: 49,000 sent of 50,000; a report overwritten by the
        # status read before it, since fixed: test_vehicle_links.py)
        options = PublisherOptions(truth_rate_hz=10.0, link_wait_s=10.0)
        with FleetPublisher(session, source, options) as publisher:
            report = publisher.run(10.0, drain_s=0.5)
            tokens = {parse_vehicle_key(rx.key)[0] for rx in alive.drain() if rx.put}
        print(
            f"\n50 vehicles: {report.sample_rate_hz:.3f} Hz over {report.elapsed_s:.3f} s, "
            f"lateness p50 {report.pacing.lateness_p50_ms:.3f} ms p99 {report.pacing.lateness_p99_ms:.3f} ms, "
            f"late {report.pacing.late}, overruns {report.pacing.overruns}"
        )
        assert report.pacing.ticks == 1000 and report.sent == 50 * 1000
        # the rate, overruns and lag depend on the host's speed, not on the publisher: they are printed above;
        # the schedule itself never slips (the timestamps below)
        assert report.lost == 0 and report.unsent_at_end == 0
        assert tokens == set(source.vehicle_ids)
        with counter.lock:
            assert set(counter.meas) == set(source.vehicle_ids)
            for messages in counter.meas.values():
                assert [m.seq for m in messages] == list(range(1000))
                assert messages[0].flags == FLAG_SEQUENCE_RESTART and messages[1].flags == 0
                assert set(np.diff([m.timestamp_ns for m in messages])) == {10_000_000}
            # ground truth decimated to 10 Hz, best effort
            truth_counts = [len(v) for v in counter.truth.values()]
            assert len(truth_counts) == 50 and min(truth_counts) >= 95 and max(truth_counts) <= 100
    finally:
        counter.close()
        alive.close()
        close_session(session)
        close_session(listener)


def test_undeliverable_samples_are_buffered_then_flushed_and_overflow_is_counted(router):
    """No subscriber for the first second: a 0.5 s buffer keeps the newest 50 samples, the rest are lost."""
    session = open_session(router.client())
    listener = open_session(router.client())
    counter: list[Counter] = []
    try:
        source = fleet_source(3, 2.0)
        options = PublisherOptions(truth_rate_hz=0.0, buffer_s=0.5)
        with FleetPublisher(session, source, options) as publisher:
            timer = threading.Timer(1.0, lambda: counter.append(Counter(listener)))
            timer.start()
            report = publisher.run(2.0, drain_s=0.5)
            timer.join()
        assert report.link_changes >= 3  # each vehicle went from unmatched to matched
        with counter[0].lock:
            for record in report.vehicles:
                seqs = [m.seq for m in counter[0].meas[record.vehicle_id]]
                # the oldest samples were dropped; what was sent arrived complete and in order
                assert 40 <= record.lost <= 60
                assert seqs == list(range(record.lost, 200))
                assert record.sent == len(seqs)
    finally:
        for c in counter:
            c.close()
        close_session(session)
        close_session(listener)


def test_peer_mode_without_a_router():
    """A publishing peer listens on an explicit endpoint; a subscribing peer connects to it directly."""
    port = free_port()
    publisher_options = TransportOptions(mode="peer", connect=(), listen=(f"tcp/127.0.0.1:{port}",))
    session = open_session(publisher_options)
    listener = open_session(TransportOptions(mode="peer", connect=(f"tcp/127.0.0.1:{port}",)))
    counter = Counter(listener)
    try:
        time.sleep(0.3)
        source = fleet_source(2, 1.0)
        with FleetPublisher(session, source, PublisherOptions(truth_rate_hz=0.0)) as publisher:
            report = publisher.run(1.0, drain_s=0.3)
        assert report.sent == 200 and report.lost == 0
        with counter.lock:
            assert {v: [m.seq for m in ms] for v, ms in counter.meas.items()} == {
                v: list(range(100)) for v in source.vehicle_ids
            }
    finally:
        counter.close()
        close_session(listener)
        close_session(session)


def test_a_publisher_without_a_buffer_waits_for_its_subscriber_and_loses_no_first_sample(router):
    """A live bridge keeps no buffer: a sample put while the matching status says nobody subscribes is lost (as
    right after its session opens, before Zenoh has learned the router's subscribers). With ``link_wait_s`` the
    run starts once the subscriber is known, here 0.3 s after the run was called: seq 0 arrives, nothing is lost."""
    session = open_session(router.client())
    listener = open_session(router.client())
    counter: list[Counter] = []
    try:
        source = fleet_source(2, 0.05)
        options = PublisherOptions(truth_rate_hz=0.0, buffer_s=0.0, link_wait_s=10.0)
        with FleetPublisher(session, source, options) as publisher:
            timer = threading.Timer(0.3, lambda: counter.append(Counter(listener)))
            timer.start()
            report = publisher.run(0.05, drain_s=0.5)
            timer.join()
        assert report.lost == 0 and report.sent == 10
        with counter[0].lock:
            assert all([m.seq for m in counter[0].meas[v]] == [0, 1, 2, 3, 4] for v in source.vehicle_ids)
    finally:
        for c in counter:
            c.close()
        close_session(session)
        close_session(listener)


def test_the_wait_for_a_subscriber_is_bounded(router):
    """Nobody subscribes: the run starts after ``link_wait_s`` and counts its samples lost."""
    started = time.monotonic()
    session = open_session(router.client())
    try:
        source = fleet_source(1, 0.05)
        options = PublisherOptions(truth_rate_hz=0.0, buffer_s=0.0, link_wait_s=0.3)
        with FleetPublisher(session, source, options) as publisher:
            report = publisher.run(0.05, drain_s=0.0)
    finally:
        close_session(session)
    assert report.lost == 5 and report.sent == 0
    assert time.monotonic() - started >= 0.3


def test_publisher_options_refuse_a_wait_out_of_range():
    with pytest.raises(ValueError, match="link_wait_s"):
        PublisherOptions(link_wait_s=-1.0)


def test_the_end_of_a_run_waits_for_the_last_estimate_of_every_answered_vehicle():
    """The drain after the last tick ends once each vehicle the service answers has an estimate per sample sent;
    a vehicle nobody answers (no service, or not served) is not waited for."""
    records = [VehicleRecord("a", sent=100, estimates=100), VehicleRecord("b", sent=100, estimates=98)]
    assert not answered(records)
    records[1].estimates = 100
    assert answered(records)
    records.append(VehicleRecord("c", sent=100))
    assert answered(records)
