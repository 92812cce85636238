"""`agv-fe replay`: run the observer over a recorded 100 Hz stream, with the service's alarm levels."""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from agv_fe.common import (
    CommandError,
    VehicleProfileFile,
    add_bag_argument,
    add_design_arguments,
    add_estimator_argument,
    estimator_factory,
    fail,
    gains_from_args,
    load_profile_file,
    read_input,
)

if TYPE_CHECKING:
    from edge_client.recording import Recording
    from edge_client.simulation import EstimatorFactory, EstimatorOutput
    from service.profiles import AlarmThresholds, InputLimits
    from synth.gains import ObserverGains
    from synth.model import FloatArray

#: The fault channels, in the order of the level columns (torque_level, steer_level).
CHANNELS = ("torque", "steer")


def register(sub: Any) -> None:
    parser = sub.add_parser(
        "replay",
        help="estimate faults from a recorded CSV stream",
        description="Run the observer over a recorded 100 Hz stream with columns t, vx, r, torque, steer "
        "(others ignored) and write t, vx_hat, vy_hat, r_hat, torque_fault_hat, steer_fault_hat, in_domain, "
        "torque_level, steer_level. The levels (OK, WARN, FAULT) come from the service's alarm code with the "
        "alarm thresholds of the --params profile (default: the default thresholds), on the time stamps "
        "t_ns = round(t * 1e9): the service gives the same levels for the same stream.",
    )
    parser.add_argument("input", metavar="INPUT.csv", help="recorded stream (a ROS 2 bag with --map)")
    add_bag_argument(parser)
    parser.add_argument("--out", required=True, metavar="OUTPUT.csv", help="estimates")
    parser.add_argument(
        "--gains",
        metavar="gains.json",
        help="use stored gains instead of synthesising (the alarm thresholds still come from --params)",
    )
    parser.add_argument(
        "--initial-state",
        metavar="VX,VY,R",
        help="observer initial [v_x, v_y, r] (default: measured v_x, r and v_y = 0, as the service starts)",
    )
    parser.add_argument(
        "--effectiveness",
        action="store_true",
        help="estimate each actuator's effectiveness beside its bias (synth.effectiveness), as the profile's "
        "'effectiveness' section sets it (enabled there too): torque_fault_hat and steer_fault_hat are then the "
        "total faults, and the columns torque_bias_hat, steer_bias_hat, torque_alpha_hat, steer_alpha_hat follow",
    )
    parser.add_argument(
        "--payload-kg",
        type=float,
        default=0.0,
        metavar="KG",
        help="the vehicle carried this payload over the recording (at most the profile's mass_kg): the model's "
        "drive torque follows it, as in the service after PUT /vehicles/{id}/payload (docs/math.md 12.5)",
    )
    add_design_arguments(parser, default_design="robust")
    add_estimator_argument(parser)
    parser.set_defaults(handler=run)


@dataclass(frozen=True)
class ServiceInputs:
    """What the service steps for a recording's samples (synth.model.model_inputs): the observer's demand
    ``model_u`` (K, 2), the effectiveness stage's ``stage_u`` (K, 2), and ``rho`` (K,) that a torque fault is seen
    through (1 without a payload)."""

    model_u: FloatArray
    stage_u: FloatArray
    rho: FloatArray


@dataclass(frozen=True)
class Replay:
    """A recording of K samples replayed: x_hat (K, 3), f_hat (K, 2), in_domain (K,), levels (K, 2) level
    ranks of [torque, steer] (service.fleet.alarms.LEVEL_NAMES), restarts: observer restarts after a
    non-finite estimate; beyond_grip (K,) the combined acceleration was above the profile's grip limit, judged
    (K,) the fault levels judged the sample (after the warm-up and the grip gate's hold)."""

    x_hat: FloatArray
    f_hat: FloatArray
    in_domain: np.ndarray
    levels: np.ndarray
    restarts: int
    beyond_grip: np.ndarray
    judged: np.ndarray
    #: with the effectiveness stage: the estimated bias and effectiveness (K, 2) each, [torque, steer]
    bias: FloatArray | None = None
    alpha: FloatArray | None = None


def run(args: argparse.Namespace) -> int:
    from edge_client.recording import write_estimates
    from service.fleet.alarms import LEVEL_NAMES

    try:
        x0 = _initial_state(args.initial_state)
        profile = load_profile_file(args.params)
        # stored gains load at once; a design takes seconds: the recording is checked before one is made
        gains = gains_from_args(args, profile) if args.gains else None
        period = profile.params.sample_period_s if gains is None else gains.params.sample_period_s
        recording = read_input(args.input, args.map, period)
        if gains is None:
            gains = gains_from_args(args, profile)
        effectiveness = args.effectiveness or profile.effectiveness.enabled
        if effectiveness and args.estimator == "ekf":
            raise CommandError("--effectiveness runs beside the observer, not the EKF")
        if effectiveness:
            from edge_client.simulation import effectiveness_factory
            from synth.errors import BadParameters

            options = profile.effectiveness.model_copy(update={"enabled": True})
            try:
                effectiveness_factory(gains, options)(recording.y[:1], None, recording.u[:1])
            except BadParameters as exc:
                raise CommandError(f"--effectiveness: {exc}") from exc
            factory = effectiveness_factory(gains, options)
        else:
            factory = estimator_factory(args, gains)
        inputs = service_inputs(recording, args.payload_kg, gains)
    except CommandError as exc:
        return fail(exc)
    result = replay(recording, factory, x0, profile.alarms, profile.params.sample_period_s, inputs)
    names = np.array(LEVEL_NAMES)[result.levels]
    extra = (
        {}
        if result.alpha is None or result.bias is None
        else {
            "torque_bias_hat": result.bias[:, 0],
            "steer_bias_hat": result.bias[:, 1],
            "torque_alpha_hat": result.alpha[:, 0],
            "steer_alpha_hat": result.alpha[:, 1],
        }
    )
    try:
        write_estimates(
            args.out, recording.t, result.x_hat, result.f_hat, result.in_domain, names[:, 0], names[:, 1], extra
        )
    except OSError as exc:
        return fail(CommandError(f"{args.out}: cannot write: {exc.strerror}"))
    n = len(recording)
    print(
        f"replayed {n} samples ({recording.t[-1] - recording.t[0]:.2f} s) with the "
        f"{'EKF' if args.estimator == 'ekf' else repr(gains.options.design) + ' observer'} "
        f"(gains version {gains.version}); premise in domain {result.in_domain.mean():.1%} of the time"
    )
    for line in level_summary(recording.t, result.levels, profile):
        print(line)
    for line in grip_summary(recording.t, result, profile.alarms):
        print(line)
    if result.restarts:
        print(f"the estimate was not finite {result.restarts} time(s): the observer restarted, as the service's does")
    outside = int(outside_limits(recording, profile.limits).sum())
    if outside:
        print(
            f"warning: {outside} samples lie outside the profile's input limits; the service rejects them "
            "(they never reach its observer), so its estimates and levels differ from these"
        )
    print(f"written {Path(args.out)}")
    return 0


def replay(
    recording: Recording,
    make: EstimatorFactory,
    x0: FloatArray | None,
    alarms: AlarmThresholds,
    sample_period_s: float = 0.01,
    inputs: ServiceInputs | None = None,
) -> Replay:
    """Step the estimator over the recording and the fault channels' levels, as the service does per vehicle.

    The levels are :class:`service.fleet.alarms.FaultLevels` fed the fault estimates on the time stamps
    t_ns = round(t * 1e9) [ns], warm-up from the observer's start; with the effectiveness stage, each
    channel's level is the higher of that and :class:`~service.fleet.alarms.EffectivenessLevels` on alpha_hat and
    its sigma. With ``inputs`` (a payload, a road grade) the estimator steps on their demands, and the torque fault
    and torque bias are divided by rho, as in the service's bank; without, on the recording's demand.
    A non-finite estimate is not fed and restarts the estimator from the next measurement (cold, like the
    service's bank).
    """
    from service.fleet.alarms import EffectivenessLevels, FaultLevels
    from synth.effectiveness import EffectivenessObserver, EffectivenessStep

    if inputs is None:
        inputs = ServiceInputs(recording.u, recording.u, np.ones(len(recording)))
    n = len(recording)
    t_ns = np.rint(recording.t * 1e9).astype(np.int64)
    levels = FaultLevels(1, alarms, sample_period_s)
    effectiveness = EffectivenessLevels(1, alarms)
    row = np.zeros(1, dtype=np.intp)
    x_hat = np.zeros((n, 3))
    f_hat = np.zeros((n, 2))
    in_domain = np.zeros(n, dtype=bool)
    level = np.zeros((n, 2), dtype=np.intp)
    beyond_grip, judged = np.zeros(n, dtype=bool), np.zeros(n, dtype=bool)
    bias: FloatArray | None = None
    alpha: FloatArray | None = None
    alpha_sigma: FloatArray = np.zeros((1, 2))
    estimator = None
    restarts = 0
    for k in range(n):
        y, u, t = recording.y[k : k + 1], inputs.model_u[k : k + 1], t_ns[k : k + 1]
        if estimator is None:
            estimator = make(y, x0 if k == 0 else None, u)
            levels.restart(row, t)
            effectiveness.reset(row, keep_level=True)
        step: EstimatorOutput = (
            estimator.step(y, u, inputs.stage_u[k : k + 1])
            if isinstance(estimator, EffectivenessObserver)
            else estimator.step(y, u)
        )
        x_hat[k], f_hat[k], in_domain[k] = step.state[0], step.faults[0], step.in_domain[0]
        f_hat[k, 0] /= inputs.rho[k]
        if isinstance(step, EffectivenessStep):
            if alpha is None or bias is None:
                alpha, bias = np.ones((n, 2)), np.zeros((n, 2))
            alpha[k], bias[k], alpha_sigma = step.alpha[0], step.bias[0], step.alpha_sigma
            bias[k, 0] /= inputs.rho[k]
        if np.isfinite(x_hat[k]).all() and np.isfinite(f_hat[k]).all():
            before = levels.beyond_grip
            levels.update(row, f_hat[k : k + 1], t, certified=step.certified, measured=y)
            beyond_grip[k], judged[k] = levels.beyond_grip > before, levels.judged(row, t)[0]
            if alpha is not None and judged[k]:
                effectiveness.update(row, alpha[k : k + 1], alpha_sigma, t)
        else:
            estimator = None
            restarts += 1
        level[k] = (
            max(levels.torque.level[0], effectiveness.torque.level[0]),
            max(levels.steer.level[0], effectiveness.steer.level[0]),
        )
    return Replay(x_hat, f_hat, in_domain, level, restarts, beyond_grip, judged, bias, alpha)


def service_inputs(recording: Recording, payload_kg: float, gains: ObserverGains) -> ServiceInputs | None:
    """The demands the service steps a vehicle carrying ``payload_kg`` on the recording's road grade (its ``grade``
    column; level ground without one) with, None when neither changes them; a bad payload is a CommandError."""
    limit = gains.params.mass_kg
    if not (math.isfinite(payload_kg) and 0.0 <= payload_kg <= limit):
        raise CommandError(
            f"--payload-kg must be finite, >= 0 and at most the profile's mass_kg ({limit:g}), got {payload_kg}"
        )
    if payload_kg == 0.0 and recording.grade is None:
        return None
    from synth.model import model_inputs

    payload = payload_kg if payload_kg > 0.0 else None
    model_u, stage_u, rho = model_inputs(recording.y, recording.u, payload, recording.grade, gains.params)
    return ServiceInputs(model_u, stage_u, np.broadcast_to(1.0 if rho is None else rho, (len(recording),)))


def level_summary(t: FloatArray, levels: np.ndarray, profile: VehicleProfileFile) -> list[str]:
    """One line per fault channel: time at WARN and at FAULT, and when it first reached WARN (or higher) and
    FAULT. t : (K,) [s]; levels : (K, 2) level ranks of [torque, steer]."""
    from service.fleet.alarms import FAULT, WARN

    a = profile.alarms
    period_s = float(np.median(np.diff(t))) if t.size > 1 else 0.0
    thresholds = {
        "torque": f"|T_f| >= {a.torque_warn_nm:g} / {a.torque_fault_nm:g} N m",
        "steer": f"|delta_f| >= {a.steer_warn_rad:g} / {a.steer_fault_rad:g} rad",
    }
    rule = (
        f"a CUSUM on {a.cusum_block_s:g} s block means tuned for shifts of WARN / FAULT, "
        f"{a.cusum_false_alarms_per_1000_h:g} false alarm(s) per 1,000 h"
        if a.rule == "cusum"
        else f"WARN / FAULT held {a.raise_after_s:g} s"
    )
    lines = [f"alarm levels with the thresholds of {profile.source} ({rule}, after a {a.warmup_s:g} s warm-up):"]
    for c, name in enumerate(CHANNELS):
        parts = []
        for level, label in ((WARN, "WARN"), (FAULT, "FAULT")):
            reached = np.flatnonzero(levels[:, c] >= level)
            first = f"first at t = {t[reached[0]]:.2f} s" if reached.size else "never"
            parts.append(f"{label} {np.count_nonzero(levels[:, c] == level) * period_s:.2f} s ({first})")
        lines.append(f"  {name:<6} ({thresholds[name]}): {', '.join(parts)}")
    return lines


def grip_summary(t: FloatArray, result: Replay, alarms: AlarmThresholds) -> list[str]:
    """What the grip gate did: how long the recording was beyond the grip limits, and each level raised to WARN
    (or higher) within ``warmup_s`` of the gate's hold ending (on a healthy recording: the model's miss beyond
    the tyres' grip outlasting the hold, docs/math.md 12.4). t : (K,) [s]; none if the gate flagged nothing."""
    from service.fleet.alarms import WARN

    if not result.beyond_grip.any():
        return []
    a = alarms
    lines = [
        f"beyond the grip limits ({a.grip_limit_g:g} g combined while braking or accelerating at "
        f"{a.grip_longitudinal_g:g} g or more, {a.grip_cornering_g:g} g in any case) "
        f"{result.beyond_grip.mean():.1%} of the time: the fault levels were held there and for "
        f"{a.grip_hold_s:g} s after (judged {result.judged.mean():.1%} of the time)"
    ]
    flagged = np.flatnonzero(result.beyond_grip)
    raised = []
    for c, name in enumerate(CHANNELS):
        at_warn = result.levels[:, c] >= WARN
        for k in np.flatnonzero(at_warn & ~np.concatenate([[False], at_warn[:-1]])):
            before = flagged[flagged < k]
            after_s = float(t[k] - t[before[-1]] - a.grip_hold_s) if before.size else -1.0
            if 0.0 <= after_s <= a.warmup_s:
                raised.append(f"  {name} reached WARN at t = {t[k]:.2f} s, {after_s:.2f} s after the hold ended")
    if raised:
        lines.append(f"levels raised within the warm-up ({a.warmup_s:g} s) of the grip gate's hold ending:")
        lines += raised
        lines.append(
            "  on a healthy recording that is the model's miss beyond the tyres' grip outlasting the hold: lower "
            "alarms.grip_limit_g and alarms.grip_longitudinal_g (a vehicle high for its track) or lengthen "
            "alarms.grip_hold_s (docs/math.md 12.4)"
        )
    return lines


def outside_limits(recording: Recording, limits: InputLimits) -> np.ndarray:
    """(K,) bool: the samples the service would reject as out of range under these plausibility limits."""
    vx, r = recording.y[:, 0], recording.y[:, 1]
    torque, steer = recording.u[:, 0], recording.u[:, 1]
    return np.asarray(
        (vx < limits.vx_min_mps)
        | (vx > limits.vx_max_mps)
        | (np.abs(r) > limits.r_abs_max_radps)
        | (np.abs(torque) > limits.torque_abs_max_nm)
        | (np.abs(steer) > limits.steer_abs_max_rad)
        | (False if recording.grade is None else np.abs(recording.grade) > limits.grade_abs_max_rad)
    )


def _initial_state(text: str | None) -> Any:
    if text is None:
        return None
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise CommandError(f"--initial-state: expected three numbers VX,VY,R, got {text!r}") from None
    if len(values) != 3 or not np.all(np.isfinite(values)):
        raise CommandError(f"--initial-state: expected three finite numbers VX,VY,R, got {text!r}")
    return np.array([values])
