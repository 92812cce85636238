"""Looking back around an alarm in headless Chromium: one simulated vehicle with an 80 N m torque bias streams live
at 100 Hz over Zenoh into the real service until its torque alarm latches; the vehicle view's "Look back" on the
alarm plots every estimate of the 60 s centred on the alarm from the estimate history
(GET /vehicles/{id}/estimates?start=&end=), then "Back to live" brings the live plots back."""

from __future__ import annotations

import re
import time
from typing import Any

import pytest
from playwright.sync_api import expect

from tests.service.helpers import FAST_DESIGN, make_settings, wait_for
from tests.web.helpers import cruise, dashboard_server, live_fleet, torque_bias
from tests.web.test_browser import UI_TIMEOUT_MS

pytestmark = [pytest.mark.browser, pytest.mark.network]

ALARMS = {"torque_warn_nm": 30.0, "torque_fault_nm": 60.0, "warmup_s": 1.0, "raise_after_s": 0.3}
VEHICLE = "agv-torque"
#: The look-back spans the live plots' span (dashboard.history_s, 60 s), centred on the alarm [s].
HALF_SPAN_S = 30.0
#: Plots that show estimates only, and the one hidden for a profile without the effectiveness stage.
ESTIMATE_PLOTS = ("vx", "r", "vy", "tf", "sf")


def figure(page: Any, key: str) -> Any:
    return page.locator(f'figure[data-plot="{key}"]')


def number(page: Any, key: str, attribute: str) -> float:
    return float(figure(page, key).get_attribute(attribute) or "nan")


def test_look_back_plots_the_estimate_history_around_an_alarm_then_returns_to_live(
    tmp_path, chromium, page, output_dir
):
    settings = make_settings(tmp_path, {"default": {"design": FAST_DESIGN, "alarms": ALARMS}})
    with (
        dashboard_server(settings) as srv,
        live_fleet(settings.zenoh.endpoint, {VEHICLE: cruise("torque-bias", torque_bias(80.0))}),
    ):
        alarm = wait_for(
            lambda: next((a for a in srv.get("/alarms").json() if a["kind"] == "torque_fault"), None),
            what="the torque alarm to latch",
        )
        alarm_s = alarm["raised_t_ns"] / 1e9
        page.goto(f"{srv.url}/#/vehicle/{VEHICLE}")
        expect(page.locator("#plots")).to_have_attribute("data-mode", "live")
        wait_for(lambda: number(page, "tf", "data-truth") > 0, UI_TIMEOUT_MS / 1000, "the live plot with ground truth")
        # every estimate of the look-back is in the history once its end has passed: the vehicle streams on
        time.sleep(max(0.0, alarm_s + HALF_SPAN_S + 1.0 - time.time()))
        after = {"start": alarm_s + HALF_SPAN_S, "end": alarm_s + HALF_SPAN_S + 60.0}  # a loaded service lags
        wait_for(lambda: srv.get(f"/vehicles/{VEHICLE}/estimates", params=after).json()["estimates"],
                 what="an estimate after the look-back's end in the history")  # fmt: skip
        look_back = page.locator(f'#vehicle-alarms .alarm[data-alarm-id="{alarm["id"]}"]').get_by_role(
            "button", name=re.compile("Look back")
        )
        with page.expect_response(lambda r: f"/vehicles/{VEHICLE}/estimates?" in r.url) as answered:
            look_back.click()
        response = answered.value
        assert response.status == 200 and response.request.headers.get("accept") == "application/json"
        banner = page.locator("#vehicle-lookback")
        expect(banner).to_have_attribute("data-state", "shown", timeout=UI_TIMEOUT_MS)
        expect(page.locator("#plots")).to_have_attribute("data-mode", "history")
        expect(banner).to_contain_text("Looking back")
        start, end = banner.get_attribute("data-start"), banner.get_attribute("data-end")
        assert start is not None and end is not None
        assert float(start) == pytest.approx(alarm_s - HALF_SPAN_S, abs=1e-3)
        assert float(end) == pytest.approx(alarm_s + HALF_SPAN_S, abs=1e-3)
        # the page asked for that range, and plots exactly what the history answers for it
        rows = response.json()["estimates"]
        history = srv.get(f"/vehicles/{VEHICLE}/estimates", params={"start": start, "end": end}).json()
        assert rows == history["estimates"]
        assert len(rows) > 25 * 100  # the fleet started a few seconds before the alarm: about 33 s at 100 Hz
        assert banner.get_attribute("data-count") == str(len(rows))
        for key in ESTIMATE_PLOTS:
            assert figure(page, key).get_attribute("data-points") == str(len(rows)), key
            assert figure(page, key).get_attribute("data-truth") == "0", key
            assert number(page, key, "data-first-t") == pytest.approx(rows[0]["t_ns"] / 1e9, abs=1e-6)
            assert number(page, key, "data-last-t") == pytest.approx(rows[-1]["t_ns"] / 1e9, abs=1e-6)
        # its x range is the look-back's span, which covers the alarm
        assert number(page, "tf", "data-x-min") == pytest.approx(float(start))
        assert number(page, "tf", "data-x-max") == pytest.approx(float(end))
        assert float(start) < alarm_s < float(end)
        assert figure(page, "tf").get_attribute("data-latest") == f"{rows[-1]['torque_fault']:.1f}"
        assert abs(rows[0]["torque_fault"]) < 5.0 < 75.0 < rows[-1]["torque_fault"]  # the fault's onset is in view
        expect(figure(page, "alpha")).to_be_hidden()
        page.screenshot(path=str(output_dir / "vehicle-lookback.png"), full_page=True)
        # back to live: the live trace (20 points a second, with the ground truth) since the look-back's end
        page.get_by_role("button", name="Back to live").click()
        expect(banner).to_be_hidden()
        expect(page.locator("#plots")).to_have_attribute("data-mode", "live")
        assert number(page, "tf", "data-last-t") > float(end)
        assert number(page, "tf", "data-truth") > 0
        assert number(page, "tf", "data-x-max") > float(end)
        assert int(figure(page, "tf").get_attribute("data-points") or 0) != len(rows)
        last_t = number(page, "tf", "data-last-t")
        wait_for(lambda: number(page, "tf", "data-last-t") > last_t + 0.5, what="the live plot to move on")
