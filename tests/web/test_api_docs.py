"""/docs works without internet: Swagger UI comes from the service, every operation is listed, nothing else is
fetched (headless Chromium with every request to another origin refused)."""

from __future__ import annotations

from typing import Any

from playwright.sync_api import expect

from tests.service.helpers import FAST_DESIGN, make_settings
from tests.web.helpers import dashboard_server


def test_the_api_docs_list_every_operation_with_the_network_off(tmp_path, browser_context: Any, page: Any) -> None:
    settings = make_settings(tmp_path, {"default": {"design": FAST_DESIGN}})
    with dashboard_server(settings) as srv:
        origin = f"http://127.0.0.1:{settings.http.port}"
        foreign: list[str] = []

        def only_this_service(route: Any) -> None:
            url = route.request.url
            if url.startswith(origin + "/"):
                route.continue_()
            else:  # the machine's "internet": anything that is not this service
                foreign.append(url)
                route.abort()

        browser_context.route("**/*", only_this_service)
        operations = [
            (method.upper(), path)
            for path, item in srv.get("/openapi.json").json()["paths"].items()
            for method in item
            if method in {"get", "put", "post", "delete", "patch"}
        ]
        assert len(operations) >= 19
        response = page.goto(f"{origin}/docs")
        assert response is not None and response.status == 200
        assert "default-src 'self'" in response.headers["content-security-policy"]
        blocks = page.locator(".opblock")
        expect(blocks).to_have_count(len(operations), timeout=30_000)
        shown = {
            (block.locator(".opblock-summary-method").inner_text().strip(), block.get_attribute("id") or "")
            for block in blocks.all()
        }
        assert {method for method, _ in shown} == {method for method, _ in operations}
        expect(page.locator(".opblock-summary-path").first).to_be_visible()
        assert foreign == [], foreign  # nothing came from, or went to, another origin
        # FastAPI's CDN page and ReDoc are not served
        assert srv.get("/redoc").status_code == 404
