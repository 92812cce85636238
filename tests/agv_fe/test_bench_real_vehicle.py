"""The real-vehicle benchmark (agv_fe/benchmarks/real_vehicle.py) in quick mode on parameter set 1.

One run (about 35 s on 2 cores) shared by the tests of this module: the report and its JSON exist, carry
the expected sections, and their figures agree with each other and with the rules they state.
"""

from __future__ import annotations

import copy
import json
import math
import re

import numpy as np
import pytest

from agv_fe.benchmarks import real_vehicle as bench
from agv_fe.commands.bench import BENCHMARKS
from edge_client import multibody as mb
from service.calibration import DECAY_RATE_CANDIDATES
from tests.agv_fe.markdown import assert_rows_match_headers
from tests.tolerances import SAMPLE_GRID_ATOL_S

SET = 1
LEVELS = ("OK", "WARN", "FAULT")
ESTIMATORS = ("calibrated", "EKF", "paper")
SECTIONS = (
    "## Must show",
    f"## Parameter set {SET}",
    "### Calibration",
    "### Healthy driving",
    "### Sensitivity to the calibration drive",
    "### Faults",
    "## How it was measured",
)


@pytest.fixture(scope="module")
def outcome(tmp_path_factory):
    out = tmp_path_factory.mktemp("real_vehicle")
    path = bench.run(out, parameter_sets=(SET,), quick=True)
    return path, path.read_text(), json.loads((out / "real_vehicle.json").read_text())


@pytest.fixture(scope="module")
def figures(outcome):
    _, _, document = outcome
    (result,) = document["sets"]
    return result


def _is_count(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def test_registered_and_writes_report_and_json_beside_it(outcome):
    path, text, document = outcome
    assert BENCHMARKS["real_vehicle"] == "agv_fe.benchmarks.real_vehicle"
    assert path.name == "real_vehicle.md" and (path.parent / "real_vehicle.json").is_file()
    positions = [text.find(section) for section in SECTIONS]
    assert all(p >= 0 for p in positions), dict(zip(SECTIONS, positions, strict=True))
    assert positions == sorted(positions), "sections out of order: must-show first, how-measured last"
    assert text.startswith("# Real vehicle") and "Measured " in text.split("## Must show")[0]
    assert "agv-fe bench --only real_vehicle" in text
    assert "Parameter set 2 is never used here" in text
    assert document["plan"]["parameter_sets"] == [SET] and document["plan"]["quick"] is True
    assert document["runtime_s"] > 0


def test_every_table_row_has_the_header_s_columns(outcome):
    """A stray '|' in a cell (|a_y|, |estimate|) would shift a markdown table's columns."""
    _, text, _ = outcome
    assert_rows_match_headers(text, at_least=5)


def test_must_show_has_a_line_per_target_matching_the_json(outcome, figures):
    _, text, _ = outcome
    must_show = text.split("## Must show")[1].split("## Parameter set")[0]
    rows = [line for line in must_show.splitlines() if line.startswith(f"| {SET} |")]
    assert len(rows) == len(figures["must_show"])
    targets = [
        "effective_mass_kg within 1 %",
        "front_cornering_stiffness_npr within 5 %",
        "rear_cornering_stiffness_npr within 5 %",
        "healthy driving: no WARN and no FAULT",
        *(case.label for case in bench.FAULT_CASES if case.target is not None),
        "the other channel stays OK",
        "sensitivity: no alarm on healthy driving with any of the random-drive calibrations",
        "torque loss of effectiveness, effectiveness stage",
        "torque loss of effectiveness: alpha_hat within 3 %",
        "steering (shown) loss of effectiveness, effectiveness stage",
        "steering (shown) loss of effectiveness: alpha_hat within 3 %",
        "payload reported, healthy driving",
        "payload not reported, healthy driving",
        f"payload reported, {bench.FAULT_CASES[0].label} (",
        "calibration loaded, the payload stated",
    ]
    for target in targets:
        matching = [row for row in rows if row.startswith(f"| {SET} | {target}")]
        assert len(matching) == 1, (target, rows)
    for row, line in zip(rows, figures["must_show"], strict=True):
        verdict = row.rstrip(" |").rsplit("|", 1)[1].strip()
        assert verdict == ("shown" if line["passed"] is None else "pass" if line["passed"] else "**FAIL**"), row
        assert line["target"] in row and line["figure"] in row


def test_calibration_figures_against_the_plant(figures):
    cal = figures["calibration"]
    reference = mb.reference_values(SET)
    rows = {row["name"]: row for row in cal["parameters"]}
    for name, tolerance in (
        ("effective_mass_kg", bench.EFFECTIVE_MASS_TOLERANCE),
        ("front_cornering_stiffness_npr", bench.CORNERING_STIFFNESS_TOLERANCE),
        ("rear_cornering_stiffness_npr", bench.CORNERING_STIFFNESS_TOLERANCE),
    ):
        row = rows[name]
        low, high = row["ci95"]
        assert low <= row["value"] <= high
        assert row["reference"] == pytest.approx(reference[name])
        assert row["error"] == pytest.approx(row["value"] / reference[name] - 1.0)
        assert row["passed"] is (abs(row["error"]) <= tolerance)
    noise = cal["summary"]["sensor_noise"]
    assert noise["vx_sigma_mps"] == pytest.approx(mb.DEFAULT_SPEED_SIGMA_MPS, rel=0.2)
    assert noise["r_sigma_radps"] == pytest.approx(mb.DEFAULT_YAW_RATE_SIGMA_RADPS, rel=0.2)
    assert 0.9 < cal["design"]["certified_decay_rate"] < 1.0 and cal["design"]["gain_version"]
    for table in (cal["summary"]["thresholds"], cal["ekf_thresholds"]):
        for channel in ("torque", "steer"):
            assert 0 < table[channel]["warn"] < table[channel]["fault"]
    alarms = cal["alarms"]
    assert alarms["torque_warn_nm"] == cal["summary"]["thresholds"]["torque"]["warn"]
    assert alarms["steer_fault_rad"] == cal["summary"]["thresholds"]["steer"]["fault"]


def test_every_third_healthy_drive_is_in_town_and_every_one_after_brakes_in_turns():
    """Seeds 3, 6, 9... drive at 6-12 m/s with corners up to 0.65 rad/s (seed 9's reaches 0.64 rad/s at 7 m/s^2,
    beyond the open roads' 0.5 rad/s); seeds 1, 4, 7... brake and accelerate in turns, 4, 10, 16... hard (beyond
    the grip limit); seed 2 drives on open roads, its speed changes on straights."""
    town, road = bench.healthy_drive(9, 60.0), bench.healthy_drive(2, 60.0)
    assert bench.URBAN_SPEED_MPS[0] <= town.speed_mps.min() and town.speed_mps.max() <= bench.URBAN_SPEED_MPS[1]
    assert 0.6 < np.abs(town.yaw_rate_radps).max() <= bench.URBAN_YAW_RATE_RADPS
    assert np.abs(road.yaw_rate_radps).max() <= 0.5 and road.speed_mps.min() >= 8.0

    def combined_share(drive: object) -> float:
        a_y = np.abs(drive.speed_mps * drive.yaw_rate_radps)  # type: ignore[attr-defined]
        return float(np.mean((np.abs(drive.accel_mps2) > 1.5) & (a_y > 1.5)))  # type: ignore[attr-defined]

    assert combined_share(road) == 0.0
    for seed, lateral, accel in (
        (7, bench.COMBINED_LATERAL_ACCEL_MPS2, bench.COMBINED_ACCEL_MPS2),
        (4, bench.HARD_COMBINED_LATERAL_ACCEL_MPS2, bench.HARD_COMBINED_ACCEL_MPS2),
    ):
        combined = bench.healthy_drive(seed, 60.0)
        assert combined.name == f"combined_{seed}" and combined_share(combined) > 0.2
        a_y = np.abs(combined.speed_mps * combined.yaw_rate_radps)
        assert lateral[1] - 1.0 < a_y.max() <= lateral[1] + 1e-9
        assert accel - 1.0 < np.abs(combined.accel_mps2).max() <= accel + 1e-6


def test_a_drive_on_a_slippery_road_asks_for_every_acceleration_times_its_friction():
    """grip 0.6 (a wet road): the hard combined drive's turns and speed changes, the town's and the open road's
    turns all stay under 0.6 of the dry road's limits; grip 1 is the dry drive itself."""
    same, dry4 = bench.healthy_drive(4, 60.0, 1.0), bench.healthy_drive(4, 60.0)
    assert np.array_equal(same.yaw_rate_radps, dry4.yaw_rate_radps) and np.array_equal(same.accel_mps2, dry4.accel_mps2)
    for seed, lateral, accel in (
        (4, bench.HARD_COMBINED_LATERAL_ACCEL_MPS2[1], bench.HARD_COMBINED_ACCEL_MPS2),
        (9, bench.MAX_LATERAL_ACCEL_MPS2, bench.RANDOM_ACCEL_MPS2),
        (2, bench.MAX_LATERAL_ACCEL_MPS2, bench.RANDOM_ACCEL_MPS2),
    ):
        dry, wet = bench.healthy_drive(seed, 60.0), bench.healthy_drive(seed, 60.0, 0.6)
        a_y = np.abs(wet.speed_mps * wet.yaw_rate_radps)
        assert a_y.max() <= 0.6 * lateral + 1e-9 and np.abs(wet.accel_mps2).max() <= 0.6 * accel + 1e-6
        assert a_y.max() < np.abs(dry.speed_mps * dry.yaw_rate_radps).max()


def test_healthy_counts_are_consistent(figures):
    healthy = figures["healthy"]
    driving = healthy["driving"]
    assert driving["drives"] == len(bench.QUICK_HEALTHY_SEEDS)
    assert driving["minutes"] == pytest.approx(len(bench.QUICK_HEALTHY_SEEDS) * bench.QUICK_HEALTHY_DURATION_S / 60)
    assert 0 < driving["peak_lateral_accel_mps2"] < 12
    for name in ESTIMATORS:
        result = healthy[name]
        assert _is_count(result["non_finite_samples"])
        assert 0.0 <= result["in_domain_share"] <= 1.0
        # the levels judge only samples after the warm-up (3 s of each 30 s drive at least), never more
        assert 0.0 < result["assessed_share"] <= 1.0 - 3.0 / bench.QUICK_HEALTHY_DURATION_S + 1e-9
        for channel, c in result["channels"].items():
            assert _is_count(c["warn_raised"]) and _is_count(c["fault_raised"]), (name, channel, c)
            assert 0 <= c["held_peak_abs_estimate"] <= c["peak_abs_estimate"]
            assert 0 <= c["rms_estimate"] <= c["peak_abs_estimate"]
            events = [e for e in result["events"] if e["channel"] == channel]
            # every raise to WARN is its own event; a raise to FAULT may share the sample of one
            assert c["warn_raised"] <= len(events) <= c["warn_raised"] + c["fault_raised"]
            assert all(e["level"] in ("WARN", "FAULT") for e in events)
            if c["held_peak_abs_estimate"] < c["warn_threshold"]:
                assert c["warn_raised"] == 0  # nothing held above WARN for the persistence time, nothing raised
            for e in events:  # a level is raised on a sample whose estimate is at or above its threshold
                threshold = c["fault_threshold"] if e["level"] == "FAULT" else c["warn_threshold"]
                assert abs(e["estimate"]) >= threshold, (name, e)
        assert sorted({e["seed"] for e in result["events"]}) == result["drives_with_alarm"]
    paper = healthy["paper"]["channels"]
    assert (paper["torque"]["warn_threshold"], paper["torque"]["fault_threshold"]) == (40.0, 80.0)
    line = next(m for m in figures["must_show"] if m["target"].startswith("healthy driving"))
    cal = healthy["calibrated"]["channels"].values()
    assert line["passed"] is all(c["warn_raised"] == 0 and c["fault_raised"] == 0 for c in cal)


def _check_fault_seed(s, warn_threshold, persistence_s, where):
    """One seed of a fault case: positive delays (or never), FAULT after WARN, the persistence time, its figures,
    and a level trace that agrees with the delays."""
    warn, fault = s["warn_delay_s"], s["fault_delay_s"]
    assert warn is None or warn > 0, (*where, s)
    assert fault is None or fault > 0, (*where, s)
    at_onset = next(p for p in s["time_course"] if p["offset_s"] == 0.0)
    if s["level_before_onset"] == "OK" and abs(at_onset["estimate"]) < warn_threshold and warn is not None:
        # below WARN at the onset: the level needs the condition held for the persistence time from then
        assert warn >= persistence_s - SAMPLE_GRID_ATOL_S, (*where, s)
    if warn is not None and fault is not None:
        assert fault >= warn
    if fault is not None:
        assert warn is not None
    assert s["level_before_onset"] in LEVELS and s["other_channel_level"] in LEVELS
    assert s["rmse_after_onset"] >= 0 and math.isfinite(s["rmse_after_onset"])
    assert s["demand_rms_after_onset"] > 0 and s["true_fault_peak_abs"] > 0
    assert [p["offset_s"] for p in s["time_course"]] == list(bench.TIME_COURSE_OFFSETS_S)
    # the delays agree with the level trace: OK after the onset until the first WARN, raised there
    for p in s["time_course"]:
        if p["offset_s"] < 0 or s["level_before_onset"] != "OK":
            continue
        if warn is None or p["offset_s"] < warn - SAMPLE_GRID_ATOL_S:
            assert p["level"] == "OK", (*where, p, warn)
        elif fault is not None and p["offset_s"] >= fault:
            assert p["level"] in ("WARN", "FAULT")


def test_fault_delays_are_positive_or_never_and_verdicts_follow_them(outcome, figures):
    _, text, _ = outcome
    persistence_s = figures["calibration"]["alarms"]["raise_after_s"]
    alarms = {"calibrated": figures["calibration"]["alarms"], "EKF": figures["calibration"]["ekf_alarms"]}
    for case in bench.FAULT_CASES:
        entry = figures["faults"][case.key]
        assert entry["channel"] == case.channel
        for name in ("calibrated", "EKF"):
            seeds = entry[name]["seeds"]
            assert [s["seed"] for s in seeds] == list(bench.QUICK_FAULT_SEEDS)
            warn_threshold = alarms[name][f"{case.channel}_warn_{'nm' if case.channel == 'torque' else 'rad'}"]
            for s in seeds:
                _check_fault_seed(s, warn_threshold, persistence_s, (case.key, name))
            target = case.target
            if target is None:
                assert entry[name]["meets_target"] is None
                continue

            def within(delay, limit):
                return limit is None or (delay is not None and delay <= limit)

            expected = all(
                s["level_before_onset"] == "OK"
                and within(s["warn_delay_s"], target.warn_s)
                and within(s["fault_delay_s"], target.fault_s)
                and (not target.other_channel_ok or s["other_channel_level"] == "OK")
                for s in seeds
            )
            assert entry[name]["meets_target"] is expected, (case.key, name)
    bias = figures["faults"]["torque_bias_plus"]
    assert bias["magnitude"]["magnitude"] == pytest.approx(
        bench.TORQUE_SHARE * figures["calibration"]["summary"]["nominal_torque_nm"]
    )
    # the report prints the delays as numbers or 'never', nothing else
    faults = text.split("### Faults")[1].split("## How it was measured")[0]
    for row in faults.splitlines():
        if row.startswith("| torque bias +10 %"):
            warn_cell = row.split("|")[4].strip()
            assert re.fullmatch(r"(\d+\.\d\d|never)( / (\d+\.\d\d|never))*", warn_cell), row


def test_refuses_unknown_sets_before_simulating(tmp_path):
    with pytest.raises(mb.MultibodyError, match="parameter_set"):
        bench.run(tmp_path, parameter_sets=(7,), quick=True)
    with pytest.raises(ValueError, match="distinct"):
        bench.run(tmp_path, parameter_sets=(1, 1), quick=True)
    assert not (tmp_path / "real_vehicle.md").exists()


def test_a_refused_calibration_is_reported_as_a_failed_target(outcome):
    """A set whose calibration raised keeps its place in the report, with the reason and a FAIL line."""
    _, _, document = outcome
    reason = "CalibrationRefused: no acceleration: only 2 windows"
    refused = document | {"sets": [*document["sets"], bench.refused_set(9, reason)]}
    text = bench.render(refused)
    assert (
        "## Parameter set 9" in text
        and f"Calibration failed, so nothing else was evaluated on this set: {reason}" in text
    )
    (row,) = [line for line in text.splitlines() if line.startswith("| 9 |")]
    assert reason in row and row.rstrip(" |").endswith("**FAIL**")


def _same_drive(a: mb.Drive, b: mb.Drive) -> bool:
    return a.name == b.name and all(
        np.array_equal(getattr(a, field), getattr(b, field)) for field in ("speed_mps", "accel_mps2", "curvature_1pm")
    )


def test_calibrates_from_the_scripted_drive(outcome, figures):
    _, text, document = outcome
    job = bench.calibration_job(SET)
    assert _same_drive(job.drive, mb.calibration_drive())
    assert (job.parameter_set, job.seed) == (SET, bench.CALIBRATION_SEED_OFFSET + SET)
    drive = figures["calibration"]["drive"]
    assert drive["name"] == "calibration" and drive["noise_seed"] == bench.CALIBRATION_SEED_OFFSET + SET
    assert drive["duration_s"] == pytest.approx(mb.calibration_drive().n_samples * mb.SAMPLE_PERIOD_S)
    assert document["plan"]["calibration"]["noise_seeds"] == [bench.CALIBRATION_SEED_OFFSET + SET]
    assert document["plan"]["sensitivity"] == {"seeds": list(bench.QUICK_SENSITIVITY_SEEDS), "duration_s": 120.0}
    calibration = text.split("### Calibration")[1].split("| parameter |")[0]
    assert "`calibration_drive()`" in calibration and f"sensor noise seed {drive['noise_seed']}" in calibration
    assert "excites the lateral dynamics the cornering stiffnesses are identified from" in calibration


def test_sensitivity_runs_the_random_drives_of_the_plan():
    plan = bench.Plan.make((SET,), quick=True, workers=1)
    assert plan.sensitivity_seeds == bench.QUICK_SENSITIVITY_SEEDS == (200,)
    assert bench.Plan.make((SET,), quick=False, workers=1).sensitivity_seeds == (200, 201, 202)
    jobs = bench.sensitivity_jobs(SET, plan)
    assert [(job.seed, job.parameter_set) for job in jobs] == [(200, SET)]
    expected = mb.random_drive(200, 120.0, max_lateral_accel_mps2=bench.MAX_LATERAL_ACCEL_MPS2)
    assert _same_drive(jobs[0].drive, expected)
    with pytest.raises(ValueError, match="sensitivity_seeds"):
        bench.Plan.make((SET,), quick=True, workers=1, sensitivity_seeds=())


def _check_row(row):
    assert row["duration_s"] == pytest.approx(120.0)
    assert 0 < row["peak_lateral_accel_mps2"] < 12 and row["seconds_above_5_mps2"] >= 0
    assert row["refused"] is None
    for name in bench.SENSITIVITY_PARAMETERS:
        low, high = row["error_ci95"][name]
        assert low <= row["errors"][name] <= high, (name, row)
    assert row["robust_decay_rate"] in DECAY_RATE_CANDIDATES
    alarms = row["alarms"]
    assert 0 < alarms["torque_warn_nm"] < alarms["torque_fault_nm"]
    assert 0 < alarms["steer_warn_rad"] < alarms["steer_fault_rad"]
    for channel in ("torque", "steer"):
        c = row["healthy"][channel]
        assert _is_count(c["warn_raised"]) and _is_count(c["fault_raised"]) and c["held_peak_over_warn"] >= 0
        if c["held_peak_over_warn"] < 1:
            assert c["warn_raised"] == 0, (channel, row)
    raised = sum(row["healthy"][c]["warn_raised"] + row["healthy"][c]["fault_raised"] for c in ("torque", "steer"))
    assert (raised == 0) is (row["drives_with_alarm"] == [])


def test_sensitivity_rows_are_consistent_with_the_primary_figures(figures):
    sensitivity = figures["sensitivity"]
    random = sensitivity["random"]
    assert [row["seed"] for row in random] == list(bench.QUICK_SENSITIVITY_SEEDS)
    assert [row["drive"] for row in random] == [f"random_{seed}" for seed in bench.QUICK_SENSITIVITY_SEEDS]
    for row in (sensitivity["primary"], *random):
        _check_row(row)
    # the first row is the scripted calibration everything else is measured with
    primary, cal = sensitivity["primary"], figures["calibration"]
    assert (primary["drive"], primary["seed"]) == ("calibration", cal["drive"]["noise_seed"])
    parameters = {row["name"]: row for row in cal["parameters"]}
    for name in bench.SENSITIVITY_PARAMETERS:
        assert primary["errors"][name] == pytest.approx(parameters[name]["error"])
    assert primary["robust_decay_rate"] == cal["design"]["robust_decay_rate"]
    assert primary["alarms"]["torque_warn_nm"] == cal["alarms"]["torque_warn_nm"]
    assert primary["alarms"]["steer_warn_rad"] == cal["alarms"]["steer_warn_rad"]
    healthy = figures["healthy"]["calibrated"]["channels"]
    for channel in ("torque", "steer"):
        assert primary["healthy"][channel]["warn_raised"] == healthy[channel]["warn_raised"]
        assert primary["healthy"][channel]["fault_raised"] == healthy[channel]["fault_raised"]
    line = next(m for m in figures["must_show"] if m["target"].startswith("sensitivity:"))
    quiet = all(
        row["healthy"][c]["warn_raised"] == 0 and row["healthy"][c]["fault_raised"] == 0
        for row in random
        for c in ("torque", "steer")
    )
    assert line["passed"] is quiet
    assert all(row["drive"] in line["figure"] for row in random)


def test_sensitivity_table_shows_every_calibration(outcome, figures):
    _, text, _ = outcome
    section = text.split("### Sensitivity to the calibration drive")[1].split("### Faults")[0]
    rows = [
        line for line in section.splitlines() if line.startswith("| ") and not line.startswith("| calibration drive")
    ]
    sensitivity = figures["sensitivity"]
    expected = [sensitivity["primary"], *sensitivity["random"]]
    assert len(rows) == len(expected)
    assert rows[0].startswith("| calibration (scripted, seed 101) |")
    for line, row in zip(rows, expected, strict=True):
        cells = [cell.strip() for cell in line.strip("|").split("|")]
        assert cells[0].startswith(row["drive"])
        for cell, name in zip(cells[2:5], bench.SENSITIVITY_PARAMETERS, strict=True):
            assert cell.startswith(f"{100 * row['errors'][name]:+.2f} %"), (cell, name)
        assert cells[5] == f"{row['robust_decay_rate']:g}"
        torque, steer = row["healthy"]["torque"], row["healthy"]["steer"]
        assert cells[8:10] == [
            f"{torque['warn_raised']} / {torque['fault_raised']}",
            f"{steer['warn_raised']} / {steer['fault_raised']}",
        ]
        assert cells[-1] == "-"
    primary_stiffness = [100 * sensitivity["primary"]["errors"][n] for n in bench.SENSITIVITY_PARAMETERS[1:]]
    assert f"came out {min(primary_stiffness):+.1f} % to {max(primary_stiffness):+.1f} % of the slope" in text


def test_sensitivity_line_fails_on_an_alarm_or_a_refused_calibration(outcome, figures):
    _, _, document = outcome
    rows = figures["sensitivity"]["random"]
    quiet = copy.deepcopy(rows[0])
    for c in ("torque", "steer"):
        quiet["healthy"][c] |= {"warn_raised": 0, "fault_raised": 0}
    assert bench.sensitivity_line([quiet], 2.0)["passed"] is True
    noisy = copy.deepcopy(quiet)
    noisy["healthy"]["steer"]["warn_raised"] = 1
    line = bench.sensitivity_line([quiet, noisy], 2.0)
    assert line["passed"] is False and "delta_f 1 WARN / 0 FAULT" in line["figure"]
    reason = "CalibrationRefused: no cornering: 3.1 s above 1.5 m/s^2"
    refused = {key: quiet[key] for key in ("drive", "seed", "duration_s", "peak_lateral_accel_mps2")} | {
        "seconds_above_5_mps2": 0.0,
        "refused": reason,
    }
    line = bench.sensitivity_line([quiet, refused], 2.0)
    assert line["passed"] is False and "refused" in line["figure"]
    assert bench.sensitivity_line([], 2.0)["passed"] is False
    # the report shows the refusal's reason in its row and the must-show line as failed
    (result,) = document["sets"]
    changed = copy.deepcopy(result)
    changed["sensitivity"]["random"] = [refused]
    changed["must_show"] = bench.must_show(changed)
    text = bench.render(document | {"sets": [changed]})
    (row,) = [line for line in text.splitlines() if line.startswith(f"| {quiet['drive']} |")]
    assert row.rstrip(" |").endswith(reason)
    (must,) = [line for line in text.splitlines() if line.startswith(f"| {SET} | sensitivity:")]
    assert must.rstrip(" |").endswith("**FAIL**")


def test_the_effectiveness_stage_is_measured_beside_the_additive_design(figures):
    for result in (figures,):
        for key in ("torque_loss", "steer_loss"):
            entry = result["faults"][key]
            stage, additive = entry["effectiveness"]["seeds"], entry["calibrated"]["seeds"]
            assert len(stage) == len(additive) >= 1
            for s, a in zip(stage, additive, strict=True):
                assert 0.0 <= s["alpha_after_ramp"] <= 1.5 and s["alpha_true"] == bench.LOSS_ALPHA_MIN
                assert s["rmse_after_onset"] > 0 and a["rmse_after_onset"] > 0
        (line,) = [m for m in result["must_show"] if m["target"].startswith("torque loss of effectiveness: alpha")]
        alphas = [s["alpha_after_ramp"] for s in result["faults"]["torque_loss"]["effectiveness"]["seeds"]]
        assert line["passed"] is all(abs(a - bench.LOSS_ALPHA_MIN) <= 0.03 * bench.LOSS_ALPHA_MIN for a in alphas)


def test_a_payload_calibrated_empty_is_driven_without_it_and_told_it(outcome, figures):
    """The loaded drives: the vehicle's mass plus a tenth (the MB's own parameters), the same drives estimated
    blind and told; told, no alarm and the torque bias found in time (the plan's must-show), blind shown."""
    _, text, _ = outcome
    load = figures["payload"]
    assert load["payload_kg"] == pytest.approx(0.1 * mb.vehicle_parameters(SET).m)
    assert load["driving"]["drives"] == 1 and load["fault"]["label"] == bench.FAULT_CASES[0].label
    for name in ("blind", "told"):
        for c in ("torque", "steer"):
            assert _is_count(load[name]["channels"][c]["warn_raised"])
    # the not-told torque channel reads the accelerations: its held peak well above the told one's
    held = {name: load[name]["channels"]["torque"]["held_peak_abs_estimate"] for name in ("blind", "told")}
    assert held["blind"] > 2.0 * held["told"]
    lines = [m for m in figures["must_show"] if "payload" in m["target"]]
    assert [m["passed"] for m in lines][1] is None and len(lines) == 4
    assert lines[0]["passed"] == all(
        load["told"]["channels"][c][k] == 0 for c in ("torque", "steer") for k in ("warn_raised", "fault_raised")
    )
    assert lines[2]["passed"] == load["fault"]["meets_target"]
    assert f"### Set {SET}: a payload, calibrated empty" in text
    # the calibration drive loaded, calibrated told the payload, against the empty calibration: the vehicle
    # without the payload comes back (the effective mass within its interval, not a tenth heavier)
    calibration = load["calibration"]
    assert calibration["refused"] is None and calibration["drive"] == "calibration"
    rows = {row["name"]: row for row in calibration["parameters"]}
    assert {"effective_mass_kg", "front_cornering_stiffness_npr", "rear_cornering_stiffness_npr"} <= set(rows)
    inside = [row["level_ci95"][0] <= row["value"] <= row["level_ci95"][1] for row in rows.values()]
    assert lines[3]["passed"] == all(inside)
    assert rows["effective_mass_kg"]["value"] == pytest.approx(rows["effective_mass_kg"]["level"], rel=0.02)
    assert "Calibrated loaded instead" in text and "| parameter | loaded | empty (95 % interval) |" in text
    loaded = mb.loaded_parameters(SET, 100.0)
    assert loaded.m == pytest.approx(mb.vehicle_parameters(SET).m + 100.0) and loaded.a == mb.vehicle_parameters(SET).a
    with pytest.raises(mb.MultibodyError, match="payload_kg must be finite"):
        mb.loaded_parameters(SET, -1.0)


def test_hills_are_driven_without_the_grade_and_told_it(outcome, figures):
    """The drives on hills: the same healthy drive on a road that climbs and descends, estimated blind and told
    the reported grade; told, no alarm and the torque bias found in time (the plan's must-show), blind shown."""
    _, text, _ = outcome
    hills = figures["hills"]
    assert hills["road_max_grade_rad"] == mb.HILL_GRADE_RAD
    assert 0.02 < hills["max_reported_grade_rad"] <= mb.HILL_GRADE_RAD + 6 * mb.DEFAULT_GRADE_SIGMA_RAD
    assert hills["driving"]["drives"] == 1 and hills["fault"]["label"] == bench.FAULT_CASES[0].label
    # the not-told torque channel reads the grade's pull: its held peak well above the told one's
    held = {name: hills[name]["channels"]["torque"]["held_peak_abs_estimate"] for name in ("blind", "told")}
    assert held["blind"] > 2.0 * held["told"]
    lines = [m for m in figures["must_show"] if "grade" in m["target"]]
    assert len(lines) == 4 and lines[1]["passed"] is None
    assert lines[0]["passed"] == all(
        hills["told"]["channels"][c][k] == 0 for c in ("torque", "steer") for k in ("warn_raised", "fault_raised")
    )
    assert lines[2]["passed"] == hills["fault"]["meets_target"]
    assert f"### Set {SET}: hills" in text
    # the calibration drive on hills, calibrated with the grade, against the level-ground calibration
    calibration = hills["calibration"]
    assert calibration["refused"] is None and calibration["drive"].endswith("_hills")
    rows = {row["name"]: row for row in calibration["parameters"]}
    assert {"effective_mass_kg", "front_cornering_stiffness_npr", "rear_cornering_stiffness_npr"} <= set(rows)
    assert set(rows) <= set(bench.REFERENCES)
    level = {row["name"]: row["value"] for row in figures["calibration"]["parameters"]}
    assert all(rows[name]["level"] == level[name] for name in rows)
    inside = [row["level_ci95"][0] <= row["value"] <= row["level_ci95"][1] for row in rows.values()]
    assert lines[3]["passed"] == all(inside)
    assert "Calibrated on hills instead" in text


def test_a_hill_pulls_the_multibody_vehicle_back_by_g_sin_grade():
    """multibody.on_hills: the grade's force acts on the whole mass through the MB's own equation for v_x. With
    the speed controller's feed-forward of the grade, the demanded torque follows R_w m g sin(grade); the reported
    grade is the drive's plus the sensor's noise; level ground draws no extra noise (the runs stay as they were)."""
    drive = mb.straight_drive(15.0, 40.0)
    hilly = mb.on_hills(drive, np.random.default_rng(3))
    assert hilly.grade_rad is not None and np.abs(hilly.grade_rad).max() > 0.01
    run = mb.simulate(hilly, SET, seed=4)
    level = mb.simulate(drive, SET, seed=4)
    p = mb.vehicle_parameters(SET)
    pull = p.R_w * p.m * mb.GRAVITY_MPS2 * np.sin(hilly.grade_rad)
    late = slice(1000, None)  # after the controller's integral settled
    assert np.abs(run.u[late, 0] - level.u[late, 0] - pull[late]).mean() < 0.05 * np.abs(pull[late]).mean()
    assert run.grade_rad is not None and level.grade_rad is None
    noise = run.grade_rad - hilly.grade_rad
    assert 0.5 * mb.DEFAULT_GRADE_SIGMA_RAD < noise.std() < 1.5 * mb.DEFAULT_GRADE_SIGMA_RAD
    np.testing.assert_array_equal(level.y, mb.simulate(drive, SET, seed=4).y)
    with pytest.raises(mb.MultibodyError, match="max_grade_rad"):
        mb.on_hills(drive, np.random.default_rng(0), 0.7)
