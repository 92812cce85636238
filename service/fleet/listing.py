"""A page of the fleet's vehicles as ``GET /vehicles`` lists them: filtered by profile and level, in id order,
paged by id, the vehicles no replica serves merged in.

The statuses are the engine's documents (:meth:`FleetEngine.vehicle_statuses`); a level filter writes them a round
at a time, so a short page of a large fleet does not write every vehicle's document.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from service.fleet.engine import FleetEngine
from service.fleet.vehicle import Vehicle

#: Statuses written per round while a level filter fills a page.
LEVEL_FILTER_ROUND = 512


@dataclass(frozen=True)
class VehiclePage:
    """One page of vehicle statuses."""

    #: the statuses in id order, ``served`` set on each
    rows: list[dict[str, Any]]
    #: vehicles matching the query come after the page's last one
    more: bool


def vehicle_page(
    engine: FleetEngine,
    unserved: Sequence[dict[str, Any]],
    *,
    profile: str | None = None,
    level: str | None = None,
    after: str | None = None,
    limit: int | None = None,
) -> VehiclePage:
    """The vehicles of ``profile`` (None: all) at ``level`` (None: any) with ids after ``after``, at most ``limit``
    (None: all), in id order: this replica's vehicles (``served`` true) and the ``unserved`` statuses of vehicles
    of buckets no replica holds (a shared database's replica died)."""
    candidates = sorted(
        (
            v
            for v in engine.vehicles.values()
            if (profile is None or v.profile == profile) and (after is None or v.id > after)
        ),
        key=lambda v: v.id,
    )
    rows, read = _served_rows(engine, candidates, level, len(candidates) if limit is None else limit)
    for row in rows:
        row["served"] = True
    others = [
        row
        for row in unserved
        if (profile is None or row["profile"] == profile)
        and (after is None or row["id"] > after)
        and (level is None or row["level"] == level)
    ]
    more = read < len(candidates)
    if others:
        merged = sorted(rows + others, key=lambda row: row["id"])
        cap = len(merged) if limit is None else limit
        rows, more = merged[:cap], more or len(merged) > cap
    return VehiclePage(rows, more)


def _served_rows(
    engine: FleetEngine, candidates: list[Vehicle], level: str | None, wanted: int
) -> tuple[list[dict[str, Any]], int]:
    """The statuses of the first ``wanted`` ``candidates`` at ``level``, and how many candidates were read."""
    if level is None:
        rows = engine.vehicle_statuses(candidates[:wanted])
        return rows, len(rows)
    rows = []
    read = 0
    while len(rows) < wanted and read < len(candidates):
        chunk = candidates[read : read + max(LEVEL_FILTER_ROUND, wanted - len(rows))]
        for row in engine.vehicle_statuses(chunk):
            read += 1
            if row["level"] == level:
                rows.append(row)
                if len(rows) == wanted:
                    break
    return rows, read
