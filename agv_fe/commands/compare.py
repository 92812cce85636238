"""`agv-fe compare`: the fuzzy observer against the augmented-state EKF on the same noisy data."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from agv_fe.common import CommandError, add_design_arguments, fail, gains_from_args


def register(sub: Any) -> None:
    parser = sub.add_parser(
        "compare",
        help="compare the observer with an EKF on a scenario",
        description="Run the certified observer and an augmented-state EKF (tuned from the same noise model) "
        "on the same noisy runs of a scenario; print RMSE, detection delay, per-step cost and memory; "
        "write a PNG overlay of the estimates.",
    )
    parser.add_argument("--scenario", required=True, help="built-in scenario: paper-1, paper-2, highway, urban")
    parser.add_argument("--seeds", type=int, default=5, help="number of noise seeds (median reported, default 5)")
    parser.add_argument("--batch", type=int, default=1000, help="fleet size for the per-step cost (default 1000)")
    parser.add_argument("--gains", metavar="gains.json", help="use stored gains instead of synthesising")
    parser.add_argument("--out", default="out/compare", metavar="DIR", help="where to write the figure")
    add_design_arguments(parser, default_design="robust")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from edge_client.evaluation import RMSE_AFTER_S, DetectionRule, compare
    from edge_client.library import BUILTIN_SCENARIOS
    from edge_client.plots import plot_fault_overlay
    from edge_client.simulation import ekf_factory, observer_factory

    try:
        if args.scenario not in BUILTIN_SCENARIOS:
            raise CommandError(f"--scenario: unknown {args.scenario!r}; known: {', '.join(BUILTIN_SCENARIOS)}")
        if not 1 <= args.seeds <= 100:
            raise CommandError(f"--seeds must be between 1 and 100, got {args.seeds}")
        if not 1 <= args.batch <= 100_000:
            raise CommandError(f"--batch must be between 1 and 100000, got {args.batch}")
        gains = gains_from_args(args)
    except CommandError as exc:
        return fail(exc)
    rule = DetectionRule()
    factories = {"observer": observer_factory(gains), "EKF": ekf_factory(gains)}
    figure = Path(args.out) / f"{args.scenario}-overlay.png"
    print(f"running {args.scenario} with {args.seeds} seed(s); the figure goes to {figure} ...", flush=True)
    c = compare(args.scenario, factories, args.seeds, rule, batch=args.batch)
    print(format_table(c, gains, rule, RMSE_AFTER_S))
    figure.parent.mkdir(parents=True, exist_ok=True)
    path = plot_fault_overlay(
        {f"{gains.options.design} observer": c.example["observer"], "EKF": c.example["EKF"]},
        figure,
        title=f"{args.scenario}, seed 0: fault estimates",
    )
    print(f"written {path}")
    return 0


def _fmt(value: float | None, digits: int = 4) -> str:
    return "-" if value is None else f"{value:.{digits}g}"


def format_table(c: Any, gains: Any, rule: Any, after_s: float) -> str:
    """The comparison as an aligned text table."""
    rows = [
        ("T_f RMSE [N m]", "rmse", "T_f"),
        ("delta_f RMSE [rad]", "rmse", "delta_f"),
        ("v_y RMSE [m/s]", "rmse", "v_y"),
        ("T_f detection delay [s]", "detection_delay_s", "T_f"),
        ("delta_f detection delay [s]", "detection_delay_s", "delta_f"),
    ]
    lines = [
        f"scenario {c.scenario}: median over {len(c.seeds)} seed(s); RMSE from t = {after_s:g} s; detection = "
        f"|estimate| above {rule.torque_nm:g} N m / {rule.steer_rad:g} rad for {rule.hold_s:g} s",
        f"observer: '{gains.options.design}' design, fault order {gains.options.fault_order}, version {gains.version}; "
        "EKF tuned from the same noise model",
        f"{'metric':<36}{'observer':>12}{'EKF':>12}{'ratio':>14}",
    ]
    for label, metric, channel in rows:
        a = c.median("observer", metric, channel)
        b = c.median("EKF", metric, channel)
        ratio = "-" if a is None or b is None or b == 0 else f"obs/EKF {a / b:.2f}"
        lines.append(f"{label:<36}{_fmt(a):>12}{_fmt(b):>12}{ratio:>14}")
    for channel in ("T_f", "delta_f"):
        fa = sum(sum(s.false_detections[channel] for s in c.scores[name]) for name in ("observer",))
        fb = sum(sum(s.false_detections[channel] for s in c.scores[name]) for name in ("EKF",))
        lines.append(f"{channel + ' false detections (all seeds)':<36}{fa:>12}{fb:>12}")
    o1, e1 = c.step_us_1["observer"], c.step_us_1["EKF"]
    ob, eb = c.step_us_batch["observer"], c.step_us_batch["EKF"]
    lines.append(f"{'step time, 1 vehicle [us]':<36}{o1:>12.1f}{e1:>12.1f}{'EKF/obs ' + format(e1 / o1, '.1f'):>14}")
    label = f"step time, {c.batch_size} vehicles [us]"
    lines.append(f"{label:<36}{ob:>12.1f}{eb:>12.1f}{'EKF/obs ' + format(eb / ob, '.1f'):>14}")
    lines.append(f"{'state per vehicle [bytes]':<36}{c.state_bytes['observer']:>12}{c.state_bytes['EKF']:>12}")
    return "\n".join(lines)
