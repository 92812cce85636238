"""Vehicles: status, latest estimate, estimate history, profile assignment."""

from __future__ import annotations

from typing import Annotated, Any

import orjson
from fastapi import APIRouter, HTTPException, Path, Query, Response, status

from service.api.deps import Operator, ServiceDep
from service.api.models import AlarmInfo, EstimateHistory, EstimateRow, VehicleAssignment, VehicleDetail, VehicleStatus
from service.app import Service
from service.fleet import UnknownProfile, UnknownVehicle, Vehicle
from service.protocol import VEHICLE_ID_PATTERN

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


@router.get("", response_model=list[VehicleStatus], summary="every vehicle of this replica with status and counters")
async def list_vehicles(
    service: ServiceDep,
    profile: Annotated[str | None, Query(description="only this profile")] = None,
    level: Annotated[str | None, Query(description="only this level: OK, WARN, FAULT, STALE")] = None,
) -> Response:
    engine = service.engine
    vehicles = sorted(engine.vehicles.values(), key=lambda v: v.id)
    rows = engine.vehicle_statuses([v for v in vehicles if profile is None or v.profile == profile])
    if level is not None:
        rows = [row for row in rows if row["level"] == level]
    # the documents as they are, by one orjson call: this handler runs on the event loop that runs ingest, and
    # a VehicleStatus per vehicle plus FastAPI's response validation and encoding took several times longer
    # (GET /vehicles with 1,000 vehicles: docs/benchmarks/soak.md)
    return Response(orjson.dumps(rows, option=orjson.OPT_SERIALIZE_NUMPY), media_type="application/json")


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
    rows = [EstimateRow(**row) for row in service.engine.estimate_history(vehicle, limit)]
    return EstimateHistory(vehicle=vehicle.id, gain_version=vehicle.bank.version, estimates=rows)


@router.put(
    "/{vehicle_id}",
    response_model=VehicleStatus,
    responses={401: {"description": "missing or invalid token"}, 404: {"description": "no such profile"}},
    summary="register a vehicle or move it to another profile",
)
async def assign_vehicle(
    service: ServiceDep, vehicle_id: VehicleId, body: VehicleAssignment, _operator: Operator
) -> VehicleStatus:
    try:
        vehicle = service.engine.register(vehicle_id, body.profile)
    except UnknownProfile as exc:
        raise HTTPException(status.HTTP_404_NOT_FOUND, detail=str(exc.args[0])) from exc
    service.db.put_vehicles([(vehicle.id, vehicle.profile, vehicle.registered_t_ns)])
    return VehicleStatus(**service.engine.vehicle_status(vehicle))
