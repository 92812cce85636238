"""The REST API: routers per resource and their dependencies.

Every handler is ``async def``: it runs on the event loop that owns the
fleet, between two ingest ticks, so it reads and changes the fleet state
without locks (FastAPI would run a plain ``def`` handler in a thread pool).
"""

from __future__ import annotations

from fastapi import APIRouter, Depends, FastAPI, Request, status
from fastapi.responses import JSONResponse

from service.api.deps import require_read
from service.api.routes import alarms, health, jobs, profiles, vehicles
from service.settings import Settings
from service.storage_writer import StorageUnavailable


def build_router(settings: Settings) -> APIRouter:
    router = APIRouter()
    router.include_router(health.router)
    # open reads (the default) need no token: no dependency, so the OpenAPI document does not mark them as secured
    reads = [] if settings.auth.open_reads else [Depends(require_read)]
    for module in (vehicles, alarms, profiles, jobs):
        router.include_router(module.router, dependencies=reads)
    return router


async def _storage_unavailable(request: Request, exc: Exception) -> JSONResponse:
    return JSONResponse({"detail": str(exc)}, status_code=status.HTTP_503_SERVICE_UNAVAILABLE)


def install_error_handlers(app: FastAPI) -> None:
    """HTTP answers of the service's own errors: a write the database does not accept is 503 with the reason."""
    app.add_exception_handler(StorageUnavailable, _storage_unavailable)
