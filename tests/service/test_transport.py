"""The service's Zenoh transport on its own: a real router session on loopback."""

import os
from collections.abc import Callable, Iterator

import numpy as np
import pytest
import zenoh

from agv_protocol.wire import BINARY_ESTIMATE_KIND, EstimateBatch, all_buckets, vehicle_key
from service.settings import ZenohSettings
from service.transport import (
    Transport,
    VehicleEstimates,
    apply_runtime_threads,
    open_session,
    runtime_threads_value,
)
from tests.service.helpers import free_port, wait_for

pytestmark = pytest.mark.network


def _os_threads() -> int:
    return len(os.listdir("/proc/self/task"))


@pytest.fixture
def router() -> Iterator[tuple[Transport, Callable[[], zenoh.Session]]]:
    """An open transport in router mode on a free loopback port, and a maker of client sessions of it (all closed
    after the test)."""
    settings = ZenohSettings(mode="router", endpoint=f"tcp/127.0.0.1:{free_port()}")
    transport = Transport(settings, all_buckets(), "replica-test")
    transport.open()
    clients: list[zenoh.Session] = []

    def client() -> zenoh.Session:
        clients.append(open_session("client", settings.endpoint))
        return clients[-1]

    try:
        yield transport, client
    finally:
        for session in clients:
            session.close()
        transport.close()


def test_estimate_publishers_and_their_matching_listeners_start_no_thread_per_vehicle(router):
    """With vehicle_estimates='subscribed' every vehicle's estimate publisher has a matching listener. Zenoh runs
    a callback handler on a Python thread of its own unless told otherwise: 1,014 threads at 1,000 vehicles
    (soak benchmark). The listeners' callbacks run on Zenoh's threads; they still report a subscriber that comes
    and goes."""
    transport, client = router
    ids = [f"many-{i:03d}" for i in range(60)]
    vehicles = transport.vehicle_estimates
    pubs = vehicles.pubs  # as the publisher thread keeps them: a dropped publisher is undeclared
    pubs[ids[0], "estimate"] = vehicles.declare(ids[0], "estimate")  # Zenoh's own pools start with the first
    before = _os_threads()
    for vehicle_id in ids[1:]:
        pubs[vehicle_id, "estimate"] = vehicles.declare(vehicle_id, "estimate")
    assert _os_threads() - before < 10  # 59 more publishers, each with a listener
    # the publisher thread applies the listeners' reports (here, with nothing to publish, twice a second)
    unmatched = vehicles.unmatched_keys["estimate"]
    wait_for(lambda: set(ids) <= unmatched, what="every key seen unmatched once settled")
    watcher = client().declare_subscriber(vehicle_key(ids[7], "estimate"))
    wait_for(lambda: ids[7] not in unmatched, what="the listener reporting the new subscriber")
    assert len(unmatched) == len(ids) - 1
    watcher.undeclare()
    wait_for(lambda: ids[7] in unmatched, what="the listener reporting the subscriber gone")


def _batch(ids: list[str], seq: int) -> EstimateBatch:
    n = len(ids)
    return EstimateBatch(
        ids,
        np.full(n, seq, dtype=np.int64),
        np.full(n, seq * 10_000_000, dtype=np.int64),
        np.zeros((n, 5)),
        np.ones(n, dtype=bool),
        np.zeros(n, np.int8),
        "0123456789ab",
    )


def test_a_tick_nobody_subscribes_to_is_not_handed_to_the_publisher_thread(router):
    """Once every vehicle's publishers have settled unmatched, the ingest loop keeps a tick to itself; a new
    vehicle, or a subscriber that comes, hands ticks over again, and the subscriber gets its estimates."""
    transport, client = router
    ids = [f"quiet-{i}" for i in range(3)]
    vehicles = transport.vehicle_estimates
    assert isinstance(vehicles, VehicleEstimates)
    vehicles.submit([_batch(ids, 0)])  # declares their publishers: taken as matched while they settle
    assert vehicles.handed_over == 1
    wait_for(lambda: vehicles.quiet, what="every key settled unmatched")
    assert vehicles.declared == set(ids)
    for seq in range(1, 4):
        vehicles.submit([_batch(ids, seq)])
    assert vehicles.handed_over == 1  # nothing to put: the thread was not woken
    vehicles.submit([_batch([*ids, "quiet-new"], 4)])
    assert vehicles.handed_over == 2  # a vehicle without publishers
    wait_for(lambda: vehicles.quiet, what="the new vehicle's keys settled unmatched")
    watcher = client().declare_subscriber(vehicle_key(ids[1], BINARY_ESTIMATE_KIND))
    seqs = iter(range(5, 100_000))

    def received() -> bool:
        vehicles.submit([_batch(ids, next(seqs))])
        return watcher.try_recv() is not None

    wait_for(received, what="the subscriber's estimates")
    assert vehicles.handed_over > 2 and not vehicles.quiet
    watcher.undeclare()
    wait_for(lambda: vehicles.quiet, what="the subscriber gone, every key unmatched again")


def test_the_runtime_threads_setting_becomes_zenohs_variable_unless_the_operator_set_it():
    environ: dict[str, str] = {}
    assert apply_runtime_threads(0, environ) is None and environ == {}  # Zenoh's own threads
    value = apply_runtime_threads(2, environ)
    assert value == environ["ZENOH_RUNTIME"] == runtime_threads_value(2)
    assert "(app: (worker_threads: 2)" in value and all(f"{rt}: (handover: app)" in value for rt in ("rx", "tx", "acc"))
    mine = {"ZENOH_RUNTIME": "(rx: (worker_threads: 4))"}
    assert apply_runtime_threads(1, mine) == "(rx: (worker_threads: 4))" == mine["ZENOH_RUNTIME"]
