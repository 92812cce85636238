"""`agv-fe calibrate`: a complete vehicle profile from recordings of healthy driving."""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Any

from agv_fe.common import EXIT_NO_DESIGN, CommandError, add_bag_argument, fail, load_json, read_input
from synth.calibration import REQUIRED_BASE_FIELDS


def register(sub: Any) -> None:
    parser = sub.add_parser(
        "calibrate",
        help="identify a vehicle profile from healthy recordings (grey-box least squares)",
        description="Identify what the data sheet does not give (effective mass, drag, rolling resistance, "
        "cornering stiffnesses, steering actuator lag, yaw inertia if absent, sensor noise) from recordings of "
        "healthy driving in the replay CSV format (t, vx, r, torque, steer every 10 ms), design the observer for "
        "it and set the alarm thresholds from the healthy estimates. Prints each parameter with a 95 %% "
        "confidence interval and the fit residuals; refuses, with the reason, data that cannot identify the "
        "vehicle. The profile written is accepted by synth --params, replay --params and PUT /profiles/{name}.",
    )
    parser.add_argument(
        "recordings", nargs="+", metavar="REC.csv", help="healthy recordings, 100 Hz (ROS 2 bags with --map)"
    )
    add_bag_argument(parser)
    parser.add_argument(
        "--base",
        required=True,
        metavar="BASE.json",
        help="what the data sheet gives, in the --params format: params.mass_kg, front_axle_distance_m, "
        "rear_axle_distance_m, wheel_radius_m (and yaw_inertia_kgm2 when known) are kept; a 'design' or "
        "'alarms' section is kept too",
    )
    parser.add_argument("--out", required=True, metavar="PROFILE.json", help="where to write the profile")
    parser.add_argument(
        "--false-alarms",
        type=float,
        default=1.0,
        metavar="N",
        help="false alarms per 1,000 vehicle-hours the thresholds are set for (default 1)",
    )
    parser.add_argument(
        "--nominal-torque",
        type=float,
        default=None,
        metavar="NM",
        help="the drive torque a 10 %% torque fault is measured against [N m] (default: the torque of a 2 m/s^2 "
        "acceleration, m_eff R_w 2)",
    )
    parser.add_argument(
        "--gust",
        type=float,
        default=None,
        metavar="N",
        help="the lateral wind gust [N], held 2 s, the vehicle must ride through without a steering alarm "
        "(default 800; 0: no gust floor)",
    )
    parser.add_argument(
        "--effectiveness",
        action="store_true",
        help="enable the loss-of-effectiveness stage in the profile and set the fault thresholds from its total "
        "faults on the recordings (the service then reports alpha and alarms on it)",
    )
    parser.add_argument(
        "--payload-kg",
        type=float,
        nargs="+",
        default=None,
        metavar="KG",
        help="the load the vehicle carried [kg]: one value for every recording, or one per recording in their "
        "order; calibration then identifies the vehicle without it, the profile a reported payload is added to "
        "(default 0: recorded as the vehicle usually drives)",
    )
    parser.add_argument("--report", metavar="REPORT.json", help="also write the calibration report as JSON")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from service.calibration import GUST_N, calibrate_from_base
    from synth.calibration import CalibrationRefused, Drive
    from synth.errors import SynthesisError

    try:
        base = _base(args.base)
        if not (args.false_alarms > 0):
            raise CommandError(f"--false-alarms must be positive, got {args.false_alarms}")
        if args.nominal_torque is not None and not (args.nominal_torque > 0):
            raise CommandError(f"--nominal-torque must be positive, got {args.nominal_torque}")
        gust = GUST_N if args.gust is None else args.gust
        if not (0.0 <= gust < float("inf")):
            raise CommandError(f"--gust must be a force of 0 N or more, got {args.gust}")
        payloads = _payloads(args.payload_kg, len(args.recordings))
        drives = []
        for path, payload in zip(args.recordings, payloads, strict=True):
            rec = read_input(path, args.map, float(base["params"].get("sample_period_s", 0.01)))
            name = Path(path).name
            drives.append(Drive(t=rec.t, y=rec.y, u=rec.u, name=name, grade=rec.grade, payload_kg=payload))
        print(f"calibrating from {len(drives)} recording(s) ...", flush=True)
        start = time.monotonic()

        def progress(line: str) -> None:
            print(f"  {time.monotonic() - start:5.1f} s  {line}", flush=True)

        try:
            report = calibrate_from_base(
                drives,
                base,
                nominal_torque_nm=args.nominal_torque,
                false_alarms_per_1000_h=args.false_alarms,
                gust_n=gust,
                effectiveness=args.effectiveness,
                progress=progress,
            )
        except CalibrationRefused as exc:
            raise CommandError(f"calibration refused: {exc.reason}", EXIT_NO_DESIGN) from exc
        except SynthesisError as exc:
            raise CommandError(f"the observer design for the calibrated vehicle failed: {exc}", EXIT_NO_DESIGN) from exc
        except ValueError as exc:
            raise CommandError(f"invalid base profile or option: {exc}") from exc
    except CommandError as exc:
        return fail(exc)
    print(format_report(report.summary()))
    out = Path(args.out)
    try:
        out.write_text(json.dumps(report.profile_document(), indent=1) + "\n")
        if args.report:
            Path(args.report).write_text(json.dumps(report.summary(), indent=1, default=float) + "\n")
    except OSError as exc:
        return fail(CommandError(f"cannot write: {exc.strerror}: {exc.filename}"))
    print(f"written {out}" + (f" and {args.report}" if args.report else ""))
    return 0


def _payloads(given: list[float] | None, recordings: int) -> list[float]:
    """One payload per recording from --payload-kg: none (0 kg each), one for all, or one each."""
    if given is None:
        return [0.0] * recordings
    if len(given) not in (1, recordings):
        raise CommandError(f"--payload-kg: give one value, or one per recording ({recordings}), got {len(given)}")
    for value in given:
        if not (math.isfinite(value) and value >= 0.0):
            raise CommandError(f"--payload-kg: expected kg >= 0, got {value}")
    return given * recordings if len(given) == 1 else list(given)


def _base(path: str) -> dict[str, Any]:
    data = load_json(path)
    if not isinstance(data, dict):
        raise CommandError(f"{path}: expected a JSON object")
    if "params" not in data:
        data = {"params": data}
    if not isinstance(data["params"], dict):
        raise CommandError(f"{path}: 'params' must be an object")
    unknown = set(data) - {"params", "bounds", "design", "alarms", "limits", "name", "description"}
    if unknown:
        raise CommandError(f"{path}: unknown section(s) {', '.join(sorted(unknown))}")
    missing = [name for name in REQUIRED_BASE_FIELDS if name not in data["params"]]
    if missing:
        raise CommandError(
            f"{path}: params must give {', '.join(missing)} (what the data sheet states is kept, not identified)"
        )
    return data


def format_report(summary: dict[str, Any]) -> str:
    """The calibration as aligned lines: parameters with intervals, noise, fit, thresholds, warnings."""
    lines = [f"used {summary['duration_s']:.0f} s of driving, up to {summary['peak_lateral_accel_mps2']:.1f} m/s^2"]
    lines.append("identified (95 % confidence interval):")
    for name, e in summary["estimates"].items():
        low, high = e["ci95"]
        lines.append(f"  {name:32s} {e['value']:12.5g}   [{low:.5g}, {high:.5g}]")
    noise = summary["sensor_noise"]
    lines.append(f"sensor noise: v_x {noise['vx_sigma_mps']:.4g} m/s, r {noise['r_sigma_radps']:.4g} rad/s (RMS)")
    res = summary["residuals"]
    lines.append(
        f"fit residuals: yaw rate {res['yaw_rate_rms_radps']:.4g} rad/s RMS ({res['yaw_rate_rms_over_noise']:.2f} x "
        f"the sensor noise); speed change per window {res['speed_change_rms_mps']:.4g} m/s RMS "
        f"({res['speed_change_rms_over_noise']:.2f} x noise, {int(res['longitudinal_windows'])} windows)"
    )
    lines.append(f"steering offset {summary['steer_offset_rad']:+.5f} rad (reported, not used)")
    lines.append(
        f"observer: gains {summary['gain_version']}, certified decay rate {summary['certified_decay_rate']:.4f}; "
        f"thresholds for {summary['false_alarms_per_1000_h']:g} false alarm(s) per 1,000 vehicle-hours and no "
        f"alarm in a {summary['gust']['force_n']:g} N wind gust of {summary['gust']['duration_s']:g} s:"
    )
    for channel, t in summary["thresholds"].items():
        unit = t["unit"]
        lines.append(
            f"  {channel:6s} WARN {t['warn']:.4g} FAULT {t['fault']:.4g} {unit}  (healthy estimate {t['sigma']:.3g} "
            f"RMS, largest held {t['healthy_peak']:.3g}, in the gust {t['gust_peak']:.3g}; certified RMS bound "
            f"{t['certified_rms']:.3g}; set by {t['set_by']}); smallest "
            f"bias detected: WARN {t['smallest_warn_bias']:.3g}, FAULT {t['smallest_fault_bias']:.3g} {unit}"
        )
    lines.append(f"nominal drive torque {summary['nominal_torque_nm']:.4g} N m")
    lines.extend(f"note: {note}" for note in summary["notes"])
    lines.extend(f"WARNING: {warning}" for warning in summary["warnings"])
    return "\n".join(lines)
