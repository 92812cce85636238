"""An open page survives a restart of the service: it says it is reconnecting, then shows the fleet again."""

from __future__ import annotations

import pytest
from playwright.sync_api import expect

from tests.service.helpers import FAST_DESIGN, constant_measurement, make_settings, probe, wait_for
from tests.web.helpers import DashboardServer

pytestmark = [pytest.mark.browser, pytest.mark.network]

UI_TIMEOUT_MS = 30_000


def test_the_page_reconnects_by_itself_after_the_service_restarts(tmp_path, page, page_problems):
    page_problems.allow(r"ERR_CONNECTION_REFUSED")  # its attempts while the service is down
    settings = make_settings(tmp_path, {"default": {"design": FAST_DESIGN}})
    first = DashboardServer(settings).start()
    try:
        first.wait_ready()
        with probe(settings.zenoh.endpoint) as zprobe:
            for k in range(5):
                for vehicle in ("agv-a", "agv-b"):
                    zprobe.put(constant_measurement(vehicle, k))
            wait_for(lambda: len(first.get("/vehicles").json()) == 2, what="two vehicles registered")
        page.goto(first.url + "/")
        expect(page.locator("#fleet-table")).to_have_attribute("data-total", "2", timeout=UI_TIMEOUT_MS)
    finally:
        first.stop()
    state = page.locator("#connection")
    expect(state).not_to_have_attribute("data-state", "live", timeout=UI_TIMEOUT_MS)
    expect(page.locator("#fleet-table")).to_have_attribute("data-total", "2")  # the last known fleet stays shown
    second = DashboardServer(settings).start()  # same ports, same database
    try:
        second.wait_ready()
        expect(state).to_have_attribute("data-state", "live", timeout=UI_TIMEOUT_MS)
        expect(page.locator("#fleet-body .vrow")).to_have_count(2)
        expect(page.locator('#fleet-body .vrow[data-vehicle="agv-a"]')).to_have_attribute("data-level", "STALE")
    finally:
        second.stop()
