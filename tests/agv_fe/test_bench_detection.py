"""The detection benchmark (agv_fe/benchmarks/detection.py): one quick run shared by the report tests, and the
counting and delay paths on constructed estimate sequences whose answers are known.

The quick run (about a minute on 2 cores) calibrates the car, drives a few vehicle-minutes of healthy fleet,
two runs per fault case and two short drives of multi-body set 1.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import pytest

from agv_fe.benchmarks import detection as bench
from agv_fe.commands.bench import BENCHMARKS, register
from service.fleet.alarms import FAULT, OK, WARN
from service.profiles import AlarmThresholds
from tests.agv_fe.markdown import assert_rows_match_headers
from tests.tolerances import SAMPLE_GRID_ATOL_S

SET = 1
CHANNELS = ("torque", "steer")
ESTIMATORS = ("observer", "EKF")
SECTIONS = (
    "## Must show",
    "## Current figures",
    "## Calibrated profile",
    "## Healthy fleet on the project's plant",
    "## Healthy driving on the multi-body plant",
    "## Detection delay against fault size",
    "## Loss of effectiveness: the alpha rule",
    "## Operating curve",
    "## How it was measured",
    "## Earlier runs",
)
PERIOD_S = 0.01


@pytest.fixture(scope="module")
def outcome(tmp_path_factory):
    out = tmp_path_factory.mktemp("detection")
    path = bench.run(out, parameter_sets=(SET,), quick=True)
    return path, path.read_text(), json.loads((out / "detection.json").read_text())


def _is_count(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


# --------------------------------------------------------------------------- the report


def test_registered_and_writes_report_json_and_figure(outcome):
    path, text, document = outcome
    assert BENCHMARKS["detection"] == "agv_fe.benchmarks.detection"
    assert path.name == "detection.md"
    png = path.parent / "detection.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    positions = [text.find(section) for section in SECTIONS]
    assert all(p >= 0 for p in positions), dict(zip(SECTIONS, positions, strict=True))
    assert positions == sorted(positions), "sections out of order"
    assert text.startswith("# Detection at fleet scale") and "Measured " in text.split("## Must show")[0]
    assert "agv-fe bench --only detection" in text.split("## Must show")[0]
    assert "](detection.png)" in text
    assert "Parameter set 2 is never used here" in text
    assert document["plan"]["quick"] is True and document["plan"]["multibody"]["parameter_sets"] == [SET]
    # the calibrated profile carries the block sigmas, so the service's CUSUM rule runs beside the thresholds
    assert document["plan"]["cusum_rule"] is True and "CUSUM rule" in text
    assert document["timings"]["total_s"] > 0


def test_every_table_row_has_the_header_s_columns(outcome):
    """A stray '|' in a cell (|a_y|, |estimate|) would shift a markdown table's columns."""
    _, text, _ = outcome
    assert_rows_match_headers(text, at_least=7, rows_required=True)


def test_healthy_counts_are_counts_consistent_with_the_vehicle_hours(outcome):
    _, _, document = outcome
    healthy = document["healthy"]
    plan = document["plan"]["healthy"]
    warmup_s = document["calibration"]["alarms"]["warmup_s"]
    assert healthy["vehicles"] == plan["vehicles"] == bench.QUICK_HEALTHY_VEHICLES
    assert healthy["duration_s"] == pytest.approx(bench.QUICK_HEALTHY_DURATION_S)
    for name in ESTIMATORS:
        figures = healthy[name]
        expected_hours = figures["vehicles"] * (healthy["duration_s"] - warmup_s) / 3600.0
        assert figures["hours"] == pytest.approx(expected_hours)
        assert set(figures["rules"]) >= {"default", "cusum"} | {f"x{f:g}" for f in bench.THRESHOLD_FACTORS if f != 1.0}
        for rule in figures["rules"].values():
            for channel in CHANNELS:
                c = rule["channels"][channel]
                for key in ("warn_raised", "fault_raised", "warn_raised_near_gust", "vehicles_with_warn"):
                    assert _is_count(c[key]), (name, channel, key, c[key])
                assert c["hours"] == pytest.approx(expected_hours)
                assert c["warn_per_1000_h"] == pytest.approx(1000.0 * c["warn_raised"] / expected_hours)
                assert c["fault_per_1000_h"] == pytest.approx(1000.0 * c["fault_raised"] / expected_hours)
                # at least the rule of three: 3 / H for none, more for more
                assert c["warn_upper95_per_1000_h"] >= max(c["warn_per_1000_h"], 2.99 * 1000.0 / expected_hours)
                assert c["warn_raised_near_gust"] <= c["warn_raised"]
                assert c["vehicles_with_warn"] <= min(c["warn_raised"], figures["vehicles"])
        assert 0.0 <= figures["in_domain_share"] <= 1.0


def test_the_alpha_rule_counts_over_the_observer_s_hours_with_the_profile_s_thresholds(outcome):
    """The effectiveness rule on the healthy fleet: counts over the observer's vehicle-hours, its thresholds the
    profile's alpha thresholds, its peak a loss 1 - alpha_hat; the headline table lists both channels."""
    _, text, document = outcome
    alpha, observer = document["healthy"][bench.ALPHA], document["healthy"]["observer"]
    rule = document["plan"]["effectiveness"]
    assert alpha["hours"] == pytest.approx(observer["hours"]) and set(alpha["rules"]) == {"default"}
    for channel in CHANNELS:
        c = alpha["rules"]["default"]["channels"][channel]
        assert _is_count(c["warn_raised"]) and _is_count(c["fault_raised"])
        assert c["warn_per_1000_h"] == pytest.approx(1000.0 * c["warn_raised"] / alpha["hours"])
        assert (c["warn_threshold"], c["fault_threshold"]) == (rule["warn_below"], rule["fault_below"])
    assert all(0.0 <= peak < 1.0 for peak in alpha["peak_abs_estimate"])
    headline = text.split("## Current figures")[1].split("## Calibrated profile")[0]
    assert "Effectiveness alarm rule" in headline and "| delta_f |" in headline
    for case in document["faults"]["cases"].values():
        stats = case[bench.ALPHA]["default"]
        assert stats["warn"]["runs"] == stats["fault"]["runs"] == case["runs"]
        assert 0.0 <= stats["warn"]["never_share"] <= stats["fault"]["never_share"] <= 1.0


def test_the_healthy_fleet_counts_the_stage_s_bias_jump_detections(outcome):
    """The stage's bias-jump test on the healthy fleet (docs/math.md section 14): the calibrated car tests the
    steering only (its gust barely moves the torque estimate), the detections are counted per channel, and the
    effectiveness part's report gives them per vehicle-hour beside the design's rate."""
    _, _, document = outcome
    stage = document["plan"]["effectiveness"]["stage"]
    detections = document["healthy"][bench.ALPHA]["jump_detections"]
    assert stage["torque_jump_nm"] == 0.0 and stage["steer_jump_rad"] > 0.0
    assert len(detections) == 2 and all(_is_count(n) for n in detections) and detections[0] == 0
    made_up = {"healthy": {"hours": 2.0, bench.ALPHA: {"jump_detections": [0, 600]}}, "plan": document["plan"]}
    line = bench._jump_lines(made_up)[-1]
    expected = 3600.0 / stage["jump_false_alarm_interval_s"]
    assert "0 / 300 detections per vehicle-hour T_f / delta_f (0 / 600)" in line and f"{expected:g} per hour" in line


def test_multibody_counts_are_consistent_with_the_drives(outcome):
    _, _, document = outcome
    (result,) = document["multibody"]
    assert result["parameter_set"] == SET and result["refused"] is None
    assert result["drives"] == bench.QUICK_MB_DRIVES
    warmup_s = document["calibration"]["alarms"]["warmup_s"]
    assert result["hours_after_warmup"] == pytest.approx(result["drives"] * (result["drive_s"] - warmup_s) / 3600)
    for name in ESTIMATORS:
        for c in result[name]["channels"].values():
            assert _is_count(c["warn_raised"]) and _is_count(c["fault_raised"])
            assert c["warn_upper95_per_1000_h"] == pytest.approx(
                1000.0 * bench.poisson_upper_95(c["warn_raised"]) / result["hours_after_warmup"]
            )


def test_fault_cases_have_their_runs_and_ordered_delays(outcome):
    _, _, document = outcome
    cases = document["faults"]["cases"]
    assert list(cases) == [case.key for case in bench.FAULT_CASES] and len(cases) == 18
    nominal = document["calibration"]["nominal_torque_nm"]
    assert cases["steer_bias_10"]["magnitude"] == pytest.approx(0.02)
    assert cases["torque_bias_10"]["magnitude"] == pytest.approx(0.1 * nominal)
    for case in cases.values():
        assert case["runs"] == bench.QUICK_VEHICLES_PER_CASE
        low, high = case["onset_range_s"]
        assert bench.ONSET_RANGE_S[0] <= low <= high <= bench.ONSET_RANGE_S[1]
        for name in ESTIMATORS:
            for rule in case[name].values():
                for level in ("warn", "fault"):
                    stats = rule[level]
                    assert stats["runs"] == case["runs"] and 0.0 <= stats["never_share"] <= 1.0
                    known = [stats[k] for k in ("p50_s", "p95_s") if stats[k] is not None]
                    assert known == sorted(known)
                    assert all(0.0 <= v <= stats["worst_detected_s"] for v in known)
                assert _is_count(rule["warn_before_onset"]) and _is_count(rule["other_warn_raised"])
                assert rule["runs_with_other_alarm"] <= min(case["runs"], rule["other_warn_raised"])


def test_must_show_lines_follow_the_figures(outcome):
    _, text, document = outcome
    lines = document["must_show"]
    judged = [line for line in lines if line["judged"]]
    assert [line["target"][:7] for line in judged] == ["at most", "a 10 % "]
    observer = document["healthy"]["observer"]["rules"]["default"]["channels"]
    assert judged[0]["passed"] is all(
        c["warn_per_1000_h"] <= bench.FALSE_WARN_PER_1000_H and c["fault_raised"] == 0 for c in observer.values()
    )
    bias = [document["faults"]["cases"][f"{c}_bias_10"]["observer"]["default"]["warn"] for c in CHANNELS]
    assert judged[1]["passed"] is all(s["p95_s"] is not None and s["p95_s"] <= bench.BIAS_P95_WARN_S for s in bias)
    must_show = text.split("## Must show")[1].split("## Current figures")[0]
    for line in lines:
        label = f"| {bench._rule_label(line['estimator'], line['rule'])} |"
        (row,) = [r for r in must_show.splitlines() if line["figure"] in r and label in r and line["target"] in r]
        verdict = row.rstrip(" |").rsplit("|", 1)[1].strip()
        if line["judged"]:
            assert verdict == ("pass" if line["passed"] else "**FAIL**")
        else:
            assert verdict == f"shown: {'pass' if line['passed'] else 'fail'}"


def test_operating_curve_is_the_rules_figures(outcome):
    _, _, document = outcome
    for name in ESTIMATORS:
        for channel in CHANNELS:
            points = document["operating_curve"][name][channel]
            assert [p["factor"] for p in points] == sorted(bench.THRESHOLD_FACTORS)
            thresholds = [p["warn_threshold"] for p in points]
            assert thresholds == sorted(thresholds)
            (default,) = [p for p in points if p["factor"] == 1.0]
            rates = document["healthy"][name]["rules"]["default"]["channels"][channel]
            assert default["warn_raised"] == rates["warn_raised"]
            delay = document["faults"]["cases"][f"{channel}_bias_10"][name]["default"]["warn"]["p95_s"]
            assert default["bias_p95_warn_s"] == delay


# --------------------------------------------------------------------------- counting and delays, constructed


ALARMS = AlarmThresholds(
    torque_warn_nm=10.0,
    torque_fault_nm=20.0,
    steer_warn_rad=0.01,
    steer_fault_rad=0.02,
    hysteresis=0.8,
    raise_after_s=0.5,
    clear_after_s=1.0,
    warmup_s=3.0,
)


def _samples(t0_s: float, t1_s: float) -> slice:
    return slice(round(t0_s / PERIOD_S), round(t1_s / PERIOD_S))


def test_counting_path_counts_raised_levels_of_a_known_sequence():
    """Six vehicles, 15 s, each with an estimate whose raised levels are known from the rule."""
    f_hat = np.zeros((1500, 6, 2))
    # 0: two torque excursions above WARN, each held for > 0.5 s, apart by more than the 1 s clearing time
    f_hat[_samples(5.0, 7.0), 0, 0] = 15.0
    f_hat[_samples(10.0, 11.0), 0, 0] = -15.0
    # 1: above WARN for 0.4 s only: shorter than the persistence
    f_hat[_samples(5.0, 5.4), 1, 0] = 15.0
    # 2: above FAULT for 2 s: OK to FAULT in one step, which raises both; then 2 s between hysteresis x WARN
    #    and hysteresis x FAULT (8 and 16 N m): FAULT drops to WARN, which raises nothing
    f_hat[_samples(5.0, 7.0), 2, 0] = 25.0
    f_hat[_samples(7.0, 9.0), 2, 0] = 12.0
    # 3: a steering excursion during the warm-up only
    f_hat[_samples(0.0, 2.9), 3, 1] = 0.015
    # 4: a steering WARN that dips below the threshold but above hysteresis x threshold (0.008), then below it
    #    for 0.5 s (shorter than the clearing time): one raise
    f_hat[_samples(5.0, 12.0), 4, 1] = 0.015
    f_hat[_samples(7.0, 7.3), 4, 1] = 0.0085
    f_hat[_samples(9.0, 9.5), 4, 1] = 0.001
    # 5: non-finite estimates above WARN are not fed to the levels
    f_hat[_samples(5.0, 7.0), 5, 0] = np.nan
    f_hat[_samples(5.0, 7.0), 5, 1] = 0.05
    counter = bench.count_raises(f_hat, ALARMS, PERIOD_S)
    assert counter.warn_raised.tolist() == [[2, 0], [0, 0], [1, 0], [0, 0], [0, 1], [0, 0]]
    assert counter.fault_raised.tolist() == [[0, 0], [0, 0], [1, 0], [0, 0], [0, 0], [0, 0]]
    # and the levels it ends with: 2 dropped one level per clearing time, back to OK
    assert counter.level.tolist() == [[OK, OK]] * 6


def test_tally_counts_the_same_as_the_counter_and_splits_alarms_near_gusts():
    """The fleet's per-sample path (Tally over the rules) on the same kind of sequence: two vehicles with one
    WARN each, one of them in a gust; the scaled rule at x2 sees only the larger excursion."""
    rules = bench.rule_set(ALARMS, factors=(2.0,))
    tally = bench.Tally.make(2, rules)
    tally.restart(0)
    f_hat = np.zeros((800, 2, 2))
    f_hat[_samples(4.0, 5.0), 0, 0] = 15.0  # above WARN at x1, below it at x2 (20)
    f_hat[_samples(4.0, 5.0), 1, 1] = 0.025  # above WARN at x1 and x2
    gust = np.array([False, True])
    for k in range(f_hat.shape[0]):
        t_ns = k * round(PERIOD_S * 1e9)
        tally.update(f_hat[k], np.ones(2, dtype=bool), t_ns, t_ns >= 3e9, gust, lambda row: {"vehicle": row})
    summary = tally.summary()
    default, doubled = summary["rules"]["default"], summary["rules"]["x2"]
    assert default["warn_raised"] == [1, 1] and default["warn_raised_near_gust"] == [0, 1]
    assert default["fault_raised"] == [0, 1] and default["fault_raised_near_gust"] == [0, 1]
    assert doubled["warn_raised"] == [0, 1] and doubled["fault_raised"] == [0, 0]
    assert [(e["vehicle"], e["channel"], e["level"]) for e in summary["events"]] == [
        (0, "torque", "WARN"),
        (1, "steer", "FAULT"),
    ]
    assert summary["samples_after_warmup"] == 2 * 500
    assert summary["peak_abs"] == [15.0, 0.025]


def test_delays_are_measured_from_the_onset():
    """A step of 15 N m at the onset (WARN 10, persistence 0.5 s) reaches WARN 0.5 s after it, whatever the
    onset; an earlier excursion is reported as an alarm before the onset, not as a delay."""
    onset = np.array([5.0, 7.37, 9.0, 6.0])
    channel = np.array([0, 0, 1, 0], dtype=np.intp)
    f_hat = np.zeros((1500, 4, 2))
    for i, start in enumerate(onset[:2]):
        f_hat[round(start / PERIOD_S) :, i, 0] = 15.0
    f_hat[round(9.0 / PERIOD_S) :, 2, 1] = 0.05  # steering above FAULT from the onset
    f_hat[_samples(4.0, 5.0), 3, 0] = 15.0  # torque WARN before the onset, nothing after
    counter = bench.RaiseCounter(4, ALARMS)
    counter.restart(0)
    tracker = bench.DelayTracker(onset, channel)
    for k in range(f_hat.shape[0]):
        counter.update(f_hat[k], k * round(PERIOD_S * 1e9))
        tracker.update(round(k * PERIOD_S, 9), counter.level)
    warn, fault = tracker.warn_delay_s, tracker.fault_delay_s
    assert warn[:3] == pytest.approx([0.5, 0.5, 0.5], abs=PERIOD_S + SAMPLE_GRID_ATOL_S)
    assert (
        math.isnan(fault[0])
        and math.isnan(fault[1])
        and fault[2] == pytest.approx(0.5, abs=PERIOD_S + SAMPLE_GRID_ATOL_S)
    )
    assert tracker.before_onset.tolist() == [False, False, False, True]
    # vehicle 3's WARN cleared before its onset (1 s below 8 N m): never detected after it
    assert math.isnan(warn[3])
    assert counter.level[2, 1] == FAULT and counter.level[0, 0] == WARN


def test_the_alpha_rule_counts_raised_levels_of_a_known_sequence():
    """The effectiveness rule (alpha held below 0.9 for 1 s: WARN, below 0.75: FAULT) through the same counter and
    delay tracker: a loss to 0.85 held 1.5 s, one to 0.7 held 2 s, one to 0.85 held 0.8 s, and a gain to 1.2."""
    alarms = ALARMS.model_copy(
        update={"effectiveness_warn": 0.9, "effectiveness_fault": 0.75, "effectiveness_after_s": 1.0}
    )
    alpha = np.ones((1500, 4, 2))
    alpha[_samples(5.0, 6.5), 0, 0] = 0.85
    alpha[_samples(5.0, 7.0), 1, 1] = 0.7
    alpha[_samples(5.0, 5.8), 2, 0] = 0.85
    alpha[_samples(5.0, 9.0), 3, :] = 1.2
    counter = bench.RaiseCounter(4, alarms, effectiveness=True)
    counter.restart(0)
    tracker = bench.DelayTracker(np.full(4, 5.0), np.array([0, 1, 0, 0], dtype=np.intp))
    for k in range(alpha.shape[0]):
        counter.update(alpha[k], k * round(PERIOD_S * 1e9))
        tracker.update(round(k * PERIOD_S, 9), counter.level)
    assert counter.warn_raised.tolist() == [[1, 0], [0, 1], [0, 0], [0, 0]]
    assert counter.fault_raised.tolist() == [[0, 0], [0, 1], [0, 0], [0, 0]]
    assert tracker.warn_delay_s[:2] == pytest.approx([1.0, 1.0], abs=PERIOD_S + SAMPLE_GRID_ATOL_S)
    assert math.isnan(tracker.warn_delay_s[2]) and math.isnan(tracker.fault_delay_s[0])


def test_the_alpha_rule_counts_only_what_its_confidence_bound_identifies():
    """The same counter fed alpha_hat 0.8 for 2 s with the stage's sigma: the service's rule (k = 3 by default)
    counts the vehicle whose bound 0.8 + 3 sigma is below 0.9 and not the one whose sigma leaves it above."""
    alpha = np.ones((500, 2, 2))
    alpha[_samples(1.0, 3.0)] = 0.8
    sigma = np.zeros((2, 2))
    sigma[0], sigma[1] = 0.01, 0.05  # bounds 0.83 and 0.95
    counter = bench.RaiseCounter(2, ALARMS, effectiveness=True)
    counter.restart(0)
    for k in range(alpha.shape[0]):
        counter.update(alpha[k], k * round(PERIOD_S * 1e9), None, sigma)
    assert ALARMS.effectiveness_confidence_k == 3.0
    assert counter.warn_raised.tolist() == [[1, 1], [0, 0]] and counter.fault_raised.sum() == 0


def test_the_bench_command_runs_the_effectiveness_part_with_its_options():
    from agv_fe.commands.bench import _options

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    args = parser.parse_args(["bench", "--only", "detection"])
    assert _options("detection", args) == ("run", {})
    part = ["--detection-part", "effectiveness", "--detection-hours", "50", "--detection-runs", "60"]
    args = parser.parse_args(["bench", *part, "--detection-confidence-k", "0"])
    assert _options("detection", args) == (
        "run_effectiveness",
        {"vehicle_hours": 50.0, "vehicles_per_case": 60, "confidence_k": 0.0},
    )
    assert callable(bench.run_effectiveness)
    with pytest.raises(ValueError, match="vehicle_hours must be > 0"):
        bench.run_effectiveness(Path("unused"), vehicle_hours=0.0)


def test_delay_statistics_rank_the_undetected_runs_last():
    stats = bench.delay_stats([1.0, 2.0, None, 0.5])
    assert stats == {"runs": 4, "p50_s": 1.0, "p95_s": None, "worst_detected_s": 2.0, "never_share": 0.25}
    stats = bench.delay_stats([0.1 * i for i in range(1, 21)])
    assert stats["p50_s"] == pytest.approx(1.0) and stats["p95_s"] == pytest.approx(1.9)
    assert stats["never_share"] == 0.0 and stats["worst_detected_s"] == pytest.approx(2.0)
    assert bench.poisson_upper_95(0) == pytest.approx(2.996, abs=1e-3)
