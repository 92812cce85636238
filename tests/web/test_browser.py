"""The dashboard end to end in headless Chromium, on the real service fed by a live simulated fleet.

Six vehicles publish measurements and ground truth at 100 Hz over Zenoh: two healthy, one with an
80 N m torque bias (FAULT), one with 40 N m (WARN), one with a 0.03 rad steering bias (FAULT) and one
that falls silent after 2 s (STALE). Screenshots go to test-output/web/.
"""

from __future__ import annotations

import re
import time
from typing import Any

import pytest
from playwright.sync_api import expect

from tests.service.helpers import FAST_DESIGN, TOKEN, make_settings, wait_for
from tests.web.conftest import watch
from tests.web.helpers import cruise, dashboard_server, live_fleet, steer_bias, torque_bias

pytestmark = [pytest.mark.browser, pytest.mark.network]

ALARMS = {
    "torque_warn_nm": 30.0,
    "torque_fault_nm": 60.0,
    "steer_warn_rad": 0.015,
    "steer_fault_rad": 0.025,
    "warmup_s": 1.0,
    "raise_after_s": 0.3,
}
EXPECTED_LEVELS = {
    "agv-01": "OK",
    "agv-02": "OK",
    "agv-torque": "FAULT",
    "agv-warn": "WARN",
    "agv-steer": "FAULT",
    "agv-stale": "STALE",
}
#: Longest wait for something the page shows [ms].
UI_TIMEOUT_MS = 30_000
#: Background colours of the level badges (style.css): the level is shown by colour as well as by word.
BADGE_COLOURS = {"FAULT": "rgb(207, 34, 46)", "WARN": "rgb(255, 248, 197)", "OK": "rgb(218, 251, 225)"}


@pytest.fixture(scope="module")
def server(tmp_path_factory, chromium):
    settings = make_settings(tmp_path_factory.mktemp("browser"), {"default": {"design": FAST_DESIGN, "alarms": ALARMS}})
    scenarios = {
        "agv-01": cruise("healthy-1"),
        "agv-02": cruise("healthy-2", seed=1),
        "agv-torque": cruise("torque-bias", torque_bias(80.0)),
        "agv-warn": cruise("small-torque-bias", torque_bias(40.0)),
        "agv-steer": cruise("steering-bias", steer_bias(0.03)),
        "agv-stale": cruise("falls-silent"),
    }
    with (
        dashboard_server(settings) as srv,
        live_fleet(settings.zenoh.endpoint, scenarios, silent_after_s={"agv-stale": 2.0}, grades={"agv-02": 0.0}),
    ):
        wait_for(
            lambda: {v["id"]: v["level"] for v in srv.get("/vehicles").json()} == EXPECTED_LEVELS,
            what="every vehicle at its expected level",
        )
        yield srv


def row(page: Any, vehicle: str) -> Any:
    return page.locator(f'#fleet-body .vrow[data-vehicle="{vehicle}"]')


def cell_number(page: Any, vehicle: str, index: int) -> float:
    return float(row(page, vehicle).locator('[role="cell"]').nth(index).inner_text())


def test_the_fleet_view_lists_the_running_fleet_with_levels_estimates_and_alarms(server, page, output_dir):
    page.goto(server.url + "/")
    expect(page.locator("#connection")).to_have_attribute("data-state", "live", timeout=UI_TIMEOUT_MS)
    expect(page.locator("#fleet-table")).to_have_attribute("data-total", "6", timeout=UI_TIMEOUT_MS)
    for vehicle, level in EXPECTED_LEVELS.items():
        expect(row(page, vehicle)).to_have_attribute("data-level", level, timeout=UI_TIMEOUT_MS)
    for level, colour in BADGE_COLOURS.items():
        badge = page.locator(f'#fleet-body .vrow[data-level="{level}"] .level').first
        assert badge.evaluate("e => getComputedStyle(e).backgroundColor") == colour
    # the current fault estimates: columns v_x, T_f, delta_f
    assert 75.0 < cell_number(page, "agv-torque", 5) < 85.0
    assert 35.0 < cell_number(page, "agv-warn", 5) < 45.0
    assert 0.027 < cell_number(page, "agv-steer", 6) < 0.033
    assert abs(cell_number(page, "agv-01", 5)) < 5.0
    assert 9.0 < cell_number(page, "agv-01", 4) < 13.0
    expect(row(page, "agv-01").locator('[role="cell"]').nth(3)).to_have_text("just now")
    expect(row(page, "agv-stale").locator('[role="cell"]').nth(3)).to_have_text(re.compile(r"^\d+ s ago$"))
    # the FAULT rows sort first
    first_two = {page.locator("#fleet-body .vrow").nth(i).get_attribute("data-vehicle") for i in range(2)}
    assert {row(page, v).get_attribute("data-level") for v in first_two} == {"FAULT"}
    # active alarms, each with an acknowledge button
    alarms = page.locator("#fleet-alarms .alarm")
    expect(alarms).to_have_count(4, timeout=UI_TIMEOUT_MS)
    torque = page.locator('#fleet-alarms .alarm[data-vehicle="agv-torque"][data-kind="torque_fault"]')
    expect(torque).to_have_attribute("data-level", "FAULT")
    expect(torque.get_by_role("button", name="Acknowledge torque fault of agv-torque")).to_be_visible()
    expect(page.locator("#alarm-badge")).to_have_text("4 unacknowledged alarms")
    page.screenshot(path=str(output_dir / "fleet.png"))
    # filters
    page.locator('#level-filters button[data-level="FAULT"]').click()
    expect(page.locator("#fleet-table")).to_have_attribute("data-shown", "2")
    page.locator('#level-filters button[data-level="ALL"]').click()
    page.fill("#fleet-search", "stale")
    expect(page.locator("#fleet-table")).to_have_attribute("data-shown", "1")
    expect(page.locator("#fleet-body .vrow:not([hidden])")).to_have_count(1)


def plot_state(page: Any, key: str) -> dict[str, Any]:
    figure = page.locator(f'figure[data-plot="{key}"]')
    return {
        "points": int(figure.get_attribute("data-points") or 0),
        "truth": int(figure.get_attribute("data-truth") or 0),
        "last_t": float(figure.get_attribute("data-last-t") or 0),
        "latest": figure.get_attribute("data-latest"),
        "image": figure.locator("canvas").evaluate("c => c.toDataURL()"),
    }


def test_a_vehicle_view_plots_live_estimates_with_thresholds_and_ground_truth(server, page, output_dir):
    page.goto(server.url + "/")
    row(page, "agv-torque").get_by_role("link", name="agv-torque").click()
    expect(page).to_have_url(re.compile(r"#/vehicle/agv-torque$"))
    expect(page.locator("#vehicle-level")).to_have_text("FAULT", timeout=UI_TIMEOUT_MS)
    expect(page.locator('#vehicle-facts [data-fact="truth"] dd')).to_have_text("shown", timeout=UI_TIMEOUT_MS)
    figures = page.locator("figure.plot")
    expect(figures).to_have_count(6)
    for key in ("vx", "r", "vy", "tf", "sf"):
        expect(page.locator(f'figure[data-plot="{key}"] canvas')).to_have_count(1)
    expect(page.locator('figure[data-plot="alpha"]')).to_be_hidden()  # the profile runs no effectiveness stage
    wait_for(lambda: plot_state(page, "tf")["truth"] > 20, UI_TIMEOUT_MS / 1000, "ground truth in the plot")
    before = plot_state(page, "tf")
    time.sleep(1.5)
    after = plot_state(page, "tf")
    assert after["last_t"] >= before["last_t"] + 1.0  # new samples arrived and were drawn
    assert after["points"] > before["points"] and after["truth"] > before["truth"]
    assert after["image"] != before["image"]  # the plot was redrawn
    assert 75.0 < float(after["latest"]) < 85.0
    legend = page.locator('figure[data-plot="tf"] .u-legend')
    for label in ("estimated", "true", "WARN", "FAULT"):
        expect(legend).to_contain_text(label)
    expect(page.locator('figure[data-plot="vx"] .u-legend')).to_contain_text("measured")
    expect(page.locator("#vehicle-alarms .alarm")).to_have_count(1)
    expect(page.locator('#vehicle-facts [data-fact="payload"] dd')).to_have_text("none reported")
    expect(page.locator('#vehicle-facts [data-fact="grade"] dd')).to_have_text("not sent")
    # past its warm-up, driving gently: the alarms judge it (GET /vehicles/{id}'s faults_judged)
    expect(page.locator('#vehicle-facts [data-fact="judged"] dd')).to_have_text("judging", timeout=UI_TIMEOUT_MS)
    page.screenshot(path=str(output_dir / "vehicle.png"), full_page=True)


def cell(page: Any, vehicle: str, column: str) -> Any:
    """The fleet table's cell of ``vehicle`` under the header that sorts by ``column``."""
    headers = page.locator("#fleet-table .vhead [role='columnheader']")
    index = [headers.nth(i).get_attribute("data-sort") for i in range(headers.count())].index(column)
    return row(page, vehicle).locator('[role="cell"]').nth(index)


def test_the_road_grade_a_vehicle_sends_shows_in_the_vehicle_view(server, page):
    """agv-02 sends a grade of 0 with every sample (level ground, flag bit 1): the view shows it, as the REST
    status does; the grade it shows is the latest sample's."""
    status = server.get("/vehicles/agv-02").json()
    assert status["grade_rad"] == 0.0 and status["grade_seq"] is not None and status["grade_seq"] > 0
    assert server.get("/vehicles/agv-01").json()["grade_seq"] is None
    page.goto(server.url + "/#/vehicle/agv-02")
    expect(page.locator('#vehicle-facts [data-fact="grade"] dd')).to_have_text("0.0 %", timeout=UI_TIMEOUT_MS)


def test_a_reported_payload_shows_in_the_fleet_table_and_the_vehicle_view(server, page):
    reported = server.http.put("/vehicles/agv-stale/payload", json={"payload_kg": 35.0}, headers=server.auth)
    assert reported.status_code == 200
    page.goto(server.url + "/")
    expect(cell(page, "agv-stale", "load")).to_have_text("35", timeout=UI_TIMEOUT_MS)
    expect(cell(page, "agv-01", "load")).to_have_text("–")
    page.goto(server.url + "/#/vehicle/agv-stale")
    expect(page.locator('#vehicle-facts [data-fact="payload"] dd')).to_have_text("35 kg", timeout=UI_TIMEOUT_MS)


def test_an_operator_reports_a_payload_from_the_vehicle_view(server, page, page_problems):
    """The form puts the payload through the REST API with the operator's token: refused without it, and for a
    load the vehicle cannot carry, with the reason on the page; accepted, it shows in the facts and the fleet."""
    status = page.locator("#payload-status")
    page.goto(server.url + "/#/vehicle/agv-stale")
    expect(page.locator("#vehicle-title")).to_have_text("agv-stale", timeout=UI_TIMEOUT_MS)
    before = server.get("/vehicles/agv-stale").json()["payload_kg"]
    page_problems.allow(r"status of (401|422)")
    page.fill("#payload-input", "60")
    page.get_by_role("button", name="Report", exact=True).click()
    expect(status).to_contain_text("token", timeout=UI_TIMEOUT_MS)
    assert server.get("/vehicles/agv-stale").json()["payload_kg"] == before
    page.fill("#token-input", TOKEN)
    page.get_by_role("button", name="Save token").click()
    page.get_by_role("button", name="Report", exact=True).click()
    expect(status).to_have_text("Reported: 60 kg", timeout=UI_TIMEOUT_MS)
    expect(page.locator('#vehicle-facts [data-fact="payload"] dd')).to_have_text("60 kg", timeout=UI_TIMEOUT_MS)
    assert server.get("/vehicles/agv-stale").json()["payload_kg"] == 60.0
    page.fill("#payload-input", "1000000")  # more than the vehicle's mass
    page.get_by_role("button", name="Report", exact=True).click()
    expect(status).to_contain_text("Not reported", timeout=UI_TIMEOUT_MS)
    expect(status).to_have_attribute("data-state", "error")
    assert server.get("/vehicles/agv-stale").json()["payload_kg"] == 60.0
    page.goto(server.url + "/")
    expect(cell(page, "agv-stale", "load")).to_have_text("60", timeout=UI_TIMEOUT_MS)


def test_acknowledging_an_alarm_changes_its_state_in_every_open_page(server, page, page_problems, browser_context):
    alarm_id = next(
        a["id"] for a in server.get("/alarms").json() if a["vehicle"] == "agv-warn" and a["kind"] == "torque_fault"
    )
    other = browser_context.new_page()
    other_problems = watch(other)
    other.goto(server.url + "/")
    page.goto(server.url + "/")
    item = page.locator(f'#fleet-alarms .alarm[data-alarm-id="{alarm_id}"]')
    expect(item).to_have_attribute("data-acknowledged", "false", timeout=UI_TIMEOUT_MS)
    # without the token the service refuses, and the page says so
    page_problems.allow(r"status of 401")
    page.evaluate("localStorage.clear()")
    item.get_by_role("button", name=re.compile("Acknowledge")).click()
    expect(item.locator(".alarm-error")).to_contain_text("token", timeout=UI_TIMEOUT_MS)
    assert server.get(f"/alarms/{alarm_id}").json()["acknowledged"] is False
    # with the token
    page.fill("#token-input", TOKEN)
    page.get_by_role("button", name="Save token").click()
    expect(page.locator("#token-state")).to_have_text("saved")
    item.get_by_role("button", name=re.compile("Acknowledge")).click()
    expect(item).to_have_attribute("data-acknowledged", "true", timeout=UI_TIMEOUT_MS)
    expect(item.locator(".alarm-state")).to_have_text("active · acknowledged")
    expect(item.get_by_role("button", name=re.compile("Acknowledge"))).to_be_hidden()
    expect(page.locator("#alarm-badge")).to_have_text("3 unacknowledged alarms")
    stored = server.get(f"/alarms/{alarm_id}").json()
    assert stored["acknowledged"] is True and stored["acknowledged_by"] == "dashboard"
    # the other page learnt it from its stream
    other_item = other.locator(f'#fleet-alarms .alarm[data-alarm-id="{alarm_id}"]')
    expect(other_item).to_have_attribute("data-acknowledged", "true", timeout=UI_TIMEOUT_MS)
    assert not other_problems.unexpected(), other_problems


def profile_card(page: Any) -> Any:
    return page.locator('article.profile[data-profile="default"]')


def test_a_design_from_the_form_activates_a_new_gain_version_and_a_failed_one_says_why(
    server, page, page_problems, output_dir
):
    before = server.get("/profiles/default").json()
    page.goto(server.url + "/#/profiles")
    card = profile_card(page)
    expect(card).to_have_attribute("data-active-version", before["active_version"], timeout=UI_TIMEOUT_MS)
    expect(card.locator("dl.kv dd").first).to_have_text("yes")
    expect(card.locator("dl.kv")).to_contain_text("CLARABEL")
    page.screenshot(path=str(output_dir / "profiles.png"), full_page=True)
    page.fill("#token-input", TOKEN)
    page.get_by_role("button", name="Save token").click()
    # an impossible design: the job fails, says why, and the active gains stay
    card.get_by_label("steer_fault_gain").fill("1e-9")
    card.get_by_role("button", name="Save and design new gains").click()
    job = card.locator(".job")
    expect(job).to_have_attribute("data-status", "failed", timeout=UI_TIMEOUT_MS)
    expect(job).to_contain_text("infeasible")
    expect(job).to_contain_text("not detectable")
    assert server.get("/profiles/default").json()["active_version"] == before["active_version"]
    # a heavier vehicle: a new certified design becomes active
    card.get_by_label("steer_fault_gain").fill("1")
    card.get_by_label("mass_kg", exact=True).fill("1600")
    expect(card.get_by_label("mass_kg", exact=True)).to_have_class(re.compile("changed"))
    card.get_by_role("button", name="Save and design new gains").click()
    expect(profile_card(page).locator(".job")).to_have_attribute("data-status", "succeeded", timeout=60_000)
    after = server.get("/profiles/default").json()
    assert after["active_version"] != before["active_version"]
    assert after["gain_versions"] == [*before["gain_versions"], after["active_version"]]
    assert after["spec"]["params"]["mass_kg"] == 1600.0
    card = profile_card(page)
    expect(card).to_have_attribute("data-active-version", after["active_version"])
    expect(card.locator(".job .new-version")).to_have_text(after["active_version"])
    expect(card.locator(".versions li.active")).to_have_attribute("title", after["active_version"])
    # only the changed field was sent: the rest of the spec still follows the defaults
    stored = server.get("/ui/profiles/default/form").json()["stored"]
    assert stored["params"] == {"mass_kg": 1600.0} and "bounds" not in stored
    # a value the service refuses is explained next to the form
    page_problems.allow(r"status of 422")
    card.get_by_label("vx_min_mps").fill("40")
    card.get_by_role("button", name="Save and design new gains").click()
    expect(card.locator(".errors")).to_contain_text("vx_min_mps must be below vx_max_mps")
    page.screenshot(path=str(output_dir / "profiles-after-design.png"), full_page=True)
