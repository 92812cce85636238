"""The dashboard's effectiveness plot in headless Chromium: a profile running the loss-of-effectiveness stage,
one simulated vehicle losing drive-torque effectiveness (alpha 1 to 0.6 from 8 s) live at 100 Hz over Zenoh.
The vehicle view shows the alpha plot with its WARN and FAULT lines, alpha falling below them, and the alarm."""

from __future__ import annotations

import pytest
from playwright.sync_api import expect

from tests.service.helpers import make_settings, wait_for
from tests.synth.test_effectiveness import OPTIONS, torque_loss_scenario
from tests.web.helpers import dashboard_server, live_fleet
from tests.web.test_browser import UI_TIMEOUT_MS, plot_state

pytestmark = [pytest.mark.browser, pytest.mark.network]

PROFILE = {
    "design": {"design": "robust"},
    "effectiveness": OPTIONS.model_dump(mode="json"),
    "alarms": {"torque_warn_nm": 1000.0, "torque_fault_nm": 2000.0},
}


def test_the_vehicle_view_plots_alpha_and_shows_the_effectiveness_alarm(tmp_path, chromium, page, output_dir):
    settings = make_settings(tmp_path, {"loe": PROFILE}, ingest={"default_profile": "loe"})
    with dashboard_server(settings) as srv, live_fleet(settings.zenoh.endpoint, {"loe-1": torque_loss_scenario()}):
        wait_for(lambda: srv.get("/vehicles").json(), what="the vehicle registered")
        page.goto(srv.url + "/#/vehicle/loe-1")
        figure = page.locator('figure[data-plot="alpha"]')
        expect(figure).to_be_visible(timeout=UI_TIMEOUT_MS)
        expect(page.locator('#vehicle-facts [data-fact="effectiveness"] dd')).to_have_text(
            "WARN below 0.9 / FAULT below 0.75"
        )
        legend = figure.locator(".u-legend")
        for label in ("drive torque", "steering", "WARN", "FAULT"):
            expect(legend).to_contain_text(label)
        # alpha starts at 1 and falls below the FAULT line (0.75) once the loss has ramped far enough
        wait_for(
            lambda: (latest := plot_state(page, "alpha")["latest"]) not in (None, "", "–") and float(latest) < 0.75,
            60.0,
            "alpha below 0.75 in the plot",
        )
        alarm = page.locator('#vehicle-alarms .alarm[data-kind="torque_effectiveness"]')
        expect(alarm).to_have_count(1, timeout=UI_TIMEOUT_MS)
        expect(alarm).to_contain_text("Drive-torque effectiveness lost")
        expect(page.locator("#vehicle-level")).to_have_text("FAULT", timeout=UI_TIMEOUT_MS)
        # the alarm links the vehicle's estimates around it, from the estimate history, as CSV
        href = alarm.locator("a.around").get_attribute("href")
        assert href is not None and "format=csv" in href
        csv_text = page.request.get(srv.url + href).text()
        header, *rows = csv_text.splitlines()
        assert "torque_alpha" in header and len(rows) > 100
        page.screenshot(path=str(output_dir / "vehicle-effectiveness.png"), full_page=True)
