"""The monitoring kit of deploy/: Prometheus scrape config and alert rules, the Grafana dashboard, and their compose
services, against what a real service exposes on /metrics.

The promtool tests need Debian's ``prometheus`` package (``apt-get install prometheus``): without promtool they
skip on a developer's machine and fail under CI (the CI environment variable is set), whose
.ci/install-system-deps installs it.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests.service.helpers import constant_measurement, make_settings, parse_metrics, probe, running, wait_for

ROOT = Path(__file__).resolve().parent.parent
PROMETHEUS = ROOT / "deploy" / "prometheus"
SCRAPE_CONFIG = PROMETHEUS / "prometheus.yml"
ALERTS = PROMETHEUS / "alerts.yml"
ALERT_TESTS = PROMETHEUS / "alerts_test.yml"
GRAFANA = ROOT / "deploy" / "grafana"
DASHBOARD = GRAFANA / "dashboards" / "agv-fe.json"
COMPOSE = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
#: Series that Prometheus makes itself for every target, not the service.
PROMETHEUS_SERIES = {"up"}
#: The alerts the operations issue asks for, each by the series it watches.
REQUIRED_ALERTS = {
    "AgvFeReplicaMissing": "up",
    "AgvFeNotReady": "agv_fe_ready",
    "AgvFeIngestStalled": "agv_fe_ingest_heartbeat_age_seconds",
    "AgvFeRejectRateHigh": "agv_fe_measurements_rejected_total",
    "AgvFeTickSlow": "agv_fe_tick_seconds_bucket",
    "AgvFeFaultAlarmLatched": "agv_fe_alarms_latched",
}

_PROMQL_KEYWORDS = {"by", "without", "on", "ignoring", "group_left", "group_right", "and", "or", "unless", "bool"}
_PROMQL_KEYWORDS |= {"offset", "inf", "nan"}


def promql_metric_names(expr: str) -> set[str]:
    """The metric names an expression selects: identifiers that are not functions, keywords, label names (in
    braces or in by/without/on/ignoring lists), strings, durations or numbers."""
    text = re.sub(r'"(?:[^"\\]|\\.)*"', '""', expr)  # strings, label values included
    text = re.sub(r"\{[^}]*\}", " ", text)  # label matchers
    text = re.sub(r"\[[^\]]*\]", " ", text)  # range and subquery durations, $__rate_interval
    text = re.sub(r"\b(by|without|on|ignoring|group_left|group_right)\s*\([^)]*\)", " ", text)
    names = set()
    for match in re.finditer(r"(?<![\w.$])([A-Za-z_:][A-Za-z0-9_:]*)\b(\s*\()?", text):
        name, call = match.groups()
        if call or name.lower() in _PROMQL_KEYWORDS:
            continue
        names.add(name)
    return names


def test_the_promql_name_parser_finds_metrics_and_only_metrics():
    expr = (
        'sum by (instance, le) (rate(agv_fe_tick_seconds_bucket{job="a b", le!="x"}[5m])) / on (instance) '
        'ignoring(le) agv_fe_ready > bool 0.5 or vector(0) and absent(up{job="agv-fe"} == 1) offset 1m'
    )
    assert promql_metric_names(expr) == {"agv_fe_tick_seconds_bucket", "agv_fe_ready", "up"}
    assert promql_metric_names("rate(x_total[$__rate_interval]) * 1e3") == {"x_total"}


def promtool() -> str:
    path = shutil.which("promtool")
    if path is None:
        if os.environ.get("CI"):
            pytest.fail("promtool is not installed: CI must install it (.ci/install-system-deps)")
        pytest.skip("promtool is not installed (apt-get install prometheus): promtool checks skipped")
    return path


def run_promtool(*args: str, stdin: str | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([promtool(), *args], input=stdin, capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def scrape(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """The /metrics text of a real service that has estimated a few samples (so every histogram has data)."""
    settings = make_settings(tmp_path_factory.mktemp("monitoring"))
    with running(settings) as srv, probe(settings.zenoh.endpoint) as p:
        for k in range(10):
            p.put(constant_measurement("scraped-1", k))
        wait_for(lambda: len(p.estimates_of("scraped-1")) >= 10, what="estimates")
        wait_for(
            lambda: parse_metrics(srv.get("/metrics").text).value("agv_fe_estimate_latency_seconds_count") >= 10,
            what="the estimates' delays observed",
        )
        yield srv.get("/metrics").text


@pytest.fixture(scope="module")
def exposed(scrape: str) -> set[str]:
    """Every series name the scrape declares, with samples or not yet (no latched alarm: no labelled sample)."""
    metrics = parse_metrics(scrape)
    names = {name for name, _ in metrics.samples} | set(metrics.types)
    for family, kind in metrics.types.items():
        if kind == "histogram":
            names |= {f"{family}_bucket", f"{family}_sum", f"{family}_count"}
    return names


def alert_rules() -> list[dict[str, Any]]:
    groups = yaml.safe_load(ALERTS.read_text())["groups"]
    return [rule for group in groups for rule in group["rules"]]


def test_promtool_accepts_the_alert_rules_and_their_unit_tests_pass():
    checked = run_promtool("check", "rules", str(ALERTS))
    assert checked.returncode == 0, checked.stdout + checked.stderr
    tested = run_promtool("test", "rules", str(ALERT_TESTS))
    assert tested.returncode == 0, tested.stdout + tested.stderr


def test_promtool_accepts_the_scrape_config():
    checked = run_promtool("check", "config", str(SCRAPE_CONFIG))
    assert checked.returncode == 0, checked.stdout + checked.stderr
    config = yaml.safe_load(SCRAPE_CONFIG.read_text())
    assert config["rule_files"] == [ALERTS.name]
    (job,) = config["scrape_configs"]
    assert job["job_name"] == "agv-fe" and job["metrics_path"] == "/metrics"
    # the target is the compose service on its HTTP port
    port = COMPOSE["services"]["service"]["environment"]["AGV_FE_HTTP__PORT"]
    assert job["static_configs"][0]["targets"] == [f"service:{port}"]


def test_promtool_accepts_a_real_services_metrics(scrape):
    checked = run_promtool("check", "metrics", stdin=scrape)
    # promtool check metrics lints too; it must find no problem at all
    assert checked.returncode == 0 and not checked.stdout.strip(), checked.stdout + checked.stderr


def test_the_service_reports_its_cpu_by_thread(scrape):
    """The event loop's thread (here uvicorn's, in the test process), Zenoh's and the service's own threads each
    have a series, and none is negative."""
    samples = parse_metrics(scrape).samples
    cpu = {dict(labels)["thread"]: value for (name, labels), value in samples.items()
           if name == "agv_fe_thread_cpu_seconds_total"}  # fmt: skip
    assert {"event_loop", "zenoh", "storage-writer"} <= set(cpu), sorted(cpu)
    assert cpu["event_loop"] > 0 and min(cpu.values()) >= 0


def test_every_alert_watches_series_the_service_exposes(exposed):
    rules = {rule["alert"]: rule for rule in alert_rules()}
    for name, series in REQUIRED_ALERTS.items():
        assert series in promql_metric_names(rules[name]["expr"]), name
    for name, rule in rules.items():
        unknown = promql_metric_names(rule["expr"]) - exposed - PROMETHEUS_SERIES
        assert not unknown, f"alert {name} names series the service does not expose: {sorted(unknown)}"
        assert rule["labels"]["severity"] in ("critical", "warning") and rule["annotations"]["summary"], name


def dashboard_panels() -> list[dict[str, Any]]:
    dashboard = json.loads(DASHBOARD.read_text())
    return list(dashboard["panels"])


def test_the_dashboard_queries_only_series_the_service_exposes(exposed):
    dashboard = json.loads(DASHBOARD.read_text())
    assert dashboard["uid"] and dashboard["title"]
    panels = dashboard_panels()
    datasource = yaml.safe_load((GRAFANA / "provisioning" / "datasources" / "prometheus.yml").read_text())
    (source,) = datasource["datasources"]
    ids = [panel["id"] for panel in panels]
    assert len(set(ids)) == len(ids)
    queried: set[str] = set()
    for panel in panels:
        assert panel["datasource"]["uid"] == source["uid"], panel["title"]
        assert panel["targets"], panel["title"]
        for target in panel["targets"]:
            names = promql_metric_names(target["expr"])
            unknown = names - exposed - PROMETHEUS_SERIES
            assert names and not unknown, f"panel {panel['title']!r} queries unknown series {sorted(unknown)}"
            queried |= names
    # the panels the operations issue asks for
    for series in (
        "agv_fe_vehicles_by_level",
        "agv_fe_measurements_received_total",
        "agv_fe_measurements_rejected_total",
        "agv_fe_tick_seconds_bucket",
        "agv_fe_estimate_latency_seconds_bucket",
        "agv_fe_alarms_latched",
        "agv_fe_storage_degraded",
        "process_cpu_seconds_total",
        "process_resident_memory_bytes",
    ):
        assert series in queried, series


def _mounts(service: str) -> dict[str, Path]:
    """Container path -> host path of each bind mount of a compose service (named volumes left out)."""
    out = {}
    for volume in COMPOSE["services"][service]["volumes"]:
        host, container, *_ = volume.split(":")
        if host.startswith("./"):
            out[container] = (ROOT / host).resolve()
    return out


def test_compose_mounts_the_scrape_config_rules_and_grafana_provisioning():
    prometheus = _mounts("prometheus")
    config = prometheus["/etc/prometheus/prometheus.yml"]
    assert (
        config == SCRAPE_CONFIG
        and "--config.file=/etc/prometheus/prometheus.yml" in (COMPOSE["services"]["prometheus"]["command"])
    )
    # the rule file sits beside the config in the container, as rule_files names it
    assert prometheus["/etc/prometheus/" + ALERTS.name] == ALERTS
    grafana = _mounts("grafana")
    provisioning = grafana["/etc/grafana/provisioning"]
    assert provisioning == GRAFANA / "provisioning" and provisioning.is_dir()
    providers = yaml.safe_load((provisioning / "dashboards" / "agv-fe.yml").read_text())["providers"]
    (provider,) = providers
    dashboards_in_container = provider["options"]["path"]
    assert grafana[dashboards_in_container] == DASHBOARD.parent
    (source,) = yaml.safe_load((provisioning / "datasources" / "prometheus.yml").read_text())["datasources"]
    assert source["url"] == "http://prometheus:9090" and "9090:9090" in COMPOSE["services"]["prometheus"]["ports"]
    for path in [*prometheus.values(), *grafana.values()]:
        assert path.exists(), path
