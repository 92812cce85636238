"""The API's interactive documentation at /docs: Swagger UI served by the service itself.

FastAPI's own /docs loads Swagger UI from a CDN, which is a blank page on a
network without internet. Here the page, its start script and Swagger UI 5
(vendored unmodified under service/web/static/vendor/swagger-ui, with its
licence and checksum) all come from the service, under a content security
policy that allows no other origin. /redoc is not served (it would need a
CDN too); /openapi.json is FastAPI's.
"""

from __future__ import annotations

from fastapi import FastAPI
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

from service.api.routes.ui import STATIC_DIR

DOCS_DIR = STATIC_DIR / "apidocs"
SWAGGER_UI_DIR = STATIC_DIR / "vendor" / "swagger-ui"
#: Only this service's files; Swagger UI sets inline styles and shows data: images.
CONTENT_SECURITY_POLICY = (
    "default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data:; "
    "connect-src 'self'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'"
)
PAGE_HEADERS = {
    "Content-Security-Policy": CONTENT_SECURITY_POLICY,
    "Cache-Control": "no-cache",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
}


def install_api_docs(app: FastAPI) -> None:
    """Serve /docs (the page), /docs/page (its start script) and /docs/static (Swagger UI)."""

    @app.get("/docs", include_in_schema=False)
    async def docs() -> FileResponse:
        return FileResponse(DOCS_DIR / "index.html", headers=PAGE_HEADERS)

    app.mount("/docs/page", StaticFiles(directory=DOCS_DIR), name="api-docs-page")
    app.mount("/docs/static", StaticFiles(directory=SWAGGER_UI_DIR), name="api-docs-static")
