"""Alarms: list, detail with history, acknowledgement."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Body, HTTPException, Query, status

from service.api.deps import STORAGE_UNAVAILABLE, Operator, ServiceDep
from service.api.models import Acknowledgement, AlarmDetail, AlarmInfo
from service.fleet import UnknownAlarm

router = APIRouter(prefix="/alarms", tags=["alarms"])


def _info(record: dict[str, object]) -> AlarmInfo:
    latched = not (record["state"] == "cleared" and record["acknowledged"])
    return AlarmInfo.model_validate({**record, "latched": latched})


@router.get("", response_model=list[AlarmInfo], summary="latched alarms (default) or the recent history")
async def list_alarms(
    service: ServiceDep,
    scope: Annotated[
        Literal["latched", "all"], Query(description="'latched': not yet cleared and acknowledged")
    ] = "latched",
    vehicle: Annotated[str | None, Query(description="only this vehicle")] = None,
    limit: Annotated[int, Query(ge=1, le=10_000)] = 500,
) -> list[AlarmInfo]:
    if scope == "latched":
        records = [r for r in service.engine.alarms.latched() if vehicle is None or r.vehicle == vehicle]
        records.sort(key=lambda r: r.updated_t_ns, reverse=True)
        return [AlarmInfo(**r.to_dict(), latched=True) for r in records[:limit]]
    return [_info(r) for r in service.db.alarms(vehicle, limit)]


@router.get(
    "/{alarm_id}",
    response_model=AlarmDetail,
    responses={404: {"description": "no such alarm"}},
    summary="one alarm and its events",
)
async def get_alarm(service: ServiceDep, alarm_id: str) -> AlarmDetail:
    live = service.engine.alarms.get(alarm_id)
    record = live.to_dict() if live is not None else service.db.alarm(alarm_id)
    if record is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, detail=f"no alarm {alarm_id!r}")
    info = _info(record)
    return AlarmDetail(**info.model_dump(), events=service.db.alarm_events(alarm_id))


@router.post(
    "/{alarm_id}/ack",
    response_model=AlarmInfo,
    responses={
        401: {"description": "missing or invalid token"},
        404: {"description": "no latched alarm with this id"},
        **STORAGE_UNAVAILABLE,
    },
    summary="acknowledge a latched alarm (stored before the answer)",
)
async def acknowledge(
    service: ServiceDep,
    alarm_id: str,
    _operator: Operator,
    body: Annotated[Acknowledgement | None, Body()] = None,
) -> AlarmInfo:
    service.require_storage()
    try:
        change = service.engine.acknowledge(alarm_id, body.by if body else None)
    except UnknownAlarm as exc:
        closed = service.db.alarm(alarm_id)
        if closed is not None:
            return _info(closed)  # already cleared and acknowledged: idempotent
        raise HTTPException(status.HTTP_404_NOT_FOUND, detail=f"no latched alarm {alarm_id!r}") from exc
    service.commit_alarms([change])
    await service.stored(f"the acknowledgement of {alarm_id!r}")
    return _info(change.record.to_dict())
