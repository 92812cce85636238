"""The vehicle-variants benchmark (agv_fe/benchmarks/vehicle_variants.py) in quick mode: two variants (one of each
set, the second a wet road), two short healthy drives and one bias per channel each (about 40 s on 2 cores), shared
by this module's tests: the report and its JSON exist, and every must-show line agrees with the figures it judges."""

from __future__ import annotations

import json

import numpy as np
import pytest

from agv_fe.benchmarks import real_vehicle as rv
from agv_fe.benchmarks import vehicle_variants as bench
from agv_fe.commands.bench import BENCHMARKS
from edge_client import multibody as mb
from tests.agv_fe.markdown import assert_rows_match_headers


@pytest.fixture(scope="module")
def outcome(tmp_path_factory):
    out = tmp_path_factory.mktemp("vehicle_variants")
    path = bench.run(out, quick=True)
    return path, path.read_text(), json.loads((out / "vehicle_variants.json").read_text())


def test_registered_and_writes_report_and_json_beside_it(outcome):
    path, text, document = outcome
    assert BENCHMARKS["vehicle_variants"] == "agv_fe.benchmarks.vehicle_variants"
    assert path.name == "vehicle_variants.md" and (path.parent / "vehicle_variants.json").is_file()
    assert text.startswith("# Vehicle variants") and "agv-fe bench --only vehicle_variants" in text
    assert text.index("## Must show") < text.index("## Calibration and healthy driving")
    assert "Parameter set 2 is never used here" in text
    assert [v["parameter_set"] for v in document["variants"]] == [1, 3]
    assert_rows_match_headers(text, at_least=2)


def test_each_variant_is_calibrated_against_its_own_values(outcome):
    """The errors are taken against the variant's reference values, not the set's: recomputed here."""
    _, _, document = outcome
    for v in document["variants"]:
        variant = mb.Variant(**v["variant"])
        assert mb.vehicle_parameters(v["parameter_set"], variant) != mb.vehicle_parameters(v["parameter_set"])
        errors = v["calibration_errors"]
        assert set(errors) == {"effective_mass_kg", "front_cornering_stiffness_npr", "rear_cornering_stiffness_npr"}
        assert abs(errors["effective_mass_kg"]) < 0.05 and abs(errors["front_cornering_stiffness_npr"]) < 0.3


def test_must_show_lines_agree_with_the_figures(outcome):
    _, text, document = outcome
    for v in document["variants"]:
        lines = v["must_show"]
        assert len(lines) == 2 + len(bench.QUICK_FAULT_CASES) and len(bench.QUICK_FAULT_CASES) == 2
        mass, quiet, *faults = lines
        assert mass["passed"] == (abs(v["calibration_errors"]["effective_mass_kg"]) <= rv.EFFECTIVE_MASS_TOLERANCE)
        channels = v["healthy"]["channels"]
        raised = sum(c["warn_raised"] + c["fault_raised"] for c in channels.values())
        assert quiet["passed"] == (raised == 0) and v["healthy"]["minutes"] == pytest.approx(2 * 20 / 60)
        for line, row in zip(faults, v["faults"], strict=True):
            seed = row["seed"]
            in_time = (
                seed["level_before_onset"] == "OK"
                and seed["warn_delay_s"] is not None
                and seed["warn_delay_s"] <= rv.BIAS_WARN_WITHIN_S
                and seed["fault_delay_s"] is not None
                and seed["fault_delay_s"] <= rv.BIAS_FAULT_WITHIN_S
                and seed["other_channel_level"] == "OK"
            )
            assert line["passed"] == row["meets_target"] == in_time
        label = f"set {v['parameter_set']}, {v['variant']['name']}"
        rows = [row for row in text.split("## Must show")[1].split("## Calibration")[0].splitlines() if label in row]
        assert len(rows) == len(lines)
        assert all(row.endswith("| pass |") == line["passed"] for row, line in zip(rows, lines, strict=True))


def test_a_wet_road_is_a_condition_the_dry_calibration_meets():
    """The wet variant's vehicle is calibrated on the dry road (its calibration job is the dry vehicle's) and
    drives its healthy and fault drives with every acceleration times the road's friction."""
    wet = next(v for _, v in bench.VARIANTS if v.road_friction != 1.0)
    assert wet.road_friction == bench.WET_ROAD_FRICTION
    dry = bench.on_dry_road(wet)
    assert dry.road_friction == 1.0 and mb.vehicle_parameters(3, dry) == mb.vehicle_parameters(3)
    assert mb.vehicle_parameters(3, wet).tire.p_dy1 == pytest.approx(0.6 * mb.vehicle_parameters(3).tire.p_dy1)
    jobs = bench.healthy_jobs(3, wet, bench.QUICK_HEALTHY_SEEDS, bench.QUICK_HEALTHY_DURATION_S)
    calibration, *healthy = jobs
    assert calibration.variant == dry and calibration.drive.name == rv.calibration_job(3).drive.name
    for job, seed in zip(healthy, bench.QUICK_HEALTHY_SEEDS, strict=True):
        planned = rv.healthy_drive(seed, bench.QUICK_HEALTHY_DURATION_S, wet.road_friction)
        assert job.variant == wet and np.array_equal(job.drive.yaw_rate_radps, planned.yaw_rate_radps)


def test_a_refused_calibration_is_reported_as_a_failed_target():
    entry = {"parameter_set": 1, "calibration_error": "the stiffnesses are not identified"}
    (line,) = bench.must_show(entry)
    assert not line["passed"] and "not identified" in line["figure"]
