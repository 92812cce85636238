"""Vehicles: status, latest estimate, estimate history, profile assignment."""

from __future__ import annotations

from functools import partial
from typing import Annotated, Any
from urllib.parse import urlencode

import orjson
from fastapi import APIRouter, HTTPException, Path, Query, Request, Response, status

from service.api.deps import STORAGE_UNAVAILABLE, Operator, ServiceDep, profile_bank
from service.api.models import AlarmInfo, EstimateHistory, VehicleAssignment, VehicleDetail, VehicleStatus
from service.app import Service
from service.fleet import UnknownProfile, UnknownVehicle, Vehicle
from service.protocol import VEHICLE_ID_PATTERN, Level
from service.storage import Storage

router = APIRouter(prefix="/vehicles", tags=["vehicles"])

VehicleId = Annotated[str, Path(description="vehicle id", pattern=VEHICLE_ID_PATTERN.pattern)]
NOT_FOUND: dict[int | str, dict[str, Any]] = {
    404: {"description": "no such vehicle", "content": {"application/json": {"example": {"detail": "no vehicle 'x'"}}}}
}


def _vehicle(service: Service, vehicle_id: str) -> Vehicle:
    try:
        return service.engine.vehicle(vehicle_id)
    except UnknownVehicle as exc:
        raise HTTPException(status.HTTP_404_NOT_FOUND, detail=str(exc.args[0])) from exc


#: Statuses written per round while a level filter fills a page: a short page of a large fleet does not write
#: every vehicle's document.
LEVEL_FILTER_ROUND = 512
LIST_LIMIT_MAX = 100_000


@router.get(
    "",
    response_model=list[VehicleStatus],
    summary="every vehicle of this replica with status and counters, by id; paged with limit and after",
    responses={
        200: {
            "description": "the vehicles in id order. With `limit`, a full page has a `Link` header with "
            'rel="next": the same query from the page\'s last id on. With a `level` filter that next page '
            "may be empty.",
            "headers": {"Link": {"description": 'the next page: `</vehicles?after=ID&limit=N>; rel="next"`'}},
        },
        404: {
            "description": "no such profile",
            "content": {"application/json": {"example": {"detail": "no profile named 'x'; known: default"}}},
        },
    },
)
async def list_vehicles(
    service: ServiceDep,
    request: Request,
    profile: Annotated[str | None, Query(description="only this profile", examples=["default"])] = None,
    level: Annotated[Level | None, Query(description="only vehicles at this level", examples=["FAULT"])] = None,
    limit: Annotated[
        int | None, Query(ge=1, le=LIST_LIMIT_MAX, description="at most this many (default: all)", examples=[500])
    ] = None,
    after: Annotated[
        str | None,
        Query(
            description="only ids after this one (the last id of the previous page)",
            pattern=VEHICLE_ID_PATTERN.pattern,
            examples=["agv-0042"],
        ),
    ] = None,
) -> Response:
    engine = service.engine
    if profile is not None:
        profile_bank(service, profile)
    candidates = sorted(
        (
            v
            for v in engine.vehicles.values()
            if (profile is None or v.profile == profile) and (after is None or v.id > after)
        ),
        key=lambda v: v.id,
    )
    wanted = len(candidates) if limit is None else limit
    rows: list[dict[str, Any]] = []
    read = 0  # candidates whose status was written
    if level is None:
        rows = engine.vehicle_statuses(candidates[:wanted])
        read = len(rows)
    else:
        while len(rows) < wanted and read < len(candidates):
            chunk = candidates[read : read + max(LEVEL_FILTER_ROUND, wanted - len(rows))]
            for row in engine.vehicle_statuses(chunk):
                read += 1
                if row["level"] == level:
                    rows.append(row)
                    if len(rows) == wanted:
                        break
    headers = {}
    if limit is not None and len(rows) == limit and read < len(candidates):
        query = {k: v for k, v in request.query_params.items() if k != "after"}
        headers["Link"] = f'<{request.url.path}?{urlencode({**query, "after": rows[-1]["id"]})}>; rel="next"'
    # the documents as they are, by one orjson call: this handler runs on the event loop that runs ingest, and
    # a VehicleStatus per vehicle plus FastAPI's response validation and encoding took several times longer
    # (GET /vehicles with 1,000 vehicles: docs/benchmarks/soak.md)
    return Response(
        orjson.dumps(rows, option=orjson.OPT_SERIALIZE_NUMPY), media_type="application/json", headers=headers
    )


@router.get(
    "/{vehicle_id}", response_model=VehicleDetail, responses=NOT_FOUND, summary="status, latest estimate, alarms"
)
async def get_vehicle(service: ServiceDep, vehicle_id: VehicleId) -> VehicleDetail:
    engine = service.engine
    vehicle = _vehicle(service, vehicle_id)
    alarms = [AlarmInfo(**r.to_dict(), latched=True) for r in engine.alarms.for_vehicle(vehicle.id)]
    return VehicleDetail(
        **engine.vehicle_status(vehicle), latest_estimate=engine.latest_estimate(vehicle), alarms=alarms
    )


@router.get(
    "/{vehicle_id}/estimates",
    response_model=EstimateHistory,
    responses=NOT_FOUND,
    summary="recent estimates of every sample, oldest first",
)
async def get_estimates(
    service: ServiceDep,
    vehicle_id: VehicleId,
    limit: Annotated[int, Query(ge=1, le=100_000, description="at most this many (newest)")] = 100,
) -> EstimateHistory:
    vehicle = _vehicle(service, vehicle_id)
    rows = service.engine.estimate_history(vehicle, limit)
    return EstimateHistory(vehicle=vehicle.id, gain_version=vehicle.bank.version, estimates=rows)


@router.put(
    "/{vehicle_id}",
    response_model=VehicleStatus,
    responses={
        401: {"description": "missing or invalid token"},
        404: {"description": "no such profile"},
        **STORAGE_UNAVAILABLE,
    },
    summary="register a vehicle or move it to another profile",
)
async def assign_vehicle(
    service: ServiceDep, vehicle_id: VehicleId, body: VehicleAssignment, _operator: Operator
) -> VehicleStatus:
    service.require_storage()
    try:
        vehicle = service.engine.register(vehicle_id, body.profile, announced=True)
    except UnknownProfile as exc:
        raise HTTPException(status.HTTP_404_NOT_FOUND, detail=str(exc.args[0])) from exc
    rows = [(vehicle.id, vehicle.profile, vehicle.registered_t_ns)]
    service.store(f"vehicle {vehicle.id}", partial(Storage.put_vehicles, rows=rows))
    await service.stored(f"the registration of {vehicle.id!r}")
    return VehicleStatus(**service.engine.vehicle_status(vehicle))
