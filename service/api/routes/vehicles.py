"""Vehicles: status, latest estimate, estimate history, profile assignment."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator
from datetime import UTC, datetime
from functools import partial
from typing import Annotated, Any, Literal
from urllib.parse import urlencode

import orjson
import pyarrow as pa
import pyarrow.csv as pa_csv
import pyarrow.parquet as pq
from fastapi import APIRouter, HTTPException, Path, Query, Request, Response, status
from fastapi.responses import StreamingResponse

from agv_protocol.wire import VEHICLE_ID_PATTERN, EstimateRow, Level
from service.api.deps import STORAGE_UNAVAILABLE, Operator, ServiceDep, profile_bank
from service.api.models import (
    AlarmInfo,
    EstimateHistory,
    PayloadReport,
    VehicleAssignment,
    VehicleDetail,
    VehicleStatus,
)
from service.app import Service
from service.fleet import UnknownProfile, UnknownVehicle, Vehicle
from service.fleet.listing import vehicle_page
from service.history import rows_table, table_rows
from service.history_process import HistoryUnavailable
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


LIST_LIMIT_MAX = 100_000


@router.get(
    "",
    response_model=list[VehicleStatus],
    summary="every vehicle of this replica with status and counters, and every vehicle no replica serves (served "
    "false), by id; paged with limit and after",
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
    if profile is not None:
        profile_bank(service, profile)
    page = vehicle_page(
        service.engine, service.ownership.statuses(), profile=profile, level=level, after=after, limit=limit
    )
    rows = page.rows
    headers = {}
    if limit is not None and len(rows) == limit and page.more:
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


#: Media types of GET /vehicles/{id}/estimates besides JSON.
CSV_TYPE = "text/csv"
PARQUET_TYPE = "application/vnd.apache.parquet"
#: Rows of a JSON answer from the history at most (CSV and Parquet answer the whole range).
HISTORY_JSON_MAX = 100_000


@router.get(
    "/{vehicle_id}/estimates",
    response_model=EstimateHistory,
    responses={
        **NOT_FOUND,
        200: {
            "description": "JSON by default; with `Accept: text/csv` CSV (streamed, one row per estimate, a header "
            "line of the record's fields), with `Accept: application/vnd.apache.parquet` a Parquet file",
            "content": {CSV_TYPE: {"schema": {"type": "string"}}, PARQUET_TYPE: {"schema": {"type": "string"}}},
        },
        409: {"description": "start/end asked but this replica keeps no estimate history (setting history.enabled)"},
        503: {"description": "the estimate history's own process (setting history.writer) cannot answer"},
    },
    summary="a vehicle's estimates: the newest in memory, or every one in a time range from the history",
)
async def get_estimates(
    service: ServiceDep,
    request: Request,
    vehicle_id: VehicleId,
    limit: Annotated[int | None, Query(ge=1, le=HISTORY_JSON_MAX, description="at most this many")] = None,
    start: Annotated[
        datetime | None, Query(description="from this time on (ISO 8601 or seconds since the epoch; vehicle clock)")
    ] = None,
    end: Annotated[datetime | None, Query(description="before this time (default: now)")] = None,
    output: Annotated[
        Literal["json", "csv", "parquet"] | None,
        Query(
            alias="format",
            description="instead of the Accept header (a download link): csv or parquet as an attachment",
        ),
    ] = None,
) -> Response | EstimateHistory:
    """Without start/end: the newest ``limit`` (100) of the last ``ingest.history_samples`` kept in memory. With
    them: every estimate with start <= t < end from the estimate history (service/history.py), oldest first;
    JSON answers at most ``limit`` (100,000) and a ``Link: rel="next"`` header when there are more."""
    vehicle = _vehicle(service, vehicle_id)
    accept = {"json": "application/json", "csv": CSV_TYPE, "parquet": PARQUET_TYPE}.get(
        output or "", request.headers.get("accept", "")
    )
    if start is None and end is None:
        rows = service.engine.estimate_history(vehicle, limit or 100)
        if CSV_TYPE in accept or PARQUET_TYPE in accept:
            return _export(rows_table(rows, vehicle.id), accept)
        return EstimateHistory(vehicle=vehicle.id, gain_version=vehicle.bank.version, estimates=rows)
    if service.history is None:
        raise HTTPException(status.HTTP_409_CONFLICT, detail="this replica keeps no estimate history (history.enabled)")
    start_ns = 0 if start is None else _epoch_ns(start)
    end_ns = time.time_ns() + 1 if end is None else _epoch_ns(end)
    if end_ns <= start_ns:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, detail="end must be after start")
    wanted = None if (CSV_TYPE in accept or PARQUET_TYPE in accept) else (limit or HISTORY_JSON_MAX)
    try:
        table = await asyncio.to_thread(
            service.history.read, vehicle.id, start_ns, end_ns, None if wanted is None else wanted + 1
        )
    except HistoryUnavailable as exc:  # the history's own process (history.writer='process') cannot answer
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, detail=str(exc)) from exc
    if wanted is None:
        answer = _export(table, accept)
        if output is not None:
            suffix = "csv" if output == "csv" else "parquet"
            answer.headers["Content-Disposition"] = f'attachment; filename="{vehicle.id}-estimates.{suffix}"'
        return answer
    headers = {}
    if table.num_rows > wanted:
        table = table.slice(0, wanted)
        last = int(table["t_ns"][wanted - 1].as_py())
        query = {**request.query_params, "start": f"{(last + 1) / 1e9:.9f}"}
        headers["Link"] = f'<{request.url.path}?{urlencode(query)}>; rel="next"'
    rows = [EstimateRow.model_validate(r) for r in table_rows(table)]
    body = EstimateHistory(vehicle=vehicle.id, gain_version=vehicle.bank.version, estimates=rows)
    return Response(body.model_dump_json(exclude_none=True), media_type="application/json", headers=headers)


def _epoch_ns(moment: datetime) -> int:
    """Nanoseconds since the epoch of an aware or naive (UTC) datetime."""
    aware = moment if moment.tzinfo is not None else moment.replace(tzinfo=UTC)
    return round(aware.timestamp() * 1e6) * 1000


def _export(table: pa.Table, accept: str) -> Response:
    """The table as Parquet, or as CSV streamed 10,000 rows at a time (plain columns; a column no row has, such as
    alpha for a profile without the effectiveness stage, left out), as ``accept`` asks."""
    if PARQUET_TYPE in accept:
        sink = pa.BufferOutputStream()
        pq.write_table(table, sink, compression="zstd")
        return Response(sink.getvalue().to_pybytes(), media_type=PARQUET_TYPE)
    keep = [n for n in table.column_names if table.num_rows == 0 or table[n].null_count < table.num_rows]
    plain = table.select(keep)
    plain = plain.cast(pa.schema([pa.field(f.name, _plain_type(f.type)) for f in plain.schema]))

    def chunks() -> Iterator[bytes]:
        batches = plain.to_batches(max_chunksize=10_000) or [pa.RecordBatch.from_pylist([], schema=plain.schema)]
        for i, batch in enumerate(batches):
            sink = pa.BufferOutputStream()
            pa_csv.write_csv(batch, sink, pa_csv.WriteOptions(include_header=i == 0))
            yield sink.getvalue().to_pybytes()

    return StreamingResponse(chunks(), media_type=CSV_TYPE)


def _plain_type(kind: pa.DataType) -> pa.DataType:
    return kind.value_type if pa.types.is_dictionary(kind) else kind


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


@router.put(
    "/{vehicle_id}/payload",
    response_model=VehicleStatus,
    responses={
        401: {"description": "missing or invalid token"},
        404: {"description": "no such vehicle"},
        422: {"description": "a payload that is negative, not finite, or more than the vehicle's mass"},
    },
    summary="report what the vehicle carries now: its model's drive torque follows the load (docs/math.md 12.5)",
)
async def put_payload(
    service: ServiceDep, vehicle_id: VehicleId, body: PayloadReport, _operator: Operator
) -> VehicleStatus:
    """A load is more mass to accelerate: without it, the observer reads every acceleration of a loaded vehicle as
    a torque fault. From the next sample on, the vehicle's observer takes the torque that moves the profile's
    vehicle as the loaded one moves, and reports the torque fault at the vehicle's scale. Stored: after a restart
    of the service, and on the replica that takes the vehicle over, it applies again."""
    service.require_storage()
    try:
        vehicle = service.engine.set_payload(vehicle_id, body.payload_kg)
    except UnknownVehicle as exc:
        raise HTTPException(status.HTTP_404_NOT_FOUND, detail=str(exc.args[0])) from exc
    except ValueError as exc:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, detail=str(exc)) from exc
    write = partial(Storage.put_payload, vehicle_id=vehicle.id, payload_kg=vehicle.payload_kg, t_ns=time.time_ns())
    service.store(f"the payload of {vehicle.id}", write)
    await service.stored(f"the payload of {vehicle.id!r}")
    return VehicleStatus(**service.engine.vehicle_status(vehicle))
