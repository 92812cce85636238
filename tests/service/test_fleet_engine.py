"""The fleet engine without transport or web: validation, sequencing, batching, alarms, staleness, events."""

from __future__ import annotations

import asyncio
import dataclasses
import itertools
import math

import numpy as np
import pytest

from agv_protocol.wire import (
    FLAG_SEQUENCE_RESTART,
    MEASUREMENT_HEADER_SIZE,
    Estimate,
    FleetEstimates,
    Measurement,
    bucket_of,
    encode_fleet_estimates,
    vehicle_key,
)
from edge_client.library import paper_1
from service.api.models import VehicleStatus
from service.fleet import EngineConfig, FleetEngine, UnknownVehicle
from service.fleet.vehicle import REJECT_REASONS
from service.profiles import ProfileSpec
from synth.observer import FuzzyObserver
from synth.params import VehicleParams
from tests.service.helpers import FAST_DESIGN, PERIOD_NS, T0_NS, as_array, constant_measurement, plant_measurements
from tests.tolerances import AMPLIFIED_ROUNDING_ATOL, AMPLIFIED_ROUNDING_RTOL, BATCH_EQUALITY_ATOL


class FakeClock:
    def __init__(self) -> None:
        self.mono = 1000.0

    def ns(self) -> int:
        return int(self.mono * 1e9)

    def monotonic(self) -> float:
        return self.mono


def make_engine(gains, clock=None, alarms=None, **config) -> FleetEngine:
    clock = clock or FakeClock()
    engine = FleetEngine(EngineConfig(**config), clock_ns=clock.ns, monotonic=clock.monotonic)
    spec = ProfileSpec.model_validate({"design": FAST_DESIGN, "alarms": alarms or {}})
    engine.add_profile("default", spec)
    engine.activate("default", gains)
    return engine


def pairs(measurements: list[Measurement]) -> list[tuple[str, bytes]]:
    return [(vehicle_key(m.vehicle_id, "meas"), m.encode()) for m in measurements]


def decoded(result) -> list[Estimate]:
    return [Estimate.decode(p) for _, p in result.estimates]


def test_estimates_equal_the_offline_observer_whatever_the_batching(fast_gains):
    """Samples queued several per tick are stepped in order: same result as one sample per tick and as synth."""
    ids = ["a", "b", "c"]
    samples = plant_measurements(ids, 60)
    one_by_one = make_engine(fast_gains)
    streamed = [e for row in samples for e in decoded(one_by_one.process(pairs(row)))]
    batched = make_engine(fast_gains)
    burst = [m for row in samples for m in row]
    all_at_once = decoded(batched.process(pairs(burst[:100]))) + decoded(batched.process(pairs(burst[100:])))
    key = lambda e: (e.vehicle, e.seq)  # noqa: E731
    a, b = sorted(streamed, key=key), sorted(all_at_once, key=key)
    assert [key(e) for e in a] == [key(e) for e in b] and len(a) == 3 * 60
    np.testing.assert_allclose(as_array(a), as_array(b), atol=BATCH_EQUALITY_ATOL)
    obs = FuzzyObserver(fast_gains, np.array([[s.vx_mps, s.r_radps] for s in samples[0]]))
    for row in samples:
        res = obs.step([[m.vx_mps, m.r_radps] for m in row], [[m.torque_nm, m.steer_rad] for m in row])
    last = {e.vehicle: e for e in streamed if e.seq == 59}
    got = np.array([[last[v].vx, last[v].vy, last[v].r, last[v].torque_fault, last[v].steer_fault] for v in ids])
    np.testing.assert_allclose(got, res.x_hat[:, :5], atol=BATCH_EQUALITY_ATOL)


def test_a_switched_design_runs_in_the_engine_as_offline():
    """Each vehicle's switching statistic and countdown live in the bank: same estimates and modes as synth."""
    from synth.design import synthesize
    from synth.options import DesignOptions, SwitchingRule

    rule = SwitchingRule(start_s=0.2, hold_s=0.1, threshold=2.0)
    gains = synthesize(options=DesignOptions(design="robust", lyapunov="common", switching=rule))
    ids = ["a", "b"]
    samples = plant_measurements(ids, 80)
    engine = make_engine(gains)
    burst = [m for row in samples for m in row]
    got = decoded(engine.process(pairs(burst[:70]))) + decoded(engine.process(pairs(burst[70:])))
    obs = FuzzyObserver(gains, np.array([[s.vx_mps, s.r_radps] for s in samples[0]]))
    modes, expected = [], []
    for row in samples:
        res = obs.step([[m.vx_mps, m.r_radps] for m in row], [[m.torque_nm, m.steer_rad] for m in row])
        modes.append(bool(res.fast[0]))
        expected.append(res.x_hat[0, :5])
    assert True in modes and False in modes  # the rule ran both sets in these 80 samples
    a = sorted((e for e in got if e.vehicle == "a"), key=lambda e: e.seq)
    np.testing.assert_allclose(as_array(a), np.array(expected), atol=BATCH_EQUALITY_ATOL)
    assert [e.gain_set for e in a] == ["fast" if m else "quiet" for m in modes]  # every estimate names its set
    status = engine.vehicle_status(engine.vehicles["a"])
    assert status["gain_set"] == ("fast" if modes[-1] else "quiet")
    # the fleet stream carries the same column
    late = engine.process(pairs([m for row in plant_measurements(ids, 82)[80:] for m in row]))
    fleet = FleetEstimates.decode(encode_fleet_estimates("r", late.estimate_batches)).estimates()
    assert [e.gain_set for e in fleet] == [Estimate.decode(p).gain_set for _, p in late.estimates]
    assert {e.gain_set for e in fleet} <= {"fast", "quiet"} and len(fleet) == 4
    one_set = make_engine(synthesize(options=DesignOptions(design="robust", lyapunov="common", switching=None)))
    result = one_set.process(pairs(samples[0]))
    assert one_set.vehicle_status(one_set.vehicles["a"])["gain_set"] is None
    assert all(b'"gain_set"' not in p for _, p in result.estimates)  # one set: the documents are as before
    assert b'"gain_set"' not in encode_fleet_estimates("r", result.estimate_batches)


BAD = {
    "non_finite": lambda seq: constant_measurement("v", seq, vx=math.nan),
    "non_finite_inf": lambda seq: constant_measurement("v", seq, torque=math.inf),
    "out_of_range": lambda seq: constant_measurement("v", seq, vx=250.0),
    "out_of_range_negative": lambda seq: constant_measurement("v", seq, vx=-3.0),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_values_are_rejected_counted_and_leave_the_state_intact(fast_gains, case):
    """A rejected sample changes nothing but counters: not the observer, not the sequence cursor, even when
    its sequence number is as corrupt as its values (a wild seq must not make the next good samples late)."""
    reason = case.rsplit("_", 1)[0] if case.endswith(("_inf", "_negative")) else case
    good = [constant_measurement("v", k) for k in range(20)]
    clean = make_engine(fast_gains)
    clean.process(pairs(good[:10]))
    clean_after = decoded(clean.process(pairs(good[10:])))
    dirty = make_engine(fast_gains)
    dirty.process(pairs(good[:10]))
    bad = BAD[case](1000)
    result = dirty.process(pairs([bad]))
    assert result.estimates == [] and result.accepted == 0
    assert dirty.rejected[reason] == 1 and dirty.vehicles["v"].rejected[reason] == 1
    assert dirty.vehicles["v"].last_seq == 9
    # the next good samples (seq 10...) see exactly the state the clean engine has, none is dropped or missing
    dirty_after = decoded(dirty.process(pairs(good[10:])))
    assert dirty_after == clean_after
    assert dirty.stats["missing"] == 0 and dirty.rejected["out_of_order"] == 0


@pytest.mark.parametrize(
    "corrupt",
    [
        lambda b: b[:5] + bytes([0x04]) + b[6:],  # a flag bit version 1 does not define
        lambda b: b[:5] + bytes([0x81]) + b[6:],  # the restart bit and an undefined one
        lambda b: b[:56] + (1).to_bytes(8, "little") + b[64:],  # reserved bytes not zero
        lambda b: b[:63] + b"\x80" + b[64:],
    ],
)
def test_flags_and_reserved_bytes_that_must_be_zero_are_rejected_by_name(fast_gains, corrupt):
    """docs/protocol.md: flag bits other than bits 0 and 1 are zero, and so are bytes 56-63 without bit 1 (the
    road grade). A sample that sets them is not a version 1 measurement: rejected as reserved_bits, counted, and
    nothing else moves."""
    good = [constant_measurement("v", k) for k in range(20)]
    clean = make_engine(fast_gains)
    clean.process(pairs(good[:10]))
    clean_after = decoded(clean.process(pairs(good[11:])))
    engine = make_engine(fast_gains)
    engine.process(pairs(good[:10]))
    result = engine.process([(vehicle_key("v", "meas"), corrupt(good[10].encode()))])
    assert result.accepted == 0 and result.estimates == []
    assert engine.rejected["reserved_bits"] == 1 and engine.vehicles["v"].rejected["reserved_bits"] == 1
    assert engine.vehicles["v"].last_seq == 9
    assert decoded(engine.process(pairs(good[11:]))) == clean_after  # as if the sample had been lost


def test_a_bad_sample_in_sequence_counts_as_one_missing_sample(fast_gains):
    """A NaN sample at its proper seq is rejected; the observer continues as if it had been lost."""
    good = [constant_measurement("v", k) for k in range(20)]
    lost = make_engine(fast_gains)
    lost.process(pairs(good[:10]))
    lost_after = decoded(lost.process(pairs(good[11:])))
    dirty = make_engine(fast_gains)
    dirty.process(pairs(good[:10]))
    dirty.process(pairs([BAD["non_finite"](10)]))
    dirty_after = decoded(dirty.process(pairs(good[11:])))
    assert dirty_after == lost_after
    assert dirty.rejected["non_finite"] == 1 and dirty.stats["missing"] == 1


def test_malformed_id_mismatch_and_unknown_vehicles(fast_gains):
    engine = make_engine(fast_gains, unknown_vehicles="reject")
    engine.register("v", "default")
    good = constant_measurement("v", 0).encode()
    key = vehicle_key("v", "meas")
    batch = [
        (key, good[:30]),  # truncated
        (key, b"XXXX" + good[4:]),  # bad magic
        (key, good[:4] + bytes([7]) + good[5:]),  # unknown version
        ("agv/v1/b00/not a key/meas", good),  # bad key
        (vehicle_key("w", "meas").replace(vehicle_key("w", "meas").split("/")[2], "b0f"), good),  # wrong bucket
        (key, constant_measurement("w", 1).encode()),  # id mismatch, same length
        (vehicle_key("x", "meas"), constant_measurement("x", 0).encode()),  # unknown vehicle, policy reject
        (key, Measurement("other", 1, 0, 10.0, 0.0, 0.0, 0.0).encode()),  # id mismatch, other length
        (key, good),
    ]
    result = engine.process(batch)
    assert result.accepted == 1 and len(result.estimates) == 1
    assert engine.rejected["malformed"] == 5
    assert engine.rejected["unknown_vehicle"] == 1
    assert engine.rejected["id_mismatch"] == 2
    assert engine.vehicles["v"].rejected["malformed"] == 3 and engine.vehicles["v"].rejected["id_mismatch"] == 2
    assert set(engine.vehicles) == {"v"}
    # a known vehicle's sample on the wrong bucket is counted in its own counters too, like every other reject
    wrong = vehicle_key("v", "meas").replace(bucket_of("v"), "b0f" if bucket_of("v") != "b0f" else "b00")
    engine.process([(wrong, constant_measurement("v", 1).encode())])
    assert engine.rejected["malformed"] == 6 and engine.vehicles["v"].rejected["malformed"] == 4


def test_an_id_with_a_trailing_newline_registers_nothing(fast_gains):
    """'victim-01\\n' on its own key, with its own id in the payload: malformed, not a new vehicle."""
    engine = make_engine(fast_gains)
    vehicle_id = "victim-01\n"
    header = constant_measurement("x", 0).encode()[:MEASUREMENT_HEADER_SIZE]
    payload = header[:6] + len(vehicle_id).to_bytes(2, "little") + header[8:] + vehicle_id.encode()
    key = f"agv/v1/{bucket_of(vehicle_id)}/{vehicle_id}/meas"
    result = engine.process([(key, payload)])
    assert result.new_vehicles == [] and engine.vehicles == {} and engine.rejected["malformed"] == 1


def test_unknown_vehicles_are_registered_with_the_default_profile(fast_gains):
    engine = make_engine(fast_gains)
    result = engine.process(pairs([constant_measurement("new-1", 0)]))
    assert [v.id for v in result.new_vehicles] == ["new-1"] and engine.vehicles["new-1"].profile == "default"
    assert len(result.estimates) == 1


def test_duplicates_out_of_order_gaps_and_restarts(fast_gains):
    engine = make_engine(fast_gains, long_gap_s=0.5)
    m = lambda k: constant_measurement("v", k)  # noqa: E731
    engine.process(pairs([m(0), m(1), m(2)]))
    result = engine.process(pairs([m(2), m(1), m(3), m(3), m(6)]))
    assert [e.seq for e in decoded(result)] == [3, 6]
    v = engine.vehicles["v"]
    assert v.rejected["duplicate"] == 2 and v.rejected["out_of_order"] == 1
    assert v.counters["missing"] == 2 and v.counters["gaps"] == 1 and v.counters["restarts"] == 0
    engine.process(pairs([m(7)]))
    assert engine.banks["default"].started_t_ns[v.slot] == T0_NS  # observer running since seq 0
    engine.process(pairs([m(7 + 51)]))  # 50 missing samples = 0.5 s: re-initialise
    assert v.counters["restarts"] == 1 and engine.stats["restarts"] == 1
    assert engine.banks["default"].started_t_ns[v.slot] == T0_NS + 58 * PERIOD_NS
    # a vehicle that restarts its sequence says so with the flag
    restarted = Measurement("v", 0, T0_NS, 10.0, 0.0, 60.0, 0.0, flags=FLAG_SEQUENCE_RESTART)
    assert [e.seq for e in decoded(engine.process(pairs([restarted])))] == [0]
    assert engine.vehicles["v"].counters["restarts"] == 2


def test_one_forged_sequence_number_neither_blacks_out_the_vehicle_nor_counts_missing_samples(fast_gains):
    """The hardening issue's case: seq 2^64 - 1 put once on a vehicle's key, between its genuine samples. A jump
    the time stamps cannot carry is refused as implausible_seq and moves nothing; the genuine samples go on."""
    m = lambda k: constant_measurement("v", k)  # noqa: E731
    clean = make_engine(fast_gains)
    clean.process(pairs([m(k) for k in range(724)]))
    clean_after = decoded(clean.process(pairs([m(k) for k in range(724, 1000)])))
    engine = make_engine(fast_gains)
    engine.process(pairs([m(k) for k in range(724)]))
    forged = Measurement("v", (1 << 64) - 1, T0_NS + 724 * PERIOD_NS, 10.0, 0.0, 60.0, 0.0)
    assert engine.process(pairs([forged])).accepted == 0
    v = engine.vehicles["v"]
    assert v.rejected["implausible_seq"] == 1 and engine.rejected["implausible_seq"] == 1 and v.last_seq == 723
    after = decoded(engine.process(pairs([m(k) for k in range(724, 1000)])))
    assert after == clean_after and len(after) == 276  # every genuine sample observed, as if the forgery never came
    assert v.counters["missing"] == 0 and engine.stats["missing"] == 0 and v.rejected["out_of_order"] == 0
    assert engine.alarms.current("v", "sequence_rejected") is None


def test_a_sequence_jump_is_believed_as_far_as_the_time_stamps_carry_it(fast_gains):
    """A vehicle back after 5 s off the air (500 samples lost, 5 s of time stamps) is a gap, not a forgery; a jump
    within the slack needs no time at all; one beyond twice the elapsed time plus the slack is refused."""
    engine = make_engine(fast_gains, seq_jump_slack=100)
    m = lambda k: constant_measurement("v", k)  # noqa: E731
    engine.process(pairs([m(k) for k in range(10)]))
    v = engine.vehicles["v"]
    assert [e.seq for e in decoded(engine.process(pairs([m(510)])))] == [510]  # the time stamps moved 5 s
    assert v.counters["missing"] == 500 and v.counters["restarts"] == 1
    at_once = Measurement("v", 611, T0_NS + 510 * PERIOD_NS, 10.0, 0.0, 60.0, 0.0)  # 101 ahead, same time stamp
    assert engine.process(pairs([at_once])).accepted == 0 and v.rejected["implausible_seq"] == 1
    slack = Measurement("v", 610, T0_NS + 510 * PERIOD_NS, 10.0, 0.0, 60.0, 0.0)  # 100 ahead: within the slack
    assert [e.seq for e in decoded(engine.process(pairs([slack])))] == [610]
    # 2 x 10 samples of time plus 100 of slack: 120 ahead is believed, 121 is not
    too_far = Measurement("v", 610 + 121, T0_NS + 520 * PERIOD_NS, 10.0, 0.0, 60.0, 0.0)
    assert engine.process(pairs([too_far])).accepted == 0 and v.rejected["implausible_seq"] == 2
    just = Measurement("v", 610 + 120, T0_NS + 520 * PERIOD_NS, 10.0, 0.0, 60.0, 0.0)
    assert [e.seq for e in decoded(engine.process(pairs([just])))] == [730]
    assert v.counters["missing"] == 500 + 99 + 119 and v.rejected["out_of_order"] == 0


def test_samples_refused_as_late_in_a_row_raise_an_alarm_that_clears_when_they_are_accepted(fast_gains):
    """A forgery whose time stamp is as far ahead as its seq is believed; the genuine samples after it are then
    late, and a vehicle refused this way sequence_reject_count times in a row raises sequence_rejected (stored and
    published like every alarm change). It clears when the vehicle's samples are accepted in sequence again, here
    at its restart."""
    clock = FakeClock()
    engine = make_engine(fast_gains, clock, alarms={"sequence_reject_count": 20})
    m = lambda k: constant_measurement("v", k)  # noqa: E731
    engine.process(pairs([m(k) for k in range(50)]))
    forged = m(10**9)  # time stamp and seq agree: nothing tells it from a vehicle back after 115 days
    assert engine.process(pairs([forged])).accepted == 1
    result = engine.process(pairs([m(k) for k in range(50, 69)]))
    assert result.alarms == [] and engine.vehicles["v"].rejected["out_of_order"] == 19
    result = engine.process(pairs([m(69), m(70)]))
    assert [(c.event.kind, c.event.state, c.event.level) for c in result.alarms] == [
        ("sequence_rejected", "raised", "WARN")
    ]
    assert result.alarms[0].event.value == 20.0 and result.alarms[0].event.threshold == 20.0
    assert engine.process(pairs([m(k) for k in range(71, 90)])).alarms == []  # raised once, not per sample
    restarted = Measurement("v", 0, T0_NS + 90 * PERIOD_NS, 10.0, 0.0, 60.0, 0.0, flags=FLAG_SEQUENCE_RESTART)
    result = engine.process(pairs([restarted]))
    assert [(c.event.kind, c.event.state) for c in result.alarms] == [("sequence_rejected", "cleared")]
    assert [e.seq for e in decoded(result)] == [0]
    # a vehicle whose single late sample is followed by good ones raises nothing
    engine.process(pairs([constant_measurement("v", k) for k in (1, 2, 0, 3)]))
    assert engine.vehicles["v"].seq_rejects == 0 and engine.alarms.current("v", "sequence_rejected").state == "cleared"


def test_every_reject_reason_is_counted_by_name(fast_gains):
    engine = make_engine(fast_gains)
    assert set(engine.rejected) == set(REJECT_REASONS)
    assert set(engine.register("v", "default").rejected) == set(REJECT_REASONS)


def test_no_gains_yet_rejects_without_crashing(fast_gains):
    engine = FleetEngine(EngineConfig())
    engine.add_profile("default", ProfileSpec())
    result = engine.process(pairs([constant_measurement("v", 0)]))
    assert result.estimates == [] and engine.rejected["no_gains"] == 1 and not engine.ready
    engine.activate("default", fast_gains)
    assert engine.ready and len(engine.process(pairs([constant_measurement("v", 1)])).estimates) == 1


FAULT_ALARMS = {
    "torque_warn_nm": 10.0,
    "torque_fault_nm": 20.0,
    "raise_after_s": 0.2,
    "clear_after_s": 0.5,
    "warmup_s": 1.0,
    "out_of_domain_after_s": 0.2,
}


def run_scenario(engine, scenario, n_samples, vehicle="v"):
    changes = []
    for row in plant_measurements([vehicle], n_samples, scenario=scenario):
        changes.extend(engine.process(pairs(row)).alarms)
    return changes


def test_a_torque_fault_raises_warn_then_fault_and_a_healthy_vehicle_stays_quiet(fast_gains):
    faulty = make_engine(fast_gains, alarms=FAULT_ALARMS)
    changes = run_scenario(faulty, paper_1(), 900)  # 30 N m torque bias from t = 5 s
    torque = [c.event for c in changes if c.event.kind == "torque_fault"]
    assert torque[0].state == "raised" and torque[-1].level == "FAULT"
    assert len({a.id for a in torque}) == 1 and all(a.state == "raised" for a in torque)
    raised_at = (torque[0].t_ns - T0_NS) / 1e9
    assert 5.0 < raised_at < 7.0, raised_at
    assert faulty.level_of(faulty.vehicles["v"]) == "FAULT"

    healthy = make_engine(fast_gains, alarms=FAULT_ALARMS)
    assert run_scenario(healthy, paper_1().model_copy(update={"faults": ()}), 900) == []
    assert healthy.level_of(healthy.vehicles["v"]) == "OK"


def test_out_of_domain_needs_persistence_and_clears_with_hysteresis_time(fast_gains):
    # a jump of v_x reads as a huge torque fault to the observer; only the domain alarm matters here
    quiet_faults = {"torque_warn_nm": 1e9, "torque_fault_nm": 2e9, "steer_warn_rad": 1e3, "steer_fault_rad": 2e3}
    engine = make_engine(fast_gains, alarms={**FAULT_ALARMS, **quiet_faults})
    seq = iter(range(10_000))
    feed = lambda vx, n: [engine.process(pairs([constant_measurement("v", next(seq), vx=vx)])) for _ in range(n)]  # noqa: E731
    feed(10.0, 10)
    short = feed(40.0, 15)  # 0.15 s above v_x,max = 30 m/s: not long enough
    assert not any(r.alarms for r in short)
    feed(10.0, 5)
    long = [c.event for r in feed(40.0, 30) for c in r.alarms]
    assert [(a.kind, a.state, a.level) for a in long] == [("out_of_domain", "raised", "WARN")]
    back = [c.event for r in feed(10.0, 80) for c in r.alarms]
    assert [(a.kind, a.state) for a in back] == [("out_of_domain", "cleared")]
    assert engine.alarms.current("v", "out_of_domain").state == "cleared"  # latched until acknowledged
    change = engine.acknowledge(long[0].id, by="op")
    assert change.event.state == "acknowledged" and engine.alarms.current("v", "out_of_domain") is None


def test_stale_by_timeout_and_by_liveliness_then_resume(fast_gains):
    clock = FakeClock()
    engine = make_engine(fast_gains, clock=clock, alarms={"stale_after_s": 1.0})
    engine.process(pairs([constant_measurement("v", 0), constant_measurement("w", 0)]))
    clock.mono += 0.5
    assert engine.housekeeping() == []
    clock.mono += 0.6
    stale = engine.housekeeping()
    assert sorted((c.event.vehicle, c.event.level) for c in stale) == [("v", "STALE"), ("w", "STALE")]
    result = engine.process(pairs([constant_measurement("v", 1)]))
    assert [(c.event.kind, c.event.state) for c in result.alarms] == [("stale", "cleared")]
    assert engine.level_of(engine.vehicles["v"]) == "OK"
    lost = engine.liveliness("v", alive=False)
    assert [(c.event.kind, c.event.state) for c in lost] == [("stale", "raised")]


def test_a_vehicle_announced_through_the_api_is_not_stale_before_its_first_sample(fast_gains):
    clock = FakeClock()
    engine = make_engine(fast_gains, clock=clock, alarms={"stale_after_s": 1.0})
    engine.register("announced", "default", announced=True)
    engine.register("restored", "default", registered_t_ns=T0_NS)  # restored from storage: seen before, maybe
    clock.mono += 5.0
    assert [(c.event.vehicle, c.event.level) for c in engine.housekeeping()] == [("restored", "STALE")]
    # once it has sent something, silence makes it stale like any other vehicle
    engine.process(pairs([constant_measurement("announced", 0)]))
    clock.mono += 1.5
    assert [c.event.vehicle for c in engine.housekeeping()] == ["announced"]


def test_the_latest_estimate_carries_the_estimates_level_and_gain_set_not_the_vehicles_staleness():
    from synth.design import synthesize
    from synth.options import DesignOptions

    switched = synthesize(options=DesignOptions())
    clock = FakeClock()
    engine = make_engine(switched, clock=clock, alarms={"stale_after_s": 1.0})
    engine.process(pairs([constant_measurement("v", 0)]))
    vehicle = engine.vehicles["v"]
    latest = engine.latest_estimate(vehicle)
    assert latest is not None and latest.level == "OK" and latest.gain_set in ("fast", "quiet")
    clock.mono += 2.0
    engine.housekeeping()
    assert engine.level_of(vehicle) == "STALE"  # the vehicle is stale ...
    stale_latest = engine.latest_estimate(vehicle)
    assert stale_latest is not None and stale_latest.level == "OK"  # ... its last estimate was OK when made


def test_a_burst_of_rejected_inputs_raises_and_clears(fast_gains):
    clock = FakeClock()
    engine = make_engine(fast_gains, clock=clock, alarms={"reject_burst_count": 5, "reject_burst_window_s": 1.0})
    engine.process(pairs([constant_measurement("v", 0)]))
    result = engine.process(pairs([constant_measurement("v", k, vx=math.nan) for k in range(1, 6)]))
    assert [(c.event.kind, c.event.state) for c in result.alarms] == [("rejected_inputs", "raised")]
    clock.mono += 2.0
    engine.process(pairs([constant_measurement("v", 6)]))
    assert [(c.event.kind, c.event.state) for c in engine.housekeeping()] == [("rejected_inputs", "cleared")]


def test_estimate_every_n_publishes_a_subset_but_observes_every_sample(fast_gains):
    engine = make_engine(fast_gains, estimate_every_n=4)
    published = []
    for k in range(12):
        published += decoded(engine.process(pairs([constant_measurement("v", k)])))
    assert [e.seq for e in published] == [0, 4, 8]
    assert engine.vehicles["v"].counters["estimates"] == 12
    assert engine.vehicles["v"].counters["published"] == 3


def test_vehicles_that_register_together_publish_on_different_ticks(fast_gains):
    """Eight vehicles from the first tick, every 4th estimate: two per tick, each vehicle still every 4th."""
    engine = make_engine(fast_gains, estimate_every_n=4)
    ids = [f"v{i}" for i in range(8)]
    per_tick: list[list[Estimate]] = []
    for k in range(12):
        per_tick.append(decoded(engine.process(pairs([constant_measurement(v, k) for v in ids]))))
    assert [len(tick) for tick in per_tick] == [2] * 12
    for v in ids:
        seqs = [e.seq for tick in per_tick for e in tick if e.vehicle == v]
        assert len(seqs) == 3 and seqs[1] - seqs[0] == seqs[2] - seqs[1] == 4 and seqs[0] < 4
    assert sorted({e.seq % 4 for tick in per_tick for e in tick}) == [0, 1, 2, 3]


def test_counters_follow_a_vehicle_that_moves_to_another_profile(fast_gains):
    engine = make_engine(fast_gains, estimate_every_n=2)
    engine.add_profile("other", engine.banks["default"].spec)
    engine.activate("other", fast_gains)
    for k in range(5):
        engine.process(pairs([constant_measurement("v", k)]))
    moved = engine.register("v", "other")
    assert moved.counters["accepted"] == 5 and moved.counters["published"] == 3
    for k in range(5, 9):
        engine.process(pairs([constant_measurement("v", k)]))
    counters = engine.vehicles["v"].counters
    assert (counters["accepted"], counters["estimates"], counters["published"]) == (9, 9, 5)
    newcomer = engine.register("w", "default")  # the freed row starts from zero
    assert newcomer.slot == 0 and newcomer.counters["accepted"] == 0


def test_a_reported_payload_keeps_a_loaded_vehicles_accelerations_from_reading_as_a_torque_fault(fast_gains):
    """The profile's vehicle carrying 100 kg more (the project's plant, no fault): told the payload, the observer
    reads no torque fault; not told, it reads the accelerations as one (docs/math.md 12.5)."""
    p = VehicleParams()
    heavy = p.model_copy(update={"effective_mass_kg": p.effective_mass_kg + 100.0})
    samples = plant_measurements(["v"], 900, scenario=paper_1().model_copy(update={"vehicle": heavy, "faults": ()}))
    engine = make_engine(fast_gains)
    engine.register("told", "default")
    assert engine.set_payload("told", 100.0).payload_kg == 100.0
    engine.register("blind", "default")
    torque: dict[str, list[float]] = {"told": [], "blind": []}
    for (m,) in samples:
        for e in decoded(engine.process(pairs([dataclasses.replace(m, vehicle_id=v) for v in torque]))):
            torque[e.vehicle].append(e.torque_fault)
    told, blind = (np.abs(np.array(torque[v][300:])) for v in ("told", "blind"))
    assert len(told) == len(blind) == 600
    assert blind.mean() > 3.0 and told.max() < 0.05 * blind.mean()
    assert engine.vehicle_status(engine.vehicles["told"])["payload_kg"] == 100.0
    assert engine.vehicle_status(engine.vehicles["blind"])["payload_kg"] == 0.0


def test_a_payload_follows_its_vehicle_to_another_profile_and_a_bad_one_is_refused(fast_gains):
    engine = make_engine(fast_gains)
    engine.add_profile("other", engine.banks["default"].spec)
    engine.activate("other", fast_gains)
    vehicle = engine.register("v", "default")
    engine.set_payload("v", 250.0)
    assert engine.banks["default"].loaded_rows == 1
    moved = engine.register("v", "other")
    assert moved.bank.payload_kg[moved.slot] == 250.0 and engine.banks["other"].loaded_rows == 1
    assert engine.banks["default"].loaded_rows == 0 and vehicle.payload_kg == 250.0
    mass = engine.banks["other"].spec.params.mass_kg
    for bad in (-1.0, math.nan, math.inf, mass + 1.0):
        with pytest.raises(ValueError, match="payload_kg must be finite, >= 0 and at most the vehicle's mass"):
            engine.set_payload("v", bad)
    assert vehicle.payload_kg == 250.0
    with pytest.raises(UnknownVehicle):
        engine.set_payload("nobody", 10.0)
    engine.set_payload("v", 0.0)
    assert engine.banks["other"].loaded_rows == 0


def test_the_fleet_status_list_agrees_with_each_vehicles_own_state(fast_gains):
    """GET /vehicles reads each profile's arrays once for the whole list: every document must say what the
    vehicle's own accessors say, for a faulty, a healthy, a stale, a moved and a silent vehicle, in any order."""
    engine = make_engine(fast_gains, alarms=FAULT_ALARMS, estimate_every_n=2)
    engine.add_profile("other", engine.banks["default"].spec)
    engine.activate("other", fast_gains)
    run_scenario(engine, paper_1(), 900, vehicle="faulty")
    for k in range(7):
        engine.process(pairs([constant_measurement(v, k) for v in ("healthy", "lost", "moved")]))
    engine.liveliness("lost", alive=False)
    engine.register("moved", "other")
    engine.process(pairs([constant_measurement("moved", 7)]))
    engine.register("silent", "other")
    vehicles = [engine.vehicles[v] for v in ("silent", "moved", "faulty", "lost", "healthy")]
    statuses = engine.vehicle_statuses(vehicles)
    assert [s["id"] for s in statuses] == ["silent", "moved", "faulty", "lost", "healthy"]
    for vehicle, status in zip(vehicles, statuses, strict=True):
        assert status["level"] == engine.level_of(vehicle)
        assert status["counters"] == vehicle.counters
        assert status["gain_set"] == vehicle.bank.gain_set(vehicle.slot)
        assert status["profile"] == vehicle.profile and status["stale"] == vehicle.stale
        assert status == engine.vehicle_status(vehicle) | {"seconds_since_seen": status["seconds_since_seen"]}
    levels = {s["id"]: s["level"] for s in statuses}
    assert levels == {"silent": "OK", "moved": "OK", "faulty": "FAULT", "lost": "STALE", "healthy": "OK"}
    moved, silent = statuses[1], statuses[0]
    assert (moved["counters"]["accepted"], moved["counters"]["published"], moved["last_seq"]) == (8, 4, 7)
    assert silent["counters"]["accepted"] == 0 and silent["last_seq"] is None
    assert engine.vehicle_statuses([]) == []


def test_gain_activation_continues_from_the_last_estimate(fast_gains):
    engine = make_engine(fast_gains)
    samples = plant_measurements(["v"], 200)
    for row in samples[:150]:
        engine.process(pairs(row))
    before = engine.latest_estimate(engine.vehicles["v"])
    engine.activate("default", fast_gains)
    after = decoded(engine.process(pairs(samples[150])))[0]
    assert after.seq == 150
    assert abs(after.vx - before.vx) < 0.05 and abs(after.steer_fault - before.steer_fault) < 0.01


def test_events_reach_subscribers(fast_gains):
    async def scenario():
        engine = make_engine(fast_gains)
        with engine.events.subscribe(kinds=("estimate", "vehicle")) as sub:
            engine.process(pairs([constant_measurement("v", 0)]))
            events = [await asyncio.wait_for(sub.get(), 1.0), await asyncio.wait_for(sub.get(), 1.0)]
        return events, engine.events.has_subscribers

    events, still_subscribed = asyncio.run(scenario())
    assert [e.kind for e in events] == ["vehicle", "estimate"] and events[1].data.seq == 0
    assert not still_subscribed


#: Thresholds low enough, and persistence short enough, that the noisy fault estimates of the next test raise
#: alarms on both channels.
FLICKERING_ALARMS = {
    "stale_after_s": 0.5,
    "warmup_s": 0.2,
    "raise_after_s": 0.05,
    "clear_after_s": 0.1,
    "torque_warn_nm": 300.0,
    "torque_fault_nm": 900.0,
    "steer_warn_rad": 0.002,
    "steer_fault_rad": 0.006,
}


def test_the_tick_fast_path_gives_what_one_by_one_sequencing_gives(fast_gains, monkeypatch):
    """Pass 2 takes the common case (the next sample of a vehicle seen once in the tick) at once, and stepping has
    shortcuts for a tick of one sample per vehicle. A random stream of good samples, duplicates, reordering, gaps,
    long gaps, restarts, implausible values, huge sequence numbers and a stale vehicle, cut into random ticks, must
    give the same estimates, counters, rejects and alarms with and without them."""
    rng = np.random.default_rng(7)
    ids = [f"v{i}" for i in range(40)]
    next_seq = dict.fromkeys(ids, 0)
    stream: list[Measurement] = []
    for n in range(3000):
        v = ids[n % len(ids)] if rng.random() < 0.8 else ids[int(rng.integers(len(ids)))]  # mostly round robin
        k = next_seq[v]
        roll = rng.random()
        flags = 0
        if roll < 0.05:
            seq = max(k - 1, 0)  # duplicate (or the first sample again)
        elif roll < 0.09:
            seq = max(k - 3, 0)  # out of order
        elif roll < 0.13:
            seq = k + int(rng.integers(2, 80))  # a gap, sometimes long enough to re-initialise
        elif roll < 0.15:
            seq, flags = int(rng.integers(0, 5)), FLAG_SEQUENCE_RESTART  # the vehicle restarted
        elif roll < 0.153:
            seq = (1 << 63) + k  # beyond int64: the exact path
        else:
            seq = k
        vx = float("nan") if rng.random() < 0.02 else (500.0 if rng.random() < 0.02 else 10.0 + rng.normal())
        m = Measurement(v, seq, T0_NS + seq * PERIOD_NS % (1 << 62), vx, 0.01 * rng.normal(), 60.0, 0.0, flags=flags)
        stream.append(m)
        next_seq[v] = max(next_seq[v], seq + 1) if seq < (1 << 63) else next_seq[v]
    cuts = sorted({0, len(stream), *rng.integers(1, len(stream), 300).tolist()})

    def run(fast: bool) -> tuple[list, dict, dict, dict]:
        clock = FakeClock()
        engine = make_engine(fast_gains, clock, alarms=FLICKERING_ALARMS)
        engine._shortcuts = fast  # and the stepping's shortcuts for the common tick, on or off with it
        taken = engine._in_sequence

        def counted(vehicles, *args):  # with fast=False no frame takes the fast path
            chosen = taken(vehicles, *args) & fast
            through_fast.append((int(chosen.sum()), len(vehicles)))
            return chosen

        monkeypatch.setattr(engine, "_in_sequence", counted)
        through_fast: list[tuple[int, int]] = []
        out: dict[str, list[tuple]] = {v: [] for v in ids}  # each vehicle's estimates in the order made
        alarms: list[set[tuple]] = []  # per tick: (vehicle, kind, state) of every alarm change
        for a, b in itertools.pairwise(cuts):
            result = engine.process(pairs(stream[a:b]))
            for e in decoded(result):
                out[e.vehicle].append((e.seq, e.vx, e.torque_fault, e.level))
            alarms.append({(c.record.vehicle, c.record.kind, c.event.state) for c in result.alarms})
            clock.mono += 0.05
            if a == cuts[len(cuts) // 2]:
                clock.mono += 2.0  # every vehicle goes stale, and resumes with its next sample
                alarms.append({(c.record.vehicle, c.record.kind, c.event.state) for c in engine.housekeeping()})
        seen = set().union(*alarms)
        raised = {kind for _, kind, state in seen if state == "raised"}
        assert {"torque_fault", "steer_fault"} <= raised  # the fault channels' levels moved too
        assert {(v, "stale", "raised") for v in ids} <= seen and {(v, "stale", "cleared") for v in ids} <= seen
        counters = {
            v: (engine.vehicle(v).counters, engine.vehicle(v).rejected, engine.vehicle(v).stale)
            for v in ids
            if v in engine.vehicles
        }
        fraction = sum(k for k, _ in through_fast) / sum(n for _, n in through_fast)
        assert (0.3 < fraction < 0.95) if fast else fraction == 0.0, fraction  # both paths were exercised
        return out, dict(engine.stats), dict(engine.rejected), counters, alarms

    fast_run, slow_run = run(True), run(False)
    assert sum(map(len, fast_run[0].values())) > 1000
    for v in ids:  # the same samples answered in the same order; values up to the GEMM's rounding (other batches)
        fast_v, slow_v = fast_run[0][v], slow_run[0][v]
        assert [(k, level) for k, _, _, level in fast_v] == [(k, level) for k, _, _, level in slow_v]
        np.testing.assert_allclose(
            [x[1:3] for x in fast_v],
            [x[1:3] for x in slow_v],
            rtol=AMPLIFIED_ROUNDING_RTOL,
            atol=AMPLIFIED_ROUNDING_ATOL,
        )
    assert fast_run[1:] == slow_run[1:]
    rejected = fast_run[2]
    assert all(rejected[r] > 0 for r in ("duplicate", "out_of_order", "non_finite", "out_of_range"))
    assert fast_run[1]["gaps"] > 0 and fast_run[1]["restarts"] > 0


def _hill(n_samples: int, p: VehicleParams) -> tuple[list[list[Measurement]], np.ndarray]:
    """The project's plant climbing and descending (paper scenario 1 without its faults): a road grade theta(t)
    acts on the vehicle as the torque fault -R_w M_v g sin(theta) (docs/math.md 12.6). The samples, and theta."""
    from edge_client.faults import SinusoidalFault, fault_tables
    from synth.params import STANDARD_GRAVITY_MPS2

    pull = SinusoidalFault(channel="torque", amplitude=60.0, omega_radps=0.8, offset=-80.0, phase_from_zero=True)
    t = np.arange(n_samples) * p.sample_period_s
    grade = np.arcsin(-fault_tables((pull,), t)[0][:, 0] / (p.wheel_radius_m * p.mass_kg * STANDARD_GRAVITY_MPS2))
    samples = plant_measurements(["v"], n_samples, scenario=paper_1().model_copy(update={"faults": (pull,)}))
    return samples, grade


def test_a_road_grade_in_the_measurement_keeps_a_hill_from_reading_as_a_torque_fault(fast_gains):
    """A vehicle on a hill (the project's plant, no fault) that sends the grade (flag bit 1): the observer reads no
    torque fault; one that does not, reads the grade's pull as one; a grade beyond the profile's limit, or not
    finite, is refused by name (docs/protocol.md)."""
    p = VehicleParams()
    samples, grade = _hill(900, p)
    engine = make_engine(fast_gains)
    torque: dict[str, list[float]] = {"told": [], "blind": []}
    for k, (m,) in enumerate(samples):
        told = dataclasses.replace(m, vehicle_id="told", grade_rad=float(grade[k]))
        blind = dataclasses.replace(m, vehicle_id="blind")
        for e in decoded(engine.process(pairs([told, blind]))):
            torque[e.vehicle].append(e.torque_fault)
    told_t, blind_t = (np.abs(np.array(torque[v][300:])) for v in ("told", "blind"))
    assert len(told_t) == len(blind_t) == 600
    assert blind_t.mean() > 20.0 and told_t.max() < 0.05 * blind_t.mean()
    assert sum(engine.rejected.values()) == 0
    told_v, blind_v = engine.vehicles["told"], engine.vehicles["blind"]
    status = engine.vehicle_status(told_v)
    assert (status["grade_rad"], status["grade_seq"], status["last_seq"]) == (float(grade[-1]), 899, 899)
    assert (engine.vehicle_status(blind_v)["grade_rad"], engine.vehicle_status(blind_v)["grade_seq"]) == (None, None)
    steep = dataclasses.replace(samples[0][0], vehicle_id="told", seq=900, timestamp_ns=T0_NS + 900 * PERIOD_NS)
    engine.process(pairs([dataclasses.replace(steep, grade_rad=0.5)]))
    engine.process(pairs([dataclasses.replace(steep, grade_rad=math.nan)]))
    assert told_v.rejected["out_of_range"] == 1
    assert told_v.rejected["non_finite"] == 1
    # a refused grade is not the vehicle's grade; a sample without one leaves the last one shown, with its seq
    assert engine.vehicle_status(told_v)["grade_seq"] == 899
    engine.process(pairs([steep]))
    status = engine.vehicle_status(told_v)
    assert (status["grade_rad"], status["grade_seq"], status["last_seq"]) == (float(grade[-1]), 899, 900)
    # a grade of exactly 0 (level ground, flag bit 1) is a grade sent
    level = dataclasses.replace(steep, seq=901, timestamp_ns=T0_NS + 901 * PERIOD_NS, grade_rad=0.0)
    engine.process(pairs([level]))
    status = engine.vehicle_status(told_v)
    assert (status["grade_rad"], status["grade_seq"], status["last_seq"]) == (0.0, 901, 901)


def test_a_loaded_vehicle_on_a_hill_told_both_reads_no_torque_fault(fast_gains):
    """The payload and the grade together (docs/math.md 12.5, 12.6): the project's plant carrying 100 kg on a hill,
    the weight's pull being (M_v + 100) g sin(theta); told the payload and sent the grade, the observer reads no
    torque fault; told only one of them, it reads the other."""
    from edge_client.faults import SinusoidalFault, fault_tables
    from synth.params import STANDARD_GRAVITY_MPS2

    p = VehicleParams()
    weight_torque = p.wheel_radius_m * (p.mass_kg + 100.0) * STANDARD_GRAVITY_MPS2
    pull = SinusoidalFault(channel="torque", amplitude=60.0, omega_radps=0.8, offset=-80.0, phase_from_zero=True)
    heavy = p.model_copy(update={"effective_mass_kg": p.effective_mass_kg + 100.0})
    samples = plant_measurements(
        ["v"], 900, scenario=paper_1().model_copy(update={"vehicle": heavy, "faults": (pull,)})
    )
    t = np.arange(900) * p.sample_period_s
    grade = np.arcsin(-fault_tables((pull,), t)[0][:, 0] / weight_torque)
    engine = make_engine(fast_gains)
    for v in ("both", "payload-only"):
        engine.register(v, "default")
        engine.set_payload(v, 100.0)
    torque: dict[str, list[float]] = {"both": [], "payload-only": [], "grade-only": []}
    for k, (m,) in enumerate(samples):
        frames = [dataclasses.replace(m, vehicle_id=v, grade_rad=None if v == "payload-only" else float(grade[k]))
                  for v in torque]  # fmt: skip
        for e in decoded(engine.process(pairs(frames))):
            torque[e.vehicle].append(e.torque_fault)
    rms = {v: float(np.sqrt(np.mean(np.square(torque[v][300:])))) for v in torque}
    assert all(len(torque[v]) == 900 for v in torque)
    assert rms["both"] < 0.05 * min(rms["payload-only"], rms["grade-only"]), rms


def test_a_payload_with_the_effectiveness_stage_scales_the_torque_bias_and_total_not_alpha(robust_gains_default):
    """With the stage on, a loaded vehicle's row steps the stage on the payload torque too: its estimates are the
    offline stage's on that torque, the torque bias and total fault divided by rho, alpha as it is."""
    from synth.effectiveness import EffectivenessObserver
    from synth.model import payload_torque
    from tests.synth.test_effectiveness import OPTIONS, torque_loss_scenario
    from tests.tolerances import STAGE_BATCH_ATOL

    p = VehicleParams()
    scenario = torque_loss_scenario()
    loaded = p.model_copy(update={"effective_mass_kg": p.effective_mass_kg + 90})
    heavy = scenario.model_copy(update={"vehicle": loaded})
    samples = plant_measurements(["v"], 1500, scenario=heavy)
    clock = FakeClock()
    engine = FleetEngine(EngineConfig(), clock_ns=clock.ns, monotonic=clock.monotonic)
    spec = ProfileSpec.model_validate({"design": {"design": "robust"}, "effectiveness": OPTIONS.model_dump()})
    engine.add_profile("default", spec)
    engine.activate("default", robust_gains_default)
    engine.register("v", "default")
    engine.set_payload("v", 90.0)
    got = [e for (m,) in samples for e in decoded(engine.process(pairs([m])))]
    assert [e.seq for e in got] == list(range(1500))
    y = np.array([[m.vx_mps, m.r_radps] for (m,) in samples])
    u = np.array([[m.torque_nm, m.steer_rad] for (m,) in samples])
    torque, rho = payload_torque(y[:, 0], u[:, 0], 90.0, robust_gains_default.params)
    model_u = np.column_stack([torque, u[:, 1]])
    offline = EffectivenessObserver(robust_gains_default, OPTIONS, y[:1], None, model_u[:1])
    expected = [offline.step(y[k : k + 1], model_u[k : k + 1]) for k in range(1500)]
    bias = np.vstack([s.bias for s in expected])
    total = np.vstack([s.faults for s in expected])
    bias[:, 0] /= rho
    total[:, 0] /= rho
    np.testing.assert_allclose([[e.torque_bias, e.steer_bias] for e in got], bias, atol=STAGE_BATCH_ATOL)
    np.testing.assert_allclose([[e.torque_fault, e.steer_fault] for e in got], total, atol=STAGE_BATCH_ATOL)
    alpha = np.vstack([s.alpha for s in expected])
    np.testing.assert_allclose([[e.torque_alpha, e.steer_alpha] for e in got], alpha, atol=STAGE_BATCH_ATOL)
    assert float(rho) == pytest.approx(p.effective_mass_kg / (p.effective_mass_kg + 90.0))


def test_a_held_vehicles_stored_payload_applies_when_its_profile_runs(fast_gains):
    engine = make_engine(fast_gains)
    engine.hold("later-1", "late", 5)
    assert engine.load_payloads({"later-1": 40.0, "nobody": 10.0}) == []
    assert engine.held_payloads == {"later-1": 40.0}
    engine.add_profile("late", engine.banks["default"].spec)
    engine.activate("late", fast_gains)
    (released,) = engine.release_held("late")
    assert released.payload_kg == 40.0 and released.bank.payload_kg[released.slot] == 40.0
    assert engine.held_payloads == {}
    # a stored payload heavier than the vehicle is reported, not applied
    mass = engine.banks["default"].spec.params.mass_kg
    engine.register("v", "default")
    (problem,) = engine.load_payloads({"v": mass + 1.0})
    assert problem.startswith("v: stored payload not applied") and engine.vehicles["v"].payload_kg == 0.0


def test_a_vehicle_s_status_says_whether_its_faults_were_judged_and_why_not(fast_gains):
    """A profile whose cornering limit is 0.05 g, a vehicle in a 0.1 g turn (10 m/s at 0.1 rad/s, well inside the
    certified domain) and one driving straight: during the 3 s warm-up neither is judged (the turning one beyond
    grip too); after it the straight one is, the turning one is not, beyond grip; a registered vehicle without an
    estimate yet has no answer. The documents are what GET /vehicles/{id} answers (VehicleStatus validates
    them)."""
    engine = make_engine(fast_gains, alarms={"grip_cornering_g": 0.05})
    engine.register("idle", "default")
    assert engine.vehicle_status(engine.vehicles["idle"])["faults_judged"] is None

    def statuses() -> dict[str, tuple[bool | None, list[str]]]:
        out = {}
        for name in ("turning", "straight", "idle"):
            status = VehicleStatus(**engine.vehicle_status(engine.vehicles[name]))
            out[name] = (status.faults_judged, list(status.unjudged_because))
        return out

    for k in range(40):
        engine.process(pairs([constant_measurement("turning", k, r=0.1), constant_measurement("straight", k)]))
    assert statuses() == {
        "turning": (False, ["warm-up", "beyond grip"]),
        "straight": (False, ["warm-up"]),
        "idle": (None, []),
    }
    for k in range(40, 350):
        engine.process(pairs([constant_measurement("turning", k, r=0.1), constant_measurement("straight", k)]))
    assert statuses() == {"turning": (False, ["beyond grip"]), "straight": (True, []), "idle": (None, [])}
