"""An open page copes with what a live service does: it restarts, and vehicles appear after the page is open."""

from __future__ import annotations

import pytest
from playwright.sync_api import expect

from tests.service.helpers import FAST_DESIGN, constant_measurement, make_settings, probe, wait_for
from tests.web.helpers import DashboardServer, dashboard_server

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


def test_a_vehicle_page_opened_before_the_vehicle_sends_anything_shows_it_once_it_does(tmp_path, page, page_problems):
    page_problems.allow(r"status of 404")  # its attempts while the vehicle is unknown
    settings = make_settings(tmp_path, {"default": {"design": FAST_DESIGN}})
    with dashboard_server(settings) as server, probe(settings.zenoh.endpoint) as zprobe:
        page.goto(server.url + "/#/vehicle/agv-late")
        missing = page.locator("#vehicle-missing")
        expect(missing).to_be_visible(timeout=UI_TIMEOUT_MS)
        expect(missing).to_contain_text("no vehicle 'agv-late'")
        for k in range(300):
            zprobe.put(constant_measurement("agv-late", k))
        wait_for(lambda: server.get("/vehicles/agv-late").status_code == 200, what="agv-late registered")
        expect(page.locator("#connection")).to_have_attribute("data-state", "live", timeout=UI_TIMEOUT_MS)
        expect(missing).to_be_hidden()
        expect(page.locator('figure[data-plot="tf"]')).to_have_attribute("data-estimates", "60")  # 3 s at 20 Hz
