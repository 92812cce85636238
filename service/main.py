"""The FastAPI application of one replica: the REST API, the web dashboard and the lifespan that starts and stops
the :class:`~service.app.Service`.

The one module that wires the service and its API together: service.api imports service.app (the running
service its routes read), this module imports both, and nothing imports it but the entry points
(`agv-fe serve`, the tests), so every import runs one way.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI

from service.api import build_router, install_error_handlers
from service.api.routes.apidocs import install_api_docs
from service.app import Service
from service.settings import Settings


def create_app(settings: Settings) -> FastAPI:
    """The FastAPI application; the lifespan starts and stops the :class:`Service`."""

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        service = Service(settings)
        service.on_fatal = getattr(app.state, "on_fatal", None)
        app.state.service = service
        try:
            await service.start()
            yield
        finally:
            await service.stop()

    app = FastAPI(
        title="AGV fault estimator",
        version="0.1.0",
        summary="Real-time actuator fault estimation for a fleet of ground vehicles, with certified observers.",
        description=(
            "Measurements arrive over Zenoh (see docs/protocol.md); this API reports vehicles, estimates and alarms, "
            "and manages vehicle profiles and their certified observer gains. Mutating endpoints need "
            "`Authorization: Bearer TOKEN`."
        ),
        lifespan=lifespan,
        # /docs comes from the package (service/api/routes/apidocs.py), not a CDN; /redoc would need one
        docs_url=None,
        redoc_url=None,
        swagger_ui_oauth2_redirect_url=None,
    )
    app.include_router(build_router(settings))
    install_api_docs(app)
    install_error_handlers(app, settings)
    if settings.dashboard.enabled:
        from service.api.routes.ui import install_dashboard

        install_dashboard(app, settings.auth.open_reads)
    return app
