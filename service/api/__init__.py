"""The REST API: routers per resource and their dependencies.

Every handler is ``async def``: it runs on the event loop that owns the
fleet, between two ingest ticks, so it reads and changes the fleet state
without locks (FastAPI would run a plain ``def`` handler in a thread pool).
"""

from __future__ import annotations

from fastapi import APIRouter, Depends, FastAPI, Request, status
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from service.api.deps import require_read
from service.api.limits import RequestGate, document_413, validation_error
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


def install_error_handlers(app: FastAPI, settings: Settings) -> None:
    """HTTP answers of the service's own errors: a write the database does not accept is 503 with the reason; a
    body over the limit 413 and a change without the token 401, both before the body is read; a 422 repeats no
    long input."""
    app.add_exception_handler(StorageUnavailable, _storage_unavailable)
    app.add_exception_handler(RequestValidationError, validation_error)
    app.add_middleware(RequestGate, http=settings.http)
    document_413(app, settings.http)
