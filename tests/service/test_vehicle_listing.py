"""GET /vehicles' pages (service.fleet.listing): paged by id with a profile and a level filter, the vehicles no
replica serves merged in, against the whole fleet's statuses filtered and sorted at once."""

from __future__ import annotations

import pytest

from service.fleet.listing import LEVEL_FILTER_ROUND, vehicle_page
from tests.service.test_fleet_engine import make_engine

#: more vehicles than one round of the level filter writes
FLEET = 2 * LEVEL_FILTER_ROUND + 100


@pytest.fixture
def engine(fast_gains):
    engine = make_engine(fast_gains)
    engine.add_profile("other", engine.banks["default"].spec)
    engine.activate("other", fast_gains)
    for k in range(FLEET):  # registered out of id order, a third of them STALE (liveliness token lost)
        vehicle_id = f"v{(k * 7919) % FLEET:04d}"
        engine.register(vehicle_id, "other" if k % 5 == 0 else "default")
        if k % 3 == 0:
            engine.liveliness(vehicle_id, alive=False)
    return engine


def _unserved(ids: list[str]) -> list[dict]:
    return [{"id": i, "profile": "default", "level": "STALE", "served": False} for i in ids]


def _expected(engine, unserved, profile, level) -> list[tuple[str, bool]]:
    rows = [*engine.vehicle_statuses(list(engine.vehicles.values())), *unserved]
    return sorted(
        (r["id"], r.get("served", True))
        for r in rows
        if (profile is None or r["profile"] == profile) and (level is None or r["level"] == level)
    )


@pytest.mark.parametrize("profile", [None, "other"])
@pytest.mark.parametrize("level", [None, "STALE", "OK"])
@pytest.mark.parametrize("limit", [1, 97, LEVEL_FILTER_ROUND + 1, None])
def test_the_pages_from_after_to_after_are_the_filtered_fleet_in_id_order(engine, profile, level, limit):
    unserved = _unserved(["a-first", "v0500x", "zz-last"])
    expected = _expected(engine, unserved, profile, level)
    assert _expected(engine, [], None, "OK") and _expected(engine, [], None, "STALE")  # both levels are there
    seen: list[tuple[str, bool]] = []
    after = None
    for _ in range(len(expected) + 2):
        page = vehicle_page(engine, unserved, profile=profile, level=level, after=after, limit=limit)
        assert limit is None or len(page.rows) <= limit
        seen += [(r["id"], r["served"]) for r in page.rows]
        if not (limit is not None and len(page.rows) == limit and page.more):
            break
        after = page.rows[-1]["id"]
    assert seen == expected


def test_a_page_says_there_is_more_only_when_there_is(engine):
    ids = sorted(engine.vehicles)
    assert vehicle_page(engine, [], limit=FLEET).more is False
    assert vehicle_page(engine, [], limit=FLEET - 1).more is True
    assert vehicle_page(engine, _unserved(["zz"]), limit=FLEET).more is True
    last = vehicle_page(engine, [], after=ids[-2], limit=1)
    assert [r["id"] for r in last.rows] == [ids[-1]] and last.more is False
