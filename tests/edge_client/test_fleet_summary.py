"""The fleet summary's verdicts (detection, delay, false alarms) and the progress line, without a network."""

import math

import numpy as np

from agv_protocol.wire import Alarm
from edge_client.faults import BiasFault
from edge_client.fleet import FleetSummary, summarize
from edge_client.fleet_mix import FleetMember
from edge_client.pacing import PacingStats
from edge_client.publisher import AlarmEvent, Progress, PublishReport, VehicleRecord
from edge_client.scenario import Scenario

PERIOD_NS = 10_000_000
START_NS = 5_000_000_000


def deadline_ns(k: int) -> int:
    return START_NS + k * PERIOD_NS


def alarm_event(vehicle, kind, state, at_s):
    alarm = Alarm(vehicle=vehicle, id=f"{vehicle}-{kind}", kind=kind, level="FAULT", state=state, t_ns=0)
    return AlarmEvent(received_ns=START_NS + round(at_s * 1e9), alarm=alarm)


def report_for(records):
    pacing = PacingStats(1000, 9.99, 100.0, 0.1, 0.5, 1.0, 0, 0)
    return PublishReport(
        pacing=pacing,
        sent=sum(r.sent for r in records),
        lost=0,
        unsent_at_end=0,
        estimates=0,
        alarms=0,
        rtt_p50_ms=0.4,
        rtt_p99_ms=1.2,
        rtt_max_ms=3.0,
        work_ms={},
        link_changes=0,
        bad_messages=0,
        start_ns=START_NS,
        end_ns=START_NS + 10_000_000_000,
        period_ns=PERIOD_NS,
        vehicles=records,
    )


def member(vehicle_id, faults=()):
    scenario = Scenario(name=vehicle_id, duration_s=10.0, faults=faults)
    return FleetMember(vehicle_id, "torque_bias" if faults else "healthy", scenario)


def test_alarm_delays_and_false_alarms_are_judged_against_the_onset():
    members = [
        member("quiet"),
        member("crying-wolf"),
        member("detected", (BiasFault(channel="torque", onset_s=4.0, magnitude=100.0),)),
        member("early", (BiasFault(channel="steer", onset_s=6.0, magnitude=0.02),)),
        member("missed", (BiasFault(channel="steer", onset_s=3.0, magnitude=0.02),)),
    ]
    records = [VehicleRecord(m.vehicle_id, sent=1000) for m in members]
    records[1].alarm_events.append(alarm_event("crying-wolf", "torque_fault", "raised", 2.0))
    records[2].alarm_events += [
        alarm_event("detected", "stale", "raised", 1.0),  # not a fault alarm: reported apart
        alarm_event("detected", "torque_fault", "raised", 4.75),
        alarm_event("detected", "torque_fault", "cleared", 6.0),
    ]
    records[3].alarm_events += [
        alarm_event("early", "steer_fault", "raised", 5.0),
        alarm_event("early", "steer_fault", "raised", 6.5),
    ]
    summary = summarize(members, report_for(records), np.zeros((5, 2)), deadline_ns)
    by_id = {v.vehicle_id: v for v in summary.vehicles}
    assert by_id["quiet"].false_alarms == 0 and by_id["quiet"].fault_alarms == ()
    assert by_id["crying-wolf"].false_alarms == 1
    assert by_id["detected"].fault_alarms == ("torque_fault",) and by_id["detected"].other_alarms == ("stale",)
    assert math.isclose(by_id["detected"].first_alarm_after_onset_s, 0.75)
    assert by_id["early"].false_alarms == 1 and math.isclose(by_id["early"].first_alarm_after_onset_s, 0.5)
    assert not by_id["missed"].detected and by_id["missed"].first_alarm_after_onset_s is None
    assert summary.false_alarms == 2
    assert "faulty vehicles alarmed 2/3; false alarms 2" in " ".join(summary.totals_line().split())
    text = summary.render_text(80)
    assert all(len(line) <= 80 for line in text.splitlines())
    assert "T_f bias +100" in text and "FALSE" in text and "0.75s" in text


def test_summary_json_round_trips():
    members = [member("a")]
    summary = summarize(members, report_for([VehicleRecord("a", sent=10)]), np.zeros((1, 2)), deadline_ns)
    data = summary.to_dict()
    assert isinstance(summary, FleetSummary) and data["vehicles"][0]["vehicle_id"] == "a"
    assert data["rtt_ms"] == {"p50": 0.4, "p99": 1.2, "max": 3.0}


def test_progress_line_fits_80_columns_and_says_when_the_link_is_down():
    def progress(**overrides):
        values = dict(
            elapsed_s=12345.6,
            ticks=1_234_560,
            tick_rate_hz=99.97,
            sample_rate_hz=49_985.0,
            sent=987_654_321,
            lost=123_456,
            buffered=0,
            late=10,
            overruns=2,
            rtt_p50_ms=12.3,
            rtt_p99_ms=345.6,
            estimates=987_000_000,
            alarms=12_345,
            linked=500,
            vehicles=500,
            connected=True,
        )
        values.update(overrides)
        return Progress(**values).line()

    line = progress()
    assert len(line) <= 80 and "sent 988M" in line and "lost 123k" in line and line.endswith("rtt 12/346ms")
    assert "link up" in line and "buf" not in line
    assert "link DOWN" in progress(connected=False)
    assert len(progress(linked=480)) <= 80 and progress(linked=480).endswith("link 480/500 rtt 12/346ms")
    assert "buf 100k" in progress(buffered=99_999, sent=10, lost=10)
    assert "rtt -/-ms" in progress(rtt_p50_ms=math.nan, rtt_p99_ms=math.nan, sent=10, lost=0)


def test_a_fault_that_had_not_begun_when_the_run_stopped_is_not_counted_as_missed():
    """Ctrl-C before a fault's onset: the vehicle is reported with its fault 'not begun', not as a missed fault."""
    members = [
        member("later", (BiasFault(channel="torque", onset_s=8.0, magnitude=100.0),)),
        member("begun", (BiasFault(channel="steer", onset_s=3.0, magnitude=0.02),)),
    ]
    records = [VehicleRecord(m.vehicle_id, sent=500) for m in members]  # stopped after 5 s
    summary = summarize(members, report_for(records), np.zeros((2, 2)), deadline_ns)
    later, begun = summary.vehicles
    assert not later.fault_started and not later.faulty and "not begun: the run ended at 5.0 s" in later.injected
    assert begun.fault_started and begun.faulty and not begun.detected
    assert "faulty vehicles alarmed 0/1" in " ".join(summary.totals_line().split())
