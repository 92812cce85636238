"""Structured logs: alarm transitions and job outcomes as events, one JSON object per line with --log-format json."""

from __future__ import annotations

import json
import logging

from service import logs
from tests.service.helpers import ServiceProcess, make_settings, wait_for


def test_an_event_is_a_readable_line_and_a_json_object_with_its_fields():
    record = logging.LogRecord("agv_fe.events", logging.WARNING, __file__, 1, "%s %s", ("alarm", "x"), None)
    captured: list[logging.LogRecord] = []

    class Keep(logging.Handler):
        def emit(self, r: logging.LogRecord) -> None:
            captured.append(r)

    handler = Keep()
    logs.EVENTS.addHandler(handler)
    try:
        logs.event("alarm", logging.WARNING, state="raised", vehicle="truck-7", kind="torque_fault", level="FAULT",
                   value=91.5, threshold=80.0, message=None)  # fmt: skip
    finally:
        logs.EVENTS.removeHandler(handler)
    (record,) = captured
    expected = "alarm state=raised vehicle=truck-7 kind=torque_fault level=FAULT value=91.5 threshold=80.0"
    assert record.getMessage() == expected
    line = json.loads(logs.JsonFormatter().format(record))
    assert line["event"] == "alarm" and line["severity"] == "WARNING" and line["logger"] == "agv_fe.events"
    assert line["level"] == "FAULT"  # the alarm's level; the record's is its severity
    assert line["vehicle"] == "truck-7" and line["kind"] == "torque_fault" and line["value"] == 91.5
    assert "message" in line and line["t"].endswith("Z") and "threshold" in line
    plain = logging.LogRecord("uvicorn.access", logging.INFO, __file__, 1, "%s", ("GET /health 200",), None)
    assert json.loads(logs.JsonFormatter().format(plain))["message"] == "GET /health 200"


def test_serve_writes_every_record_as_json_including_job_events_and_the_access_log(tmp_path):
    settings = make_settings(tmp_path)
    service = ServiceProcess(settings, tmp_path / "serve.log", "--log-format", "json").start()
    try:
        service.wait_ready()
        assert service.get("/health").status_code == 200
        # a design job for a new profile: its outcome is an event
        answer = service.http.put("/profiles/van", json={"params": {"mass_kg": 2100.0}}, headers=service.auth)
        assert answer.status_code == 202, answer.text
        job = answer.json()["job"]
        wait_for(lambda: f'"id": "{job}"' in service.log() and '"event": "job"' in service.log(), what="the job event")
    finally:
        service.close()
    lines = [line for line in service.log().splitlines() if line.strip()]
    parsed = [json.loads(line) for line in lines]  # every line is a JSON object
    assert all({"t", "severity", "logger", "message"} <= p.keys() for p in parsed)
    jobs = [p for p in parsed if p.get("event") == "job"]
    assert jobs and jobs[-1]["status"] == "succeeded" and jobs[-1]["profile"] == "van" and jobs[-1]["gain_version"]
    assert any(p["logger"] == "uvicorn.access" and "GET /health" in p["message"] for p in parsed)
