"""The REST API: routers per resource and their dependencies."""

from __future__ import annotations

from fastapi import APIRouter, Depends

from service.api.deps import require_read
from service.api.routes import alarms, health, jobs, profiles, vehicles
from service.settings import Settings


def build_router(settings: Settings) -> APIRouter:
    router = APIRouter()
    router.include_router(health.router)
    reads = [Depends(require_read)]
    for module in (vehicles, alarms, profiles, jobs):
        router.include_router(module.router, dependencies=reads)
    return router
