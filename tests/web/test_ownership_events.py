"""Bucket ownership changes as fleet-level events, on a real PostgreSQL server (bucket leases).

Replica ``ra`` runs in-process (uvicorn, the Zenoh router); replica ``rb`` is `agv-fe serve`, a Zenoh client of
ra's router, on the same database. rb joins (ra hands over half the buckets, rb takes them), then is killed
with SIGKILL (ra takes them back). Each replica announces its changes on Zenoh
(``{prefix}/v1/service/{replica}/ownership``); ra's dashboard pushes every replica's announcements to its fleet
streams, and the fleet view lists them, newest first.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import pytest
import zenoh
from playwright.sync_api import expect

from agv_protocol.wire import OwnershipChange, all_buckets, bucket_of, ownership_selector
from service.settings import Settings
from service.transport import open_session
from tests.service.helpers import FAST_DESIGN, ServiceProcess, make_settings, wait_for
from tests.web.helpers import dashboard_server, steady_fleet
from tests.web.test_browser import UI_TIMEOUT_MS

pytestmark = pytest.mark.network

PROFILES = {"default": {"design": FAST_DESIGN}}
#: A small fleet, so that every change moves some vehicles (12 vehicles over 16 buckets).
VEHICLES = {f"veh-{k:02d}": 0.0 for k in range(12)}


def replica_settings(tmp_path: Path, name: str, url: str, **zenoh_settings: str) -> Settings:
    overrides: dict[str, Any] = {"database": {"url": url}, "shard": {"replica_id": name, "lease_interval_s": 0.2}}
    if zenoh_settings:
        overrides["zenoh"] = zenoh_settings
    return make_settings(tmp_path / name, PROFILES, **overrides)


@contextmanager
def joining_replica(tmp_path: Path, url: str, router: Settings) -> Iterator[ServiceProcess]:
    """Replica rb, a Zenoh client of the in-process replica's router, ready (its gains read from the database)."""
    settings = replica_settings(tmp_path, "rb", url, mode="client", endpoint=router.zenoh.endpoint)
    rb = ServiceProcess(settings, tmp_path / "rb.log")
    try:
        rb.start().wait_ready()
        yield rb
    finally:
        rb.close()


def served(replicas: dict[str, Any]) -> dict[str, set[str]]:
    """The buckets each replica says it serves (GET /health)."""
    return {name: set(srv.get("/health").json()["buckets"]) for name, srv in replicas.items()}


def halves(replicas: dict[str, Any]) -> dict[str, set[str]] | None:
    """Two replicas serving 8 buckets each, every bucket once; else None."""
    shares = served(replicas)
    ok = sorted(len(s) for s in shares.values()) == [8, 8] and set().union(*shares.values()) == set(all_buckets())
    return shares if ok else None


def vehicles_in(buckets: set[str]) -> int:
    return sum(1 for v in VEHICLES if bucket_of(v) in buckets)


class Announcements:
    """Every replica's ownership announcements, as a Zenoh client on loopback receives them."""

    def __init__(self, endpoint: str) -> None:
        self.session = open_session("client", endpoint)
        self._subscriber = self.session.declare_subscriber(ownership_selector(), zenoh.handlers.FifoChannel(1024))
        self.received: list[OwnershipChange] = []

    def poll(self) -> list[OwnershipChange]:
        while (sample := self._subscriber.try_recv()) is not None:
            self.received.append(OwnershipChange.decode(sample.payload.to_bytes()))
        return self.received

    def close(self) -> None:
        self._subscriber.undeclare()
        self.session.close()  # type: ignore[no-untyped-call]


class FleetStream:
    """A replica's fleet stream (GET /ui/stream?view=fleet) read in a thread: every (event, data) pair as it comes,
    until the server ends the stream when it stops."""

    def __init__(self, url: str) -> None:
        self.events: list[tuple[str, Any]] = []
        self._thread = threading.Thread(target=self._read, args=(f"{url}/ui/stream?view=fleet",), daemon=True)
        self._thread.start()

    def _read(self, url: str) -> None:
        name = ""
        with httpx.stream("GET", url, timeout=httpx.Timeout(10.0, read=None)) as response:
            for line in response.iter_lines():
                if line.startswith("event: "):
                    name = line[7:]
                elif line.startswith("data: "):
                    self.events.append((name, json.loads(line[6:])))

    def ownership(self) -> list[dict[str, Any]]:
        """The stream's ownership frames."""
        return [data for name, data in self.events if name == "ownership"]

    def pushed(self) -> list[dict[str, Any]]:
        """The changes pushed after the first frame, oldest first."""
        return [change for frame in self.ownership()[1:] for change in frame["changes"]]


def summed(changes: list[OwnershipChange], replica: str) -> tuple[set[str], set[str], int]:
    """A replica's gained and lost buckets and the vehicles moved, over ``changes``."""
    mine = [c for c in changes if c.replica == replica]
    return {b for c in mine for b in c.gained}, {b for c in mine for b in c.lost}, sum(c.vehicles for c in mine)


def in_time_order(changes: list[OwnershipChange] | list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Announcements as JSON, in the order they were made (two replicas' may arrive in either order)."""
    documents = [c.model_dump(mode="json") if isinstance(c, OwnershipChange) else c for c in changes]
    return sorted(documents, key=lambda c: (c["t_ns"], c["replica"]))


def test_ownership_changes_go_out_on_zenoh_and_into_the_fleet_stream_of_every_replica(tmp_path, postgres_url):
    settings = replica_settings(tmp_path, "ra", postgres_url)
    with dashboard_server(settings) as ra, steady_fleet(settings.zenoh.endpoint, VEHICLES):
        wait_for(lambda: len(ra.get("/vehicles").json()) == len(VEHICLES), what="every vehicle served by ra")
        stream = FleetStream(ra.url)
        # ra took every bucket as it started: a fleet stream opened since gets that change with its first frames
        (first,) = wait_for(stream.ownership, what="the fleet stream's first ownership frame")
        assert first["full"] and [(c["replica"], c["gained"], c["lost"]) for c in first["changes"]] == [
            ("ra", all_buckets(), [])
        ]
        announcements = Announcements(settings.zenoh.endpoint)
        try:
            with joining_replica(tmp_path, postgres_url, settings) as rb:
                shares = wait_for(lambda: halves({"ra": ra, "rb": rb}), what="ra and rb serving 8 buckets each")
                moved = shares["rb"]
                # ra announced what it handed over, rb what it took (in one change or a few)
                wait_for(lambda: summed(announcements.poll(), "rb")[0] == moved, what="rb's announcements")
                assert summed(announcements.received, "ra") == (set(), moved, vehicles_in(moved))
                assert summed(announcements.received, "rb") == (moved, set(), vehicles_in(moved))
                last = {c.replica: c for c in announcements.received}
                assert set(last["ra"].buckets) == shares["ra"] and set(last["rb"].buckets) == moved
                # ra's fleet stream got both replicas' announcements, rb's through Zenoh
                joined = len(announcements.received)
                wait_for(lambda: len(stream.pushed()) == joined, what="the announcements in ra's fleet stream")
                assert in_time_order(stream.pushed()) == in_time_order(announcements.received)
                rb.kill()  # its session ends, and with it its locks: ra takes its buckets back
                wait_for(lambda: served({"ra": ra})["ra"] == set(all_buckets()), what="ra serving every bucket again")
                wait_for(lambda: summed(announcements.poll(), "ra")[0] == moved, what="ra's takeover announcement")
            takeover = announcements.received[joined:]
            assert {c.replica for c in takeover} == {"ra"} and takeover[-1].buckets == all_buckets()
            assert summed(takeover, "ra") == (moved, set(), vehicles_in(moved))
            wait_for(lambda: len(stream.pushed()) == len(announcements.received), what="the takeover in the stream")
            assert in_time_order(stream.pushed()) == in_time_order(announcements.received)
        finally:
            announcements.close()


def listed_buckets(items: Any) -> set[str]:
    """The buckets the fleet view's ownership ``items`` name."""
    return {b for text in items.evaluate_all("es => es.map(e => e.dataset.buckets)") for b in text.split()}


@pytest.mark.browser
def test_the_fleet_view_lists_the_ownership_changes_newest_first(tmp_path, postgres_url, chromium, page, output_dir):
    settings = replica_settings(tmp_path, "ra", postgres_url)
    with dashboard_server(settings) as ra:
        page.goto(ra.url + "/")
        items = page.locator("#ownership-list .ownership")
        expect(page.locator("#ownership-box")).to_be_visible(timeout=UI_TIMEOUT_MS)
        expect(items).to_have_count(1)
        expect(items.first).to_have_attribute("data-replica", "ra")
        expect(items.first).to_have_attribute("data-change", "gained")
        expect(items.first).to_contain_text("Replica ra (this replica) took b00–b0f")
        expect(items.first).to_contain_text("16 buckets, 0 vehicles · it serves 16 buckets now")
        with joining_replica(tmp_path, postgres_url, settings) as rb:
            shares = wait_for(lambda: halves({"ra": ra, "rb": rb}), what="ra and rb serving 8 buckets each")
            taken = page.locator('#ownership-list .ownership[data-replica="rb"]')
            wait_for(lambda: listed_buckets(taken) == shares["rb"], UI_TIMEOUT_MS / 1000, "rb's buckets listed")
            expect(items.first).to_have_attribute("data-replica", "rb")  # the newest first
            expect(items.first).to_contain_text("Replica rb took")
            expect(taken.first).to_have_attribute("data-change", "gained")
            handed = page.locator('#ownership-list .ownership[data-replica="ra"][data-change="lost"]')
            expect(handed.first).to_contain_text("Replica ra (this replica) handed over")
            expect(items.last).to_have_attribute("data-change", "gained")  # ra's start, the oldest
            page.screenshot(path=str(output_dir / "fleet-ownership.png"), full_page=True)
