"""The dashboard over HTTP, no browser: the page and its files, the live stream, the profile form, read access.

The real service (uvicorn, in-process Zenoh router, SQLite in tmp_path) and a live fleet publishing
measurements and ground truth at 100 Hz over a Zenoh client session.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import re
import statistics
import time
from collections.abc import Iterator
from typing import Any

import httpx
import pytest

from service.main import create_app
from service.web.hub import POINT_COLUMNS, TRUTH_COLUMNS
from tests.service.helpers import FAST_DESIGN, TOKEN, make_settings, wait_for
from tests.web.helpers import cruise, dashboard_server, live_fleet, torque_bias

pytestmark = pytest.mark.network

ALARMS = {"torque_warn_nm": 30.0, "torque_fault_nm": 60.0, "warmup_s": 1.0, "raise_after_s": 0.3}
PROFILES = {"default": {"design": FAST_DESIGN, "alarms": ALARMS}}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    settings = make_settings(tmp_path_factory.mktemp("stream"), PROFILES)
    scenarios = {"agv-ok": cruise("ok"), "agv-torque": cruise("torque", torque_bias(80.0, onset_s=1.0))}
    with dashboard_server(settings) as srv, live_fleet(settings.zenoh.endpoint, scenarios):
        wait_for(lambda: srv.get("/vehicles").json().__len__() == 2, what="both vehicles registered")
        yield srv


def read_stream(
    url: str, seconds: float, headers: dict[str, str] | None = None, max_events: int = 1_000_000
) -> list[tuple[str, Any]]:
    """The (event, data) pairs of an SSE stream during ``seconds`` (or until ``max_events`` came)."""
    events: list[tuple[str, Any]] = []
    deadline = time.monotonic() + seconds
    with httpx.stream("GET", url, headers=headers, timeout=httpx.Timeout(10.0)) as response:
        assert response.status_code == 200, response.read()
        assert response.headers["content-type"].startswith("text/event-stream")
        name = None
        for line in response.iter_lines():
            if line.startswith("event: "):
                name = line[7:]
            elif line.startswith("data: "):
                events.append((name, json.loads(line[6:])))
            if time.monotonic() > deadline or len(events) >= max_events:
                break
    return events


def of(events: list[tuple[str, Any]], name: str) -> list[Any]:
    return [data for event, data in events if event == name]


def test_the_page_and_its_files_are_served_from_the_package_under_a_strict_policy(server):
    page = server.get("/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    policy = page.headers["content-security-policy"]
    assert "default-src 'self'" in policy and "script-src 'self'" in policy and "unsafe" not in policy
    html = page.text
    assert not re.search(r"(src|href)=\"(https?:)?//", html)  # nothing from another origin: works offline
    assets = re.findall(r"(?:src|href)=\"(/ui/static/[^\"]+)\"", html)
    assert "/ui/static/vendor/uplot/uPlot.iife.min.js" in assets and "/ui/static/js/main.js" in assets
    modules = {"/ui/static/js/main.js"}
    seen: set[str] = set()
    while modules - seen:  # every ES module reachable from main.js is served
        path = sorted(modules - seen)[0]
        seen.add(path)
        script = server.get(path)
        assert script.status_code == 200 and "javascript" in script.headers["content-type"], path
        modules |= {f"/ui/static/js/{m}" for m in re.findall(r"from '\./([\w.]+)'", script.text)}
    assert len(seen) >= 7
    for path in assets:
        assert server.get(path).status_code == 200, path
    assert "MIT" in server.get("/ui/static/vendor/uplot/LICENSE").text


def test_a_vehicle_stream_carries_decimated_estimates_the_measurements_and_the_ground_truth(server):
    wait_for(lambda: server.vehicle("agv-torque")["level"] == "FAULT", what="the torque fault alarm")
    events = read_stream(f"{server.url}/ui/stream?view=vehicle&vehicle=agv-torque", 3.0)
    assert [e for e, _ in events[:4]] == ["hello", "alarms", "status", "trace"]
    hello = events[0][1]
    assert hello["vehicle"] == "agv-torque" and hello["plot_hz"] == 20.0
    status = of(events, "status")[-1]
    assert status["row"][2] == "FAULT" and status["truth"] is True
    assert status["thresholds"]["torque_fault_nm"] == 60.0
    traces = of(events, "trace")
    assert traces[0]["history"] and not any(t["history"] for t in traces[1:])
    live = [p for t in traces[1:] for p in t["points"]]
    truth = [p for t in traces for p in t["truth"]]
    assert len(live) >= 2.0 * 20 * 0.8  # the 3 s read: at least 2 s of points
    t = [p[0] for p in live]
    steps = [b - a for a, b in itertools.pairwise(t)]
    assert min(steps) > 0 and max(steps) < 0.2
    # 20 points a second of the samples' time (a loaded service sends a backlog at once: more in the read's 3 s)
    assert len(live) <= (t[-1] - t[0]) * 20 + 2 and statistics.median(steps) == pytest.approx(0.05, abs=0.005)
    point = {name: i for i, name in enumerate(POINT_COLUMNS)}
    true = {name: i for i, name in enumerate(TRUTH_COLUMNS)}
    truth_at = {p[0]: p for p in truth}
    matched = [(p, truth_at[p[0]]) for p in live if p[0] in truth_at]
    assert len(matched) >= len(live) // 2  # the same samples were kept on both sides
    for estimate, actual in matched:
        # noise-free sensors: the measured v_x is the true one; the estimate has converged to the true fault
        assert estimate[point["vx_meas"]] == pytest.approx(actual[true["vx"]], abs=1e-3)
        assert actual[true["torque_fault"]] == pytest.approx(80.0)
        assert estimate[point["torque_fault"]] == pytest.approx(80.0, abs=2.0)
    alarms = of(events, "alarms")[0]["upsert"]
    assert any(a["vehicle"] == "agv-torque" and a["kind"] == "torque_fault" for a in alarms)


def test_a_fleet_stream_sends_every_vehicle_then_changed_rows(server):
    events = read_stream(f"{server.url}/ui/stream?view=fleet", 2.0)
    hello, fleets = events[0][1], of(events, "fleet")
    columns = hello["fleet_columns"]
    first = [dict(zip(columns, row, strict=True)) for row in fleets[0]["rows"]]
    assert fleets[0]["full"] and {r["id"] for r in first} == {"agv-ok", "agv-torque"}
    assert {r["id"]: r["level"] for r in first} == {"agv-ok": "OK", "agv-torque": "FAULT"}
    assert len(fleets) >= 3 and not any(f["full"] for f in fleets[1:])  # deltas at fleet_hz = 2
    assert of(events, "trace") == []  # the fleet view gets no plot data


def test_stream_errors(server):
    assert server.get("/ui/stream", params={"view": "vehicle", "vehicle": "nobody"}).status_code == 404
    assert server.get("/ui/stream", params={"view": "vehicle"}).status_code == 404
    assert server.get("/ui/stream", params={"view": "nonsense"}).status_code == 422
    assert server.get("/ui/stream", params={"view": "vehicle", "vehicle": "bad id!"}).status_code == 422


def test_the_profile_form_has_the_stored_and_the_resolved_spec(server):
    form = server.get("/ui/profiles/default/form").json()
    assert form["stored"]["design"] == FAST_DESIGN and "params" not in form["stored"]  # only what was set
    assert form["resolved"]["params"]["mass_kg"] == 1481.0 and form["resolved"]["bounds"]["vx_max_mps"] == 30.0
    fields = {f["name"]: f for f in form["fields"]["params"]}
    assert fields["mass_kg"]["description"].startswith("M_v") and fields["mass_kg"]["exclusive_minimum"] == 0
    assert {f["name"] for f in form["fields"]["bounds"]} >= {"vx_min_mps", "r_max_radps"}
    # a switch and a number that may stay empty are edited as such, with the limits of their number branch
    assert fields["cornering_drag"]["kind"] == "boolean" and fields["mass_kg"]["kind"] == "number"
    bounds = {f["name"]: f for f in form["fields"]["bounds"]}
    assert bounds["front_lateral_force_max_n"]["kind"] == "optional_number"
    assert bounds["front_lateral_force_max_n"]["exclusive_minimum"] == 0
    assert server.get("/ui/profiles/nope/form").status_code == 404


@pytest.fixture
def closed_reads(tmp_path) -> Iterator[Any]:
    settings = make_settings(tmp_path, PROFILES, auth={"open_reads": False})
    with dashboard_server(settings) as srv:
        yield srv


def test_with_closed_reads_the_page_is_public_but_its_data_needs_the_token(closed_reads):
    srv = closed_reads
    assert srv.get("/").status_code == 200 and srv.get("/ui/static/js/main.js").status_code == 200
    assert srv.get("/ui/stream").status_code == 401 and srv.get("/ui/profiles/default/form").status_code == 401
    auth = {"Authorization": f"Bearer {TOKEN}"}
    events = read_stream(f"{srv.url}/ui/stream?view=profiles", 5.0, headers=auth, max_events=2)
    assert [e for e, _ in events[:2]] == ["hello", "alarms"]
    # the REST reads as well; health and readiness stay open for probes
    for path in ("/vehicles", "/alarms", "/profiles", "/profiles/default/gains", "/jobs"):
        denied = srv.get(path)
        assert denied.status_code == 401 and denied.headers["www-authenticate"].startswith("Bearer"), path
        assert srv.get(path, headers={"Authorization": "Bearer nope"}).status_code == 401, path
        assert srv.get(path, headers=auth).status_code == 200, path
    assert srv.get("/health").status_code == 200


def test_the_dashboard_can_be_switched_off(tmp_path):
    async def status_codes(settings) -> dict[str, Any]:
        transport = httpx.ASGITransport(app=create_app(settings))  # no lifespan: static routes only
        async with httpx.AsyncClient(transport=transport, base_url="http://dashboard") as client:
            codes: dict[str, Any] = {p: (await client.get(p)).status_code for p in ("/", "/ui/static/js/main.js")}
            codes["stream"] = "/ui/stream" in (await client.get("/openapi.json")).json()["paths"]
        return codes

    on = asyncio.run(status_codes(make_settings(tmp_path / "on", PROFILES)))
    off = asyncio.run(status_codes(make_settings(tmp_path / "off", PROFILES, dashboard={"enabled": False})))
    assert on == {"/": 200, "/ui/static/js/main.js": 200, "stream": True}
    assert off == {"/": 404, "/ui/static/js/main.js": 404, "stream": False}
