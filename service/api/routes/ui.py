"""The web dashboard: the page at /, its static files, its live stream, and the form data of a profile.

The page is plain HTML, CSS and JavaScript modules shipped in the package
(service/web/static), with uPlot vendored: nothing is fetched from another
origin. Live data comes from one server-sent-event stream per browser tab
(GET /ui/stream, see :mod:`service.web.hub`); everything else the page does
goes through the REST API, with the operator's bearer token for changes.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, FastAPI, HTTPException, Query, status
from fastapi.responses import FileResponse, StreamingResponse
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, Field

from agv_protocol.wire import VEHICLE_ID_PATTERN
from service.api.deps import ServiceDep, require_read
from service.api.routes.profiles import ProfileName
from service.fleet import UnknownVehicle
from service.web.hub import View
from synth.params import OperatingBounds, VehicleParams

STATIC_DIR = Path(__file__).resolve().parents[2] / "web" / "static"

#: The page loads only its own files; no inline script or style, no other origin.
CONTENT_SECURITY_POLICY = (
    "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data:; connect-src 'self'; "
    "base-uri 'none'; form-action 'self'; frame-ancestors 'none'"
)
PAGE_HEADERS = {
    "Content-Security-Policy": CONTENT_SECURITY_POLICY,
    "Cache-Control": "no-cache",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
}

page = APIRouter(include_in_schema=False)
router = APIRouter(prefix="/ui", tags=["dashboard"])


@page.get("/")
async def index() -> FileResponse:
    return FileResponse(STATIC_DIR / "index.html", headers=PAGE_HEADERS)


@router.get(
    "/stream",
    response_class=StreamingResponse,
    responses={
        200: {
            "content": {"text/event-stream": {}},
            "description": "hello, alarms, fleet, ownership, status and trace events",
        },
        404: {"description": "no such vehicle"},
    },
    summary="the dashboard's live stream (server-sent events) for one view",
)
async def stream(
    service: ServiceDep,
    view: Annotated[View, Query(description="fleet, vehicle or profiles")] = "fleet",
    vehicle: Annotated[
        str | None, Query(description="the vehicle of a vehicle view", pattern=VEHICLE_ID_PATTERN.pattern)
    ] = None,
) -> StreamingResponse:
    hub = service.dashboard
    try:
        client = hub.connect(view, vehicle)
    except UnknownVehicle as exc:
        raise HTTPException(status.HTTP_404_NOT_FOUND, detail=str(exc.args[0])) from exc

    async def frames() -> Any:
        try:
            async for frame in client.frames():
                yield frame
        finally:
            hub.disconnect(client)

    return StreamingResponse(
        frames(), media_type="text/event-stream", headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"}
    )


class FieldInfo(BaseModel):
    name: str
    description: str
    kind: Literal["number", "optional_number", "boolean"] = Field(
        "number", description="how the form edits it: a number, a number that may be left empty (null), a switch"
    )
    minimum: float | None = Field(None, description="inclusive lower limit")
    exclusive_minimum: float | None = None
    maximum: float | None = Field(None, description="inclusive upper limit")


class ProfileForm(BaseModel):
    """What the profile form needs: the spec as stored (only what was set) and as resolved, and the fields."""

    name: str
    stored: dict[str, Any] = Field(description="the spec as stored: fields left unset follow the defaults")
    resolved: dict[str, Any] = Field(description="the spec with every default filled in")
    fields: dict[str, list[FieldInfo]] = Field(description="editable fields of 'params' and 'bounds'")


def _fields(model: type[BaseModel]) -> list[FieldInfo]:
    properties: dict[str, dict[str, Any]] = model.model_json_schema()["properties"]
    return [_field(name, p) for name, p in properties.items()]


def _field(name: str, p: dict[str, Any]) -> FieldInfo:
    """One property of the JSON schema as a form field; an optional number's limits sit in its anyOf branch."""
    kind: Literal["number", "optional_number", "boolean"] = "number"
    limits = p
    if p.get("type") == "boolean":
        kind = "boolean"
    elif "anyOf" in p:
        kind = "optional_number"
        limits = next((branch for branch in p["anyOf"] if branch.get("type") == "number"), {})
    return FieldInfo(
        name=name,
        description=str(p.get("description", "")),
        kind=kind,
        minimum=limits.get("minimum"),
        exclusive_minimum=limits.get("exclusiveMinimum"),
        maximum=limits.get("maximum"),
    )


@router.get(
    "/profiles/{name}/form",
    response_model=ProfileForm,
    responses={404: {"description": "no such profile"}},
    summary="a profile's stored and resolved spec and its editable fields",
)
async def profile_form(service: ServiceDep, name: ProfileName) -> ProfileForm:
    bank = service.engine.banks.get(name)
    if bank is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, detail=f"no profile named {name!r}")
    return ProfileForm(
        name=name,
        stored=bank.spec.stored(),
        resolved=bank.spec.model_dump(mode="json"),
        fields={"params": _fields(VehicleParams), "bounds": _fields(OperatingBounds)},
    )


def install_dashboard(app: FastAPI, open_reads: bool = True) -> None:
    """Serve the dashboard: the page at /, static files at /ui/static, data routes under /ui (read access: open,
    or with the token when ``open_reads`` is false)."""
    app.include_router(page)
    app.include_router(router, dependencies=[] if open_reads else [Depends(require_read)])
    app.mount("/ui/static", StaticFiles(directory=STATIC_DIR), name="dashboard-static")
