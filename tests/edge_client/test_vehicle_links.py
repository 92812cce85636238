"""The vehicle side's matching state (edge_client/transport.VehicleLinks): a vehicle whose subscriber is reported
while its publisher's status is being read stays matched. The race cannot be forced on a real session (Zenoh's
thread reports when it will), so the first test drives VehicleLinks through a session stand-in that reports in
the middle of the read; the second runs a real session through a router on 127.0.0.1."""

import time
from typing import Any

import pytest

from agv_protocol.wire import fleet_selector
from edge_client.transport import ChannelSubscription, VehicleLinks, close_session, open_session


class _Status:
    def __init__(self, matching: bool) -> None:
        self.matching = matching


class _RacingPublisher:
    """Reads its status as unmatched, and while doing so Zenoh's thread reports the subscriber: the report comes
    after the value read, the order of a busy machine."""

    def __init__(self) -> None:
        self.listener: Any = None

    def declare_matching_listener(self, handler: Any) -> object:
        self.listener = handler
        return object()

    @property
    def matching_status(self) -> _Status:
        stale = _Status(False)
        self.listener(_Status(True))
        return stale


class _Session:
    def __init__(self) -> None:
        self.publishers: list[_RacingPublisher] = []

    def declare_publisher(self, *_args: Any, **_kwargs: Any) -> _RacingPublisher:
        self.publishers.append(_RacingPublisher())
        return self.publishers[-1]

    def liveliness(self) -> "_Session":
        return self

    def declare_token(self, _key: str) -> object:
        return object()


def test_a_subscriber_reported_while_the_status_is_read_leaves_the_vehicle_matched():
    session = _Session()
    links = VehicleLinks(session, ["a", "b"], truth=False)  # type: ignore[arg-type]
    assert links.matched.tolist() == [True, True]  # the report, not the stale status read before it
    changes = links.match_changes
    session.publishers[1].listener(_Status(False))  # later reports apply as they come
    assert links.matched.tolist() == [True, False] and links.match_changes == changes + 1


@pytest.mark.network
def test_every_vehicle_matches_a_subscriber_declared_before_its_publishers(router):
    listener = open_session(router.client())
    subscription = ChannelSubscription(listener, fleet_selector("meas"), 1000)
    session = open_session(router.client())
    try:
        time.sleep(0.3)
        links = VehicleLinks(session, [f"veh-{i:03d}" for i in range(200)], truth=False)
        try:
            deadline = time.monotonic() + 20.0
            while not links.matched.all() and time.monotonic() < deadline:
                time.sleep(0.01)
            assert links.matched.all(), [i for i, m in enumerate(links.matched) if not m]
        finally:
            links.close()
    finally:
        subscription.close()
        close_session(session)
        close_session(listener)
