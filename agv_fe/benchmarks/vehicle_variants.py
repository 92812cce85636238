"""Vehicle variants: do calibration, and the alarms it sets, hold on vehicles the project is not measured on?

The real-vehicle benchmark (real_vehicle.py) calibrates and judges CommonRoad's parameter sets 1 and 3. A
product tuned to two vehicles could pass there and fail on the next one. Here each set is changed physically
(:class:`edge_client.multibody.Variant`: the centre of gravity moved along the wheelbase or raised or lowered, the
tyres stiffer or softer, the brakes' front share changed, all-wheel drive; and a wet road), and each variant goes
through what a vehicle engineer does with a new vehicle: calibrate from the scripted calibration drive with the
variant's data sheet (``base_profile``), then run healthy drives (the real-vehicle benchmark's mix: open road,
town, braking and accelerating in turns) and the four bias faults with the calibrated profile and its alarm
levels. On the wet road the vehicle is calibrated on the dry one and drives gentler (every acceleration times the
road's friction); its profile is the dry road's.

Must show, per variant: the calibration gives a profile whose effective mass is within 1 % of the variant's;
no WARN or FAULT on either channel over the healthy drives; each bias fault raises WARN within 1.5 s and FAULT
within 2.5 s with the other channel OK. The cornering stiffnesses against the tyres' slope are reported, not
judged: set 1 reads its front stiffness 6 % low from roll camber (docs/benchmarks/real_vehicle.md), and its
variants inherit it.

Parameter set 2 is never used here: it is kept for checks the project does not tune on.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from agv_fe.benchmarks import real_vehicle as rv
from agv_fe.benchmarks import report_header
from edge_client import multibody as mb
from edge_client.simulation import observer_factory
from service.calibration import CalibrationReport, calibrate_profile
from synth.errors import SynthesisError

#: The wet road's peak friction as a share of the dry road's (wet asphalt).
WET_ROAD_FRICTION = 0.6
#: The variants: (parameter set, the change). Each changes one physical property by an amount that separates
#: real cars of a class (a CG 0.17 m further back is a rear-engined car's share of the wheelbase; +-25 % CG
#: height spans a saloon and a van; +-20 % tyre stiffness spans tyre makes and pressures; set 1 drives its front
#: wheels, set 3 its rear ones, and the all-wheel variant all four). A wet road is a condition, not a vehicle: those
#: variants are calibrated on the dry road, drive the healthy and fault drives with every acceleration scaled by
#: the road's friction (as a driver does), with the profile calibrated on the dry road as it is.
VARIANTS: tuple[tuple[int, mb.Variant], ...] = (
    (1, mb.Variant("CG 0.17 m further back", cg_back_m=0.17)),
    (1, mb.Variant("CG 25 % higher", cg_height_factor=1.25)),
    (1, mb.Variant("tyres 20 % softer", tyre_stiffness_factor=0.8)),
    (3, mb.Variant("CG 25 % lower", cg_height_factor=0.75)),
    (3, mb.Variant("tyres 20 % stiffer", tyre_stiffness_factor=1.2)),
    (3, mb.Variant("front brake share 0.76", brake_front_share=0.76)),
    (3, mb.Variant("all-wheel drive, half the torque in front", drive_front_share=0.5)),
    (1, mb.Variant("wet road, friction 0.6", road_friction=WET_ROAD_FRICTION)),
    (3, mb.Variant("wet road, friction 0.6", road_friction=WET_ROAD_FRICTION)),
)
#: Healthy drives per variant (the real-vehicle benchmark's seeds: every third in town, the next braking and
#: accelerating in turns), each HEALTHY_DURATION_S long.
HEALTHY_SEEDS = tuple(range(1, 13))
HEALTHY_DURATION_S = rv.HEALTHY_DURATION_S
QUICK_HEALTHY_SEEDS = (1, 2)
QUICK_HEALTHY_DURATION_S = 20.0
#: The fault cases run on every variant: the four biases, one seed each.
FAULT_CASES = tuple(case for case in rv.FAULT_CASES if case.kind == "bias")
#: Quick mode (tests): one bias per channel.
QUICK_FAULT_CASES = tuple(case for case in FAULT_CASES if case.size > 0)
FAULT_SEED = rv.FAULT_SEEDS[0]


@dataclass(frozen=True)
class Plan:
    variants: tuple[tuple[int, mb.Variant], ...]
    healthy_seeds: tuple[int, ...]
    healthy_duration_s: float
    fault_cases: tuple[rv.FaultCase, ...]
    workers: int
    quick: bool


def _percent(share: float, digits: int) -> str:
    return f"{100 * share:+.{digits}f} %"


def _label(parameter_set: int, variant: mb.Variant) -> str:
    return f"set {parameter_set}, {variant.name}"


def calibrate(parameter_set: int, variant: mb.Variant, run: mb.MultibodyRun) -> CalibrationReport:
    """:func:`calibrate_profile` on the calibration drive with the variant's data sheet; raises what it raises."""
    return calibrate_profile(
        [rv.recording(run)],
        mb.base_profile(parameter_set, variant)["params"],
        description=f"CommonRoad parameter set {parameter_set}, {variant.name}: the vehicle_variants benchmark",
    )


def on_dry_road(variant: mb.Variant) -> mb.Variant:
    """The variant's vehicle on the dry road: what it is calibrated on."""
    return dataclasses.replace(variant, road_friction=1.0)


def calibration_errors(parameter_set: int, variant: mb.Variant, report: CalibrationReport) -> dict[str, float]:
    """The identified effective mass and cornering stiffnesses against the variant's values: relative errors."""
    reference = mb.reference_values(parameter_set, variant)
    params = report.profile.params
    return {
        name: getattr(params, name) / reference[name] - 1.0
        for name in ("effective_mass_kg", "front_cornering_stiffness_npr", "rear_cornering_stiffness_npr")
    }


def evaluate(
    parameter_set: int,
    variant: mb.Variant,
    report: CalibrationReport,
    healthy: Sequence[mb.MultibodyRun],
    cases: Sequence[rv.FaultCase],
    faults: Sequence[mb.MultibodyRun],
) -> dict[str, Any]:
    """The calibration errors, the healthy drives' alarms and peaks, and each bias fault's delays."""
    alarms = report.profile.alarms
    factory = observer_factory(report.gains)
    period = report.profile.params.sample_period_s
    figures = rv.healthy_figures(healthy, rv.estimate_runs(factory, healthy, alarms), alarms, period)
    fault_rows = []
    for case, run, est in zip(cases, faults, rv.estimate_runs(factory, faults, alarms), strict=True):
        seed = rv.fault_run_figures(case, run, est, alarms, rv.FAULT_ONSET_S)
        fault_rows.append({"key": case.key, "label": case.label, "seed": seed, "meets_target": rv.meets(case, [seed])})
    return {
        "calibration_errors": calibration_errors(parameter_set, variant, report),
        "warn_thresholds": {"torque": alarms.torque_warn_nm, "steer": alarms.steer_warn_rad},
        "healthy": {
            "minutes": sum(len(r) for r in healthy) * mb.SAMPLE_PERIOD_S / 60.0,
            "channels": _healthy_channels(figures),
            "drives_with_alarm": figures["drives_with_alarm"],
        },
        "faults": fault_rows,
    }


_HEALTHY_KEYS = ("warn_raised", "fault_raised", "held_peak_abs_estimate", "warn_threshold")


def _healthy_channels(figures: dict[str, Any]) -> dict[str, Any]:
    return {
        channel: {key: values[key] for key in _HEALTHY_KEYS} | {"held_at": values["held_peak_at"]}
        for channel, values in figures["channels"].items()
    }


def _channels_text(channels: dict[str, Any]) -> str:
    return ", ".join(
        f"{rv.SYMBOLS[name]} {c['warn_raised']} WARN / {c['fault_raised']} FAULT, held peak "
        f"{c['held_peak_abs_estimate'] / c['warn_threshold']:.2f} of WARN"
        for name, c in channels.items()
    )


def must_show(result: dict[str, Any]) -> list[dict[str, Any]]:
    """The variant's targets: a profile with the effective mass within 1 %, healthy driving quiet, the biases
    detected in time."""
    if "calibration_error" in result:
        return [{"target": "calibration gives a profile", "figure": result["calibration_error"], "passed": False}]
    mass = result["calibration_errors"]["effective_mass_kg"]
    channels = result["healthy"]["channels"]
    quiet = all(c["warn_raised"] == 0 and c["fault_raised"] == 0 for c in channels.values())
    lines = [
        {
            "target": f"effective mass within {100 * rv.EFFECTIVE_MASS_TOLERANCE:g} % of the variant's",
            "figure": _percent(mass, 2),
            "passed": abs(mass) <= rv.EFFECTIVE_MASS_TOLERANCE,
        },
        {
            "target": "healthy driving: no WARN and no FAULT on either channel",
            "figure": f"{result['healthy']['minutes']:.0f} min: " + _channels_text(channels),
            "passed": quiet,
        },
    ]
    for row in result["faults"]:
        case = next(c for c in FAULT_CASES if c.key == row["key"])
        lines.append(
            {
                "target": f"{case.label}: {rv._target_text(case)}",
                "figure": rv._delays_text([row["seed"]], case),
                "passed": row["meets_target"],
            }
        )
    return lines


def healthy_jobs(
    parameter_set: int, variant: mb.Variant, seeds: Sequence[int], duration_s: float
) -> list[mb.MultibodyJob]:
    """The variant's calibration drive (on the dry road) and its healthy drives (each acceleration times the
    road's friction)."""
    calibration = dataclasses.replace(rv.calibration_job(parameter_set), variant=on_dry_road(variant))
    return [calibration] + [
        mb.MultibodyJob(
            drive=rv.healthy_drive(seed, duration_s, variant.road_friction),
            parameter_set=parameter_set,
            seed=seed,
            variant=variant,
        )
        for seed in seeds
    ]


def measure(plan: Plan) -> dict[str, Any]:
    """Simulate and evaluate every variant: the run's document (what vehicle_variants.json holds)."""
    started = time.perf_counter()
    print(f"  simulating calibration and healthy drives of {len(plan.variants)} variants ...", flush=True)
    per_variant = 1 + len(plan.healthy_seeds)
    jobs = [
        job
        for parameter_set, variant in plan.variants
        for job in healthy_jobs(parameter_set, variant, plan.healthy_seeds, plan.healthy_duration_s)
    ]
    runs = mb.simulate_many(jobs, plan.workers)
    reports: list[CalibrationReport | str] = []
    for i, (parameter_set, variant) in enumerate(plan.variants):
        print(f"  calibrating {_label(parameter_set, variant)} ...", flush=True)
        try:
            reports.append(calibrate(parameter_set, variant, runs[i * per_variant]))
        except SynthesisError as exc:  # CalibrationRefused, Infeasible, ...: the product's answer, reported
            reports.append(str(exc))
    fault_plan = rv.Plan.make(sorted({s for s, _ in plan.variants}), plan.quick, plan.workers)
    fault_jobs = [
        dataclasses.replace(
            mb.MultibodyJob(
                drive=rv.fault_drive(case, FAULT_SEED, parameter_set, fault_plan, variant.road_friction),
                parameter_set=parameter_set,
                faults=case.faults(report.nominal_torque_nm, fault_plan.fault_onset_s),
                seed=FAULT_SEED,
            ),
            variant=variant,
        )
        for (parameter_set, variant), report in zip(plan.variants, reports, strict=True)
        if not isinstance(report, str)
        for case in plan.fault_cases
    ]
    print(f"  simulating {len(fault_jobs)} fault runs ...", flush=True)
    fault_runs = iter(mb.simulate_many(fault_jobs, plan.workers))
    results = []
    for i, ((parameter_set, variant), report) in enumerate(zip(plan.variants, reports, strict=True)):
        entry: dict[str, Any] = {"parameter_set": parameter_set, "variant": dataclasses.asdict(variant)}
        if isinstance(report, str):
            entry["calibration_error"] = report
        else:
            healthy = runs[i * per_variant + 1 : (i + 1) * per_variant]
            faults = [next(fault_runs) for _ in plan.fault_cases]
            entry |= evaluate(parameter_set, variant, report, healthy, plan.fault_cases, faults)
        entry["must_show"] = must_show(entry)
        results.append(entry)
    return {
        "benchmark": "vehicle_variants",
        "plan": {
            "healthy_seeds": list(plan.healthy_seeds),
            "healthy_duration_s": plan.healthy_duration_s,
            "fault_seed": FAULT_SEED,
            "fault_cases": [case.key for case in plan.fault_cases],
            "quick": plan.quick,
        },
        "variants": results,
        "runtime_s": time.perf_counter() - started,
    }


def render(document: dict[str, Any]) -> str:
    """The markdown report: must-show first, then the calibration and healthy-driving tables."""
    out = [report_header("Vehicle variants: calibration and alarms beyond the measured vehicles", "vehicle_variants")]
    plan = document["plan"]
    out.append(
        f"{len(document['variants'])} variants of CommonRoad's parameter sets 1 and 3 "
        "(`edge_client.multibody.Variant`), each calibrated from the scripted calibration drive with its own data "
        f"sheet, then {len(plan['healthy_seeds'])} healthy drives of {plan['healthy_duration_s']:g} s (the "
        "real-vehicle benchmark's mix; a wet road's vehicle is calibrated on the dry road and drives the mix with "
        f"every acceleration times the road's friction) and {len(plan['fault_cases'])} bias faults (seed "
        f"{plan['fault_seed']}) with the calibrated profile; this run took {document['runtime_s'] / 60:.1f} min. "
        "Parameter set 2 is never used here.\n"
    )
    out += ["## Must show", "", "| variant | target | measured | result |", "|---|---|---|---|"]
    for v in document["variants"]:
        label = _label(v["parameter_set"], mb.Variant(**v["variant"]))
        for line in v["must_show"]:
            result = "pass" if line["passed"] else "**FAIL**"
            out.append(f"| {label} | {line['target']} | {line['figure']} | {result} |")
    out += [
        "",
        "## Calibration and healthy driving",
        "",
        "Errors of the identified parameters against the variant's own (the stiffnesses against the tyres' slope at "
        "the static load, as in the real-vehicle benchmark); the WARN levels calibration set; the largest estimate "
        "held for the alarm's persistence time over the healthy drives, as a share of WARN (an alarm needs 1).",
        "",
        "| variant | m_eff error | C_f error | C_r error | T_f WARN [N m] | delta_f WARN [rad] "
        "| T_f held peak / WARN | delta_f held peak / WARN |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for v in document["variants"]:
        label = _label(v["parameter_set"], mb.Variant(**v["variant"]))
        if "calibration_error" in v:
            out.append(f"| {label} | refused: {v['calibration_error']} | | | | | | |")
            continue
        e, w, c = v["calibration_errors"], v["warn_thresholds"], v["healthy"]["channels"]
        held = [c[name]["held_peak_abs_estimate"] / c[name]["warn_threshold"] for name in ("torque", "steer")]
        out.append(
            f"| {label} | {_percent(e['effective_mass_kg'], 2)} | {_percent(e['front_cornering_stiffness_npr'], 1)} "
            f"| {_percent(e['rear_cornering_stiffness_npr'], 1)} | {w['torque']:.1f} | {w['steer']:.4g} "
            f"| {held[0]:.2f} | {held[1]:.2f} |"
        )
    out.append("")
    return "\n".join(out)


def run(out_dir: Path, quick: bool = False, workers: int = rv.WORKERS) -> Path:
    """Run every variant; write vehicle_variants.md and vehicle_variants.json to ``out_dir``. ``quick``: the
    first variant of set 1 and the wet road on set 3, two short healthy drives and one bias per channel each (for
    tests)."""
    plan = Plan(
        variants=(VARIANTS[0], VARIANTS[-1]) if quick else VARIANTS,
        healthy_seeds=QUICK_HEALTHY_SEEDS if quick else HEALTHY_SEEDS,
        healthy_duration_s=QUICK_HEALTHY_DURATION_S if quick else HEALTHY_DURATION_S,
        fault_cases=QUICK_FAULT_CASES if quick else FAULT_CASES,
        workers=workers,
        quick=quick,
    )
    document = measure(plan)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "vehicle_variants.json").write_text(json.dumps(rv._clean(document), indent=1) + "\n")
    path = out_dir / "vehicle_variants.md"
    path.write_text(render(document))
    return path
