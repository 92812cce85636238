"""The service's Zenoh transport on its own: a real router session on loopback."""

import os

import pytest

from agv_protocol.wire import all_buckets, vehicle_key
from service.settings import ZenohSettings
from service.transport import Transport, open_session
from tests.service.helpers import free_port, wait_for

pytestmark = pytest.mark.network


def _os_threads() -> int:
    return len(os.listdir("/proc/self/task"))


def test_estimate_publishers_and_their_matching_listeners_start_no_thread_per_vehicle():
    """With vehicle_estimates='subscribed' every vehicle's estimate publisher has a matching listener. Zenoh runs
    a callback handler on a Python thread of its own unless told otherwise: 1,014 threads at 1,000 vehicles
    (soak benchmark). The listeners' callbacks run on Zenoh's threads; they still report a subscriber that comes
    and goes."""
    settings = ZenohSettings(mode="router", endpoint=f"tcp/127.0.0.1:{free_port()}")
    transport = Transport(settings, all_buckets(), "replica-test")
    transport.open()
    client = None
    try:
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
        client = open_session("client", settings.endpoint)
        watcher = client.declare_subscriber(vehicle_key(ids[7], "estimate"))
        wait_for(lambda: ids[7] not in unmatched, what="the listener reporting the new subscriber")
        assert len(unmatched) == len(ids) - 1
        watcher.undeclare()
        wait_for(lambda: ids[7] in unmatched, what="the listener reporting the subscriber gone")
    finally:
        if client is not None:
            client.close()
        transport.close()
