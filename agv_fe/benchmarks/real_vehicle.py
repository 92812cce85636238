"""Real vehicle: calibration, false alarms and fault detection on CommonRoad's multi-body model.

The plant is :mod:`edge_client.multibody` (the 29-state multi-body vehicle of
``commonroad-vehicle-models`` with actuators, a closed-loop driver and sensor
noise), which the estimator was not derived from. Per parameter set:

1. **Calibration**: the scripted two-minute :func:`edge_client.multibody.calibration_drive`
   (brisk turn entries, lane changes and slaloms at 10-20 m/s: the recommended
   calibration procedure) through :func:`service.calibration.calibrate_profile`,
   the identified parameters against the MB's own values
   (:func:`edge_client.multibody.reference_values`); everything below is measured
   with this profile;
2. **Healthy driving**: random drives (seeds distinct from the calibration's)
   through the calibrated observer, the augmented EKF (thresholds set the same
   way from its own estimates on the calibration drive) and the ``paper``
   profile (the paper's vehicle, default design, default thresholds); alarms
   counted by the service's own :class:`service.fleet.alarms.FaultLevels`;
3. **Faults**: biases, loss-of-effectiveness ramps and sinusoidal faults on
   both channels, onset at 10 s of a 30 s drive: delays to WARN and FAULT,
   the other channel's level, the RMSE against the true fault;
4. **Sensitivity to the calibration drive**: calibrations from random two-minute
   drives instead, their identification errors, thresholds and alarms on the
   same healthy driving.

The benchmark measures; it adjusts nothing. Any CommonRoad set id with
multi-body data can be passed (``parameter_sets``); the default is (1, 3).
"""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from agv_fe.benchmarks import report_header
from edge_client import multibody as mb
from edge_client.faults import CHANNEL_INDEX, BiasFault, Channel, Fault, LossOfEffectivenessFault, SinusoidalFault
from edge_client.simulation import (
    EstimatorFactory,
    effectiveness_factory,
    ekf_factory,
    observer_factory,
    payload_factory,
)
from service.calibration import (
    CHANNELS,
    UNITS,
    CalibrationReport,
    ChannelThresholds,
    block_sigma,
    calibrate_profile,
    effectiveness_stepper,
    fault_thresholds,
    gust_drives,
    healthy_fault_estimates,
    held_peaks,
)
from service.calibration import channel_thresholds as calibrated_thresholds
from service.fleet.alarms import FAULT, LEVEL_NAMES, OK, WARN, FaultLevels
from service.profiles import AlarmThresholds
from synth.calibration import Drive as Recording
from synth.design import synthesize
from synth.effectiveness import EffectivenessStep
from synth.errors import SynthesisError
from synth.gains import ObserverGains
from synth.model import FloatArray, model_inputs
from synth.options import DesignOptions
from synth.params import OperatingBounds, VehicleParams

DEFAULT_PARAMETER_SETS = (1, 3)
#: The calibration drive is the scripted mb.calibration_drive(), sensor noise seed CALIBRATION_SEED_OFFSET + set.
CALIBRATION_SEED_OFFSET = 100
#: Sensitivity to the calibration drive: one calibration from random_drive(seed, SENSITIVITY_DURATION_S) per seed
#: (the seed of the drive and of the sensor noise).
SENSITIVITY_SEEDS = (200, 201, 202)
QUICK_SENSITIVITY_SEEDS = (200,)
SENSITIVITY_DURATION_S = 120.0
#: Healthy driving: one random drive per seed [s].
HEALTHY_SEEDS = tuple(range(1, 31))
HEALTHY_DURATION_S = 60.0
QUICK_HEALTHY_SEEDS = (1, 2, 3, 4)
#: Every URBAN_EVERY-th healthy seed drives in town: speeds in URBAN_SPEED_MPS [m/s], yaw rates to
#: URBAN_YAW_RATE_RADPS [rad/s] (tight corners, beyond the calibration drive's envelope at its speeds); the others
#: random_drive's defaults (8 to 22 m/s, 0.5 rad/s). The lateral limit is MAX_LATERAL_ACCEL_MPS2 for both.
URBAN_EVERY = 3
URBAN_SPEED_MPS = (6.0, 12.0)
URBAN_YAW_RATE_RADPS = 0.65
#: The healthy seeds one after the urban ones (seed % URBAN_EVERY == 1) brake and accelerate in turns
#: (mb.combined_drive: |a_y| to COMBINED_LATERAL_ACCEL_MPS2, |a_x| to COMBINED_ACCEL_MPS2, 10 to 22 m/s), where
#: the load moves between the axles (docs/math.md 12.4).
COMBINED_LATERAL_ACCEL_MPS2 = (2.0, 4.5)
COMBINED_ACCEL_MPS2 = 3.5
#: Every other one of those (seed % (2 URBAN_EVERY) == URBAN_EVERY + 1) brakes and accelerates hard in faster
#: turns: combined accelerations to 0.8 g, beyond the profile's grip limit (docs/math.md 12.4).
HARD_COMBINED_LATERAL_ACCEL_MPS2 = (4.0, 5.5)
HARD_COMBINED_ACCEL_MPS2 = 5.5
QUICK_HEALTHY_DURATION_S = 30.0
#: Fault runs: seeds of the drive and of the sensor noise, distinct from the healthy and calibration seeds.
FAULT_SEEDS = (1001, 1002, 1003)
QUICK_FAULT_SEEDS = (1001,)
FAULT_DURATION_S = 30.0
FAULT_ONSET_S = 10.0
#: Processes simulating the plant.
WORKERS = 2
#: Lateral acceleration of the random drives' manoeuvre limit [m/s^2] (random_drive's default).
MAX_LATERAL_ACCEL_MPS2 = 7.0
#: random_drive's peak |a_x| on a dry road [m/s^2] (its default)
RANDOM_ACCEL_MPS2 = 3.0
#: Must-show targets: identification errors (relative), detection delays after the onset [s].
EFFECTIVE_MASS_TOLERANCE = 0.01
CORNERING_STIFFNESS_TOLERANCE = 0.05
BIAS_WARN_WITHIN_S = 1.5
BIAS_FAULT_WITHIN_S = 2.5
LOSS_WARN_WITHIN_S = 6.0
#: The faults: a torque share of the nominal drive torque, a steering angle [rad], the loss ramp and the sines.
TORQUE_SHARE = 0.10
STEER_RAD = 0.02
LOSS_RATE_PER_S = 0.04
LOSS_ALPHA_MIN = 0.6
SINE_OMEGA_RADPS = 0.5
#: The drive of a torque loss: speed changes between these speeds [m/s], at most this acceleration [m/s^2]
#: and this specific power [W/kg] (random_drive's, capped at 80 % of the vehicle's a_max v_switch).
LOSS_SPEED_LOW_MPS = (8.0, 10.0)
LOSS_SPEED_HIGH_MPS = (15.0, 18.0)
LOSS_PEAK_ACCEL_MPS2 = 2.5
LOSS_SPECIFIC_POWER_W_PER_KG = 45.0
#: The drive of a steering loss: a steady turn at this lateral acceleration [m/s^2], at a speed in this range
#: [m/s], settled this long before the onset [s].
CORNERING_LATERAL_ACCEL_MPS2 = 4.0
CORNERING_SPEED_MPS = (10.0, 14.0)
CORNERING_SETTLED_S = 2.0
#: When the report shows the estimate around an onset [s after the onset].
TIME_COURSE_OFFSETS_S = (-1.0, 0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 6.0)
#: At most this many alarm events listed per estimator in the report.
LISTED_ALARMS = 12
#: Alarm events kept in the JSON per estimator and set (the counts cover them all).
KEPT_EVENTS = 50

ESTIMATOR_LABELS: dict[str, str] = {
    "calibrated": "calibrated observer",
    "effectiveness": "calibrated observer + effectiveness stage",
    "EKF": "augmented EKF",
    "paper": "`paper` profile (before)",
}
SYMBOLS = {"torque": "T_f", "steer": "delta_f"}
LevelArray = NDArray[np.int8]


# --------------------------------------------------------------------------- what is run


@dataclass(frozen=True)
class Plan:
    """Seeds and durations of one benchmark run."""

    parameter_sets: tuple[int, ...]
    healthy_seeds: tuple[int, ...]
    healthy_duration_s: float
    fault_seeds: tuple[int, ...]
    sensitivity_seeds: tuple[int, ...]
    fault_duration_s: float = FAULT_DURATION_S
    fault_onset_s: float = FAULT_ONSET_S
    sensitivity_duration_s: float = SENSITIVITY_DURATION_S
    workers: int = WORKERS
    quick: bool = False

    @classmethod
    def make(
        cls,
        parameter_sets: Sequence[int],
        quick: bool,
        workers: int,
        healthy_seeds: Sequence[int] | None = None,
        healthy_duration_s: float | None = None,
        fault_seeds: Sequence[int] | None = None,
        sensitivity_seeds: Sequence[int] | None = None,
    ) -> Plan:
        """The plan of a full (or ``quick``) run; the seeds and the healthy duration may be overridden."""
        sets = tuple(int(s) for s in parameter_sets)
        if not sets or len(set(sets)) != len(sets):
            raise ValueError(f"parameter_sets must be distinct set ids, at least one, got {parameter_sets!r}")
        for s in sets:
            mb.vehicle_parameters(s)  # an unknown set, or one without multi-body data, raises MultibodyError
        healthy = tuple(healthy_seeds) if healthy_seeds is not None else QUICK_HEALTHY_SEEDS if quick else HEALTHY_SEEDS
        faulty = tuple(fault_seeds) if fault_seeds is not None else QUICK_FAULT_SEEDS if quick else FAULT_SEEDS
        sensitivity = (
            tuple(sensitivity_seeds)
            if sensitivity_seeds is not None
            else QUICK_SENSITIVITY_SEEDS
            if quick
            else SENSITIVITY_SEEDS
        )
        duration = healthy_duration_s or (QUICK_HEALTHY_DURATION_S if quick else HEALTHY_DURATION_S)
        if not healthy or not faulty or not sensitivity:
            raise ValueError("healthy_seeds, fault_seeds and sensitivity_seeds must not be empty")
        if workers < 1 or not duration > 0:
            raise ValueError(f"workers must be >= 1 and healthy_duration_s positive, got {workers}, {duration}")
        return cls(
            parameter_sets=sets,
            healthy_seeds=healthy,
            healthy_duration_s=float(duration),
            fault_seeds=faulty,
            sensitivity_seeds=sensitivity,
            workers=workers,
            quick=quick,
        )


@dataclass(frozen=True)
class DelayTarget:
    """Must-show: WARN (and FAULT) within these delays after the onset in every seed [s]."""

    warn_s: float
    fault_s: float | None = None
    other_channel_ok: bool = False


DriveKind = Literal["random", "accelerate_brake", "cornering"]
FaultKind = Literal["bias", "loss_of_effectiveness", "sinusoidal"]


@dataclass(frozen=True)
class FaultCase:
    """One fault of section 3: ``size`` is a share of the nominal drive torque (torque) or an angle [rad]
    (steer); a loss of effectiveness ramps alpha from 1 to LOSS_ALPHA_MIN at LOSS_RATE_PER_S."""

    key: str
    label: str
    channel: Channel
    kind: FaultKind
    size: float
    drive_kind: DriveKind
    target: DelayTarget | None = None

    @property
    def other_channel(self) -> Channel:
        return "steer" if self.channel == "torque" else "torque"

    def faults(self, nominal_torque_nm: float, onset_s: float) -> tuple[Fault, ...]:
        """The fault of this case for a vehicle whose nominal drive torque is ``nominal_torque_nm`` [N m]."""
        scale = nominal_torque_nm if self.channel == "torque" else 1.0
        if self.kind == "bias":
            return (BiasFault(channel=self.channel, onset_s=onset_s, magnitude=self.size * scale),)
        if self.kind == "sinusoidal":
            return (
                SinusoidalFault(
                    channel=self.channel, onset_s=onset_s, amplitude=self.size * scale, omega_radps=SINE_OMEGA_RADPS
                ),
            )
        return (
            LossOfEffectivenessFault(
                channel=self.channel, onset_s=onset_s, rate_per_s=LOSS_RATE_PER_S, alpha_min=LOSS_ALPHA_MIN
            ),
        )


_BIAS_TARGET = DelayTarget(BIAS_WARN_WITHIN_S, BIAS_FAULT_WITHIN_S, other_channel_ok=True)
_LOSS_TARGET = DelayTarget(LOSS_WARN_WITHIN_S)
FAULT_CASES = (
    FaultCase("torque_bias_plus", "torque bias +10 %", "torque", "bias", TORQUE_SHARE, "random", _BIAS_TARGET),
    FaultCase("torque_bias_minus", "torque bias -10 %", "torque", "bias", -TORQUE_SHARE, "random", _BIAS_TARGET),
    FaultCase("steer_bias_plus", "steering bias +0.02 rad", "steer", "bias", STEER_RAD, "random", _BIAS_TARGET),
    FaultCase("steer_bias_minus", "steering bias -0.02 rad", "steer", "bias", -STEER_RAD, "random", _BIAS_TARGET),
    FaultCase(
        "torque_loss",
        "torque loss of effectiveness (alpha 1 to 0.6 in 10 s)",
        "torque",
        "loss_of_effectiveness",
        LOSS_ALPHA_MIN,
        "accelerate_brake",
        _LOSS_TARGET,
    ),
    FaultCase(
        "steer_loss",
        "steering loss of effectiveness (alpha 1 to 0.6 in 10 s)",
        "steer",
        "loss_of_effectiveness",
        LOSS_ALPHA_MIN,
        "cornering",
        _LOSS_TARGET,
    ),
    FaultCase("torque_sine", "torque sine 10 % at 0.5 rad/s", "torque", "sinusoidal", TORQUE_SHARE, "random"),
    FaultCase("steer_sine", "steering sine 0.02 rad at 0.5 rad/s", "steer", "sinusoidal", STEER_RAD, "random"),
)
DRIVE_DESCRIPTIONS: dict[str, str] = {
    "random": "random drive (random_drive, 30 s)",
    "accelerate_brake": "accelerating and braking on a straight after the onset",
    "cornering": f"steady turn at {CORNERING_LATERAL_ACCEL_MPS2:g} m/s^2 from before the onset",
}


# --------------------------------------------------------------------------- drives


def accelerate_brake_drive(seed: int, parameter_set: int, duration_s: float, onset_s: float) -> mb.Drive:
    """Cruise straight until ``onset_s``, then accelerate and brake between two speeds until the end.

    The speeds are drawn from LOSS_SPEED_LOW_MPS and LOSS_SPEED_HIGH_MPS; the peak acceleration is
    LOSS_PEAK_ACCEL_MPS2, or less where the specific power a v would pass LOSS_SPECIFIC_POWER_W_PER_KG or
    80 % of the vehicle's a_max v_switch [W/kg]. Deterministic for a seed.
    """
    rng = np.random.default_rng(seed)
    low = float(rng.uniform(*LOSS_SPEED_LOW_MPS))
    high = float(rng.uniform(*LOSS_SPEED_HIGH_MPS))
    longitudinal = mb.vehicle_parameters(parameter_set).longitudinal
    power = min(LOSS_SPECIFIC_POWER_W_PER_KG, 0.8 * float(longitudinal.a_max) * float(longitudinal.v_switch))
    peak = min(LOSS_PEAK_ACCEL_MPS2, power / high)
    builder = mb._DriveBuilder(limit_s=duration_s, current_speed_mps=low)
    builder.cruise(onset_s)
    while not builder.full:
        builder.change_speed(high, peak)
        builder.cruise(0.5)
        builder.change_speed(low, peak)
        builder.cruise(0.5)
    return builder.build(f"accelerate_brake_{seed}")


def cornering_drive(seed: int, duration_s: float, onset_s: float) -> mb.Drive:
    """Cruise straight, then a steady turn at CORNERING_LATERAL_ACCEL_MPS2, settled CORNERING_SETTLED_S before
    ``onset_s`` and held to the end; the speed (CORNERING_SPEED_MPS) and the direction are drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    speed = float(rng.uniform(*CORNERING_SPEED_MPS))
    sign = float(rng.choice([-1.0, 1.0]))
    builder = mb._DriveBuilder(limit_s=duration_s, current_speed_mps=speed)
    yaw_rate = sign * CORNERING_LATERAL_ACCEL_MPS2 / speed
    ramp_s = max(1.5 * abs(yaw_rate) / builder.yaw_accel_limit(speed), 0.3)
    builder.cruise(max(onset_s - ramp_s - CORNERING_SETTLED_S, 1.0))
    builder.turn(yaw_rate, hold_s=duration_s)
    return builder.build(f"cornering_{seed}")


def fault_drive(case: FaultCase, seed: int, parameter_set: int, plan: Plan, grip: float = 1.0) -> mb.Drive:
    """The drive a fault case runs on, for one seed; a random one's accelerations scaled by ``grip`` (see
    :func:`healthy_drive`)."""
    if case.drive_kind == "accelerate_brake":
        return accelerate_brake_drive(seed, parameter_set, plan.fault_duration_s, plan.fault_onset_s)
    if case.drive_kind == "cornering":
        return cornering_drive(seed, plan.fault_duration_s, plan.fault_onset_s)
    return open_road_drive(seed, plan.fault_duration_s, grip)


def calibration_job(parameter_set: int) -> mb.MultibodyJob:
    """The calibration everything is measured with: the scripted calibration drive, noise seed 100 + set."""
    return mb.MultibodyJob(
        drive=mb.calibration_drive(), parameter_set=parameter_set, seed=CALIBRATION_SEED_OFFSET + parameter_set
    )


def sensitivity_jobs(parameter_set: int, plan: Plan) -> list[mb.MultibodyJob]:
    """The random calibration drives of the sensitivity check, one per seed (drive and sensor noise)."""
    return [
        mb.MultibodyJob(
            drive=mb.random_drive(seed, plan.sensitivity_duration_s, max_lateral_accel_mps2=MAX_LATERAL_ACCEL_MPS2),
            parameter_set=parameter_set,
            seed=seed,
        )
        for seed in plan.sensitivity_seeds
    ]


def healthy_drive(seed: int, duration_s: float, grip: float = 1.0) -> mb.Drive:
    """The healthy random drive of ``seed``: in town for every URBAN_EVERY-th seed, braking and accelerating in
    turns for the seeds after those (every other one hard), else on open roads. ``grip`` scales every
    acceleration the drive asks for (a driver on a road of that share of the dry road's friction)."""
    if seed % (2 * URBAN_EVERY) == URBAN_EVERY + 1:
        return mb.combined_drive(
            seed,
            duration_s,
            lateral_accel_mps2=_scaled(HARD_COMBINED_LATERAL_ACCEL_MPS2, grip),
            max_accel_mps2=HARD_COMBINED_ACCEL_MPS2 * grip,
        )
    if seed % URBAN_EVERY == 1:
        return mb.combined_drive(
            seed,
            duration_s,
            lateral_accel_mps2=_scaled(COMBINED_LATERAL_ACCEL_MPS2, grip),
            max_accel_mps2=COMBINED_ACCEL_MPS2 * grip,
        )
    if seed % URBAN_EVERY == 0:
        return mb.random_drive(
            seed,
            duration_s,
            speed_range_mps=URBAN_SPEED_MPS,
            max_yaw_rate_radps=URBAN_YAW_RATE_RADPS,
            max_lateral_accel_mps2=MAX_LATERAL_ACCEL_MPS2 * grip,
            max_accel_mps2=RANDOM_ACCEL_MPS2 * grip,
        )
    return open_road_drive(seed, duration_s, grip)


def _scaled(pair: tuple[float, float], grip: float) -> tuple[float, float]:
    return pair[0] * grip, pair[1] * grip


def open_road_drive(seed: int, duration_s: float, grip: float = 1.0) -> mb.Drive:
    """random_drive with the benchmark's limits, its accelerations scaled by ``grip`` (1: dry)."""
    return mb.random_drive(
        seed,
        duration_s,
        max_lateral_accel_mps2=MAX_LATERAL_ACCEL_MPS2 * grip,
        max_accel_mps2=RANDOM_ACCEL_MPS2 * grip,
    )


def healthy_jobs(parameter_set: int, plan: Plan) -> list[mb.MultibodyJob]:
    return [
        mb.MultibodyJob(drive=healthy_drive(seed, plan.healthy_duration_s), parameter_set=parameter_set, seed=seed)
        for seed in plan.healthy_seeds
    ]


def fault_jobs(parameter_set: int, nominal_torque_nm: float, plan: Plan) -> list[mb.MultibodyJob]:
    """One job per (case, seed), in the order of FAULT_CASES then seeds."""
    return [
        mb.MultibodyJob(
            drive=fault_drive(case, seed, parameter_set, plan),
            parameter_set=parameter_set,
            faults=case.faults(nominal_torque_nm, plan.fault_onset_s),
            seed=seed,
        )
        for case in FAULT_CASES
        for seed in plan.fault_seeds
    ]


def recording(run: mb.MultibodyRun) -> Recording:
    """What the vehicle sends (t, y, u, and the grade on a drive with one) as a calibration recording."""
    name = f"{run.name} (set {run.parameter_set}, seed {run.seed})"
    return Recording(t=run.t, y=run.y, u=run.u, name=name, grade=run.grade_rad)


# --------------------------------------------------------------------------- estimators and alarm levels


@dataclass(frozen=True)
class Estimated:
    """One run through one estimator with the service's alarm levels, K samples.

    f_hat (K, 2) fault estimates [T_f N m, delta_f rad]; levels (K, 2) level ranks of [torque, steer]
    (service.fleet.alarms.LEVEL_NAMES) after each sample; in_domain (K,) premise in the design box; finite (K,)
    the estimate was finite (a non-finite one is not fed to the levels); assessed (K,) the levels judged the
    sample (finite, after the warm-up, which runs again after each sample outside the certified domain, and not
    within the profile's grip_hold_s of a sample beyond its grip limit).
    """

    f_hat: FloatArray
    levels: LevelArray
    in_domain: NDArray[np.bool_]
    finite: NDArray[np.bool_]
    assessed: NDArray[np.bool_]
    #: (K,) the levels were held by the grip gate (within grip_hold_s of a sample beyond the grip limit)
    grip_held: NDArray[np.bool_]
    #: the effectiveness stage's alpha_hat (K, 2) [torque, steer]; None for the other estimators
    alpha: FloatArray | None = None


def estimate_runs(
    factory: EstimatorFactory, runs: Sequence[mb.MultibodyRun], alarms: AlarmThresholds
) -> list[Estimated]:
    """Run the estimator and :class:`FaultLevels` over the runs; results in run order.

    Runs of equal length share one batch: one estimator step per sample for all of them. Each observer
    starts from its run's first measurement (u0 = first demand) at t = 0, where the warm-up starts; time
    stamps t_ns = round(t * 1e9) [ns], as the service and ``agv-fe replay`` use.
    """
    out: list[Estimated | None] = [None] * len(runs)
    by_length: dict[int, list[int]] = {}
    for i, run in enumerate(runs):
        by_length.setdefault(len(run), []).append(i)
    for indices in by_length.values():
        for i, result in zip(indices, _estimate_batch(factory, [runs[i] for i in indices], alarms), strict=True):
            out[i] = result
    return [r for r in out if r is not None]


def _estimate_batch(
    factory: EstimatorFactory, runs: Sequence[mb.MultibodyRun], alarms: AlarmThresholds
) -> list[Estimated]:
    """One batch of runs with identical sample times."""
    t = runs[0].t
    for run in runs[1:]:
        if not np.array_equal(run.t, t):
            raise ValueError(f"{run.name}: a batch needs identical sample times")
    y = np.stack([run.y for run in runs], axis=1)  # (K, nv, 2)
    u = np.stack([run.u for run in runs], axis=1)
    n, nv = y.shape[0], y.shape[1]
    t_ns = np.rint(t * 1e9).astype(np.int64)
    rows = np.arange(nv, dtype=np.intp)
    estimator = factory(y[0], None, u[0])
    levels = FaultLevels(nv, alarms)
    levels.restart(rows, np.full(nv, t_ns[0], dtype=np.int64))
    f_hat = np.empty((n, nv, 2))
    level = np.empty((n, nv, 2), dtype=np.int8)
    in_domain = np.empty((n, nv), dtype=bool)
    finite = np.empty((n, nv), dtype=bool)
    assessed = np.empty((n, nv), dtype=bool)
    grip_held = np.empty((n, nv), dtype=bool)
    alpha: FloatArray | None = None
    for k in range(n):
        step = estimator.step(y[k], u[k])
        f_hat[k] = step.faults
        if isinstance(step, EffectivenessStep):
            if alpha is None:
                alpha = np.ones((n, nv, 2))
            alpha[k] = step.alpha
        in_domain[k] = step.in_domain
        finite[k] = np.isfinite(f_hat[k]).all(axis=1)
        usable = None if finite[k].all() else finite[k]
        t_k = np.full(nv, t_ns[k], dtype=np.int64)
        levels.update(rows, f_hat[k], t_k, usable, step.certified, y[k])
        assessed[k] = finite[k] & levels.judged(rows, t_k)
        grip_held[k] = t_k < levels.held_until_ns
        level[k, :, 0] = levels.torque.level
        level[k, :, 1] = levels.steer.level
    return [
        Estimated(
            f_hat[:, j],
            level[:, j],
            in_domain[:, j],
            finite[:, j],
            assessed[:, j],
            grip_held[:, j],
            None if alpha is None else alpha[:, j],
        )
        for j in range(nv)
    ]


def ekf_thresholds(
    report: CalibrationReport, calibration_run: mb.MultibodyRun
) -> tuple[dict[str, ChannelThresholds], AlarmThresholds]:
    """The EKF's thresholds set as calibration sets the observer's: :func:`fault_thresholds` on its own
    estimates of the calibration drive after the warm-up, with the same false-alarm rate, persistence and
    required bias (no certified bound: NaN), above what the calibration's wind gust makes the EKF report on the
    identified model (:func:`service.calibration.gust_drives`); the other alarm settings are the profile's."""
    alarms = report.profile.alarms
    (estimated,) = estimate_runs(ekf_factory(report.gains), [calibration_run], alarms)
    after = calibration_run.t >= alarms.warmup_s
    ekf = ekf_factory(report.gains)
    gusts = gust_drives(report.profile.params, report.profile.bounds, report.gust_n)
    gust = held_peaks(lambda y0, u0: ekf(y0, None, u0), gusts, alarms.raise_after_s)
    thresholds = {
        channel: fault_thresholds(
            estimated.f_hat[after, i],
            math.nan,
            sample_period_s=report.profile.params.sample_period_s,
            persistence_s=alarms.raise_after_s,
            false_alarms_per_1000_h=report.false_alarms_per_1000_h,
            required_bias=report.thresholds[channel].required_bias,
            gust_peak=float(gust[i]),
        )
        for i, channel in enumerate(CHANNELS)
    }
    block_n = max(1, round(alarms.cusum_block_s / report.profile.params.sample_period_s))
    settings = alarms.model_dump() | {
        "torque_block_sigma_nm": block_sigma(estimated.f_hat[after, 0], block_n),
        "steer_block_sigma_rad": block_sigma(estimated.f_hat[after, 1], block_n),
        "torque_warn_nm": thresholds["torque"].warn,
        "torque_fault_nm": thresholds["torque"].fault,
        "steer_warn_rad": thresholds["steer"].warn,
        "steer_fault_rad": thresholds["steer"].fault,
    }
    return thresholds, AlarmThresholds.model_validate(settings)


def effectiveness_alarms(report: CalibrationReport, calibration_run: mb.MultibodyRun) -> AlarmThresholds:
    """The profile's alarms with the fault thresholds `agv-fe calibrate --effectiveness` sets: from the stage's
    total faults on the calibration drive and in the calibration's gust (the identified model, design and stage
    noise are the report's; service.calibration.calibrate_profile does the same with effectiveness=True)."""
    alarms = report.profile.alarms
    stage = report.profile.effectiveness.model_copy(update={"enabled": True})
    estimates = healthy_fault_estimates(report.gains, [recording(calibration_run)], alarms.warmup_s, stage)
    gusts = gust_drives(report.profile.params, report.profile.bounds, report.gust_n)
    gust = held_peaks(effectiveness_stepper(report.gains, stage), gusts, alarms.raise_after_s)
    nominal = report.nominal_torque_nm
    thresholds = calibrated_thresholds(report.gains, estimates, gust, alarms, report.false_alarms_per_1000_h, nominal)
    return alarms.model_copy(
        update={
            "torque_warn_nm": thresholds["torque"].warn,
            "torque_fault_nm": thresholds["torque"].fault,
            "steer_warn_rad": thresholds["steer"].warn,
            "steer_fault_rad": thresholds["steer"].fault,
        }
    )


def channel_thresholds(alarms: AlarmThresholds) -> dict[str, tuple[float, float]]:
    """(WARN, FAULT) per channel [N m], [rad]."""
    return {
        "torque": (alarms.torque_warn_nm, alarms.torque_fault_nm),
        "steer": (alarms.steer_warn_rad, alarms.steer_fault_rad),
    }


# --------------------------------------------------------------------------- healthy figures


def raises(levels: LevelArray) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Sample indices where a level (K,) was raised to WARN or higher from OK, and to FAULT from below."""
    before = np.concatenate([[OK], levels[:-1]]).astype(np.int8)
    to_warn = np.flatnonzero((before == OK) & (levels >= WARN))
    to_fault = np.flatnonzero((before < FAULT) & (levels == FAULT))
    return to_warn, to_fault


def held_peak(magnitude: FloatArray, window: int) -> tuple[float, int]:
    """The largest value a series (K,) held for ``window`` consecutive samples (max of running minima), and
    the index where that window starts (-1 for a series shorter than the window)."""
    if magnitude.size < window or window < 1:
        return 0.0, -1
    held = np.lib.stride_tricks.sliding_window_view(magnitude, window).min(axis=1)
    start = int(np.argmax(held))
    return float(held[start]), start


@dataclass(frozen=True)
class AlarmEvent:
    """A level raised on healthy driving: where, when, how high, and what the vehicle was doing."""

    seed: int
    channel: str
    t_s: float
    level: str
    estimate: float
    lateral_accel_mps2: float
    speed_mps: float


def healthy_figures(
    runs: Sequence[mb.MultibodyRun], estimated: Sequence[Estimated], alarms: AlarmThresholds, sample_period_s: float
) -> dict[str, Any]:
    """Alarm counts, peaks and RMS of the fault estimates over healthy runs, on the samples the levels judged
    (after the warm-up, which runs again after each sample outside the certified domain)."""
    window = max(1, round(alarms.raise_after_s / sample_period_s))
    thresholds = channel_thresholds(alarms)
    per_channel: dict[str, Any] = {}
    events: list[AlarmEvent] = []
    drives_with_alarm: set[int] = set()
    for c, channel in enumerate(CHANNELS):
        warn_raised = fault_raised = 0
        peak = held = 0.0
        held_at: dict[str, float] | None = None
        squares = 0.0
        count = 0
        for run, est in zip(runs, estimated, strict=True):
            # a sample the levels did not judge holds nothing: 0 there, so no window spans it
            judged = np.where(est.assessed, np.abs(np.nan_to_num(est.f_hat[:, c])), 0.0)
            magnitude = judged[est.assessed]
            if magnitude.size:
                peak = max(peak, float(magnitude.max()))
                run_held, start = held_peak(judged, window)
                if start >= 0 and run_held > held:
                    k = np.arange(start, start + window)
                    held = run_held
                    held_at = {
                        "seed": run.seed,
                        "t_s": float(run.t[k[0]]),
                        "peak_lateral_accel_mps2": float(np.abs(run.a_y[k]).max()),
                        "speed_mps": float(run.x_true[k[0], 0]),
                    }
                squares += float(np.sum(magnitude**2))
                count += magnitude.size
            to_warn, to_fault = raises(est.levels[:, c])
            warn_raised += int(to_warn.size)
            fault_raised += int(to_fault.size)
            for k in sorted({*to_warn.tolist(), *to_fault.tolist()}):
                drives_with_alarm.add(run.seed)
                events.append(
                    AlarmEvent(
                        seed=run.seed,
                        channel=channel,
                        t_s=float(run.t[k]),
                        level=LEVEL_NAMES[int(est.levels[k, c])],
                        estimate=float(est.f_hat[k, c]),
                        lateral_accel_mps2=float(run.a_y[k]),
                        speed_mps=float(run.x_true[k, 0]),
                    )
                )
        per_channel[channel] = {
            "warn_threshold": thresholds[channel][0],
            "fault_threshold": thresholds[channel][1],
            "warn_raised": warn_raised,
            "fault_raised": fault_raised,
            "peak_abs_estimate": peak,
            "held_peak_abs_estimate": held,
            "held_peak_at": held_at,
            "rms_estimate": math.sqrt(squares / count) if count else 0.0,
        }
    samples = sum(len(run) for run in runs)
    return {
        "channels": per_channel,
        "drives_with_alarm": sorted(drives_with_alarm),
        "in_domain_share": sum(int(e.in_domain.sum()) for e in estimated) / max(samples, 1),
        "assessed_share": sum(int(e.assessed.sum()) for e in estimated) / max(samples, 1),
        "grip_held_share": sum(int(e.grip_held.sum()) for e in estimated) / max(samples, 1),
        "non_finite_samples": sum(int((~e.finite).sum()) for e in estimated),
        # every alarm counts in the figures above; the first ones are kept to be read (the paper's profile
        # raises hundreds)
        "events_total": len(events),
        "events": [vars(e) for e in sorted(events, key=lambda e: (e.seed, e.t_s, e.channel))[:KEPT_EVENTS]],
    }


def driving_figures(runs: Sequence[mb.MultibodyRun]) -> dict[str, Any]:
    """Minutes driven and how hard: peak |a_y| [m/s^2], time above 5 m/s^2 [s], speed range [m/s]."""
    a_y = np.concatenate([np.abs(run.a_y) for run in runs])
    speed = np.concatenate([run.x_true[:, 0] for run in runs])
    period = mb.SAMPLE_PERIOD_S
    return {
        "drives": len(runs),
        "minutes": sum(len(run) for run in runs) * period / 60.0,
        "peak_lateral_accel_mps2": float(a_y.max()),
        "seconds_above_5_mps2": float(np.count_nonzero(a_y > 5.0) * period),
        "speed_range_mps": [float(speed.min()), float(speed.max())],
    }


# --------------------------------------------------------------------------- fault figures


def first_at_or_above(levels: LevelArray, t: FloatArray, level: int, onset_s: float) -> float | None:
    """Delay from ``onset_s`` to the first sample at or after it whose level is ``level`` or higher [s]."""
    hit = np.flatnonzero((t >= onset_s) & (levels >= level))
    return float(t[hit[0]] - onset_s) if hit.size else None


def fault_run_figures(
    case: FaultCase, run: mb.MultibodyRun, est: Estimated, alarms: AlarmThresholds, onset_s: float
) -> dict[str, Any]:
    """Delays, levels, RMSE and the time course around the onset of one fault run."""
    c, o = CHANNEL_INDEX[case.channel], CHANNEL_INDEX[case.other_channel]
    warm = run.t >= alarms.warmup_s
    before = warm & (run.t < onset_s)
    after = run.t >= onset_s
    error = est.f_hat[after, c] - run.f[after, c]
    course = []
    for offset in TIME_COURSE_OFFSETS_S:
        k = int(np.searchsorted(run.t, onset_s + offset - 1e-9))
        if 0 <= k < len(run):
            course.append(
                {
                    "offset_s": offset,
                    "estimate": float(est.f_hat[k, c]),
                    "true": float(run.f[k, c]),
                    "level": LEVEL_NAMES[int(est.levels[k, c])],
                }
            )
    return {
        "seed": run.seed,
        "warn_delay_s": first_at_or_above(est.levels[:, c], run.t, WARN, onset_s),
        "fault_delay_s": first_at_or_above(est.levels[:, c], run.t, FAULT, onset_s),
        "level_before_onset": LEVEL_NAMES[int(est.levels[before, c].max(initial=OK))],
        "other_channel_level": LEVEL_NAMES[int(est.levels[warm, o].max(initial=OK))],
        "other_channel_peak_abs_estimate": float(np.abs(est.f_hat[warm, o]).max(initial=0.0)),
        "rmse_after_onset": float(np.sqrt(np.mean(error**2))) if error.size else math.nan,
        "true_fault_peak_abs": float(np.abs(run.f[after, c]).max(initial=0.0)),
        "demand_rms_after_onset": float(np.sqrt(np.mean(run.u[after, c] ** 2))) if after.any() else math.nan,
        "demand_peak_abs_after_onset": float(np.abs(run.u[after, c]).max(initial=0.0)),
        "peak_lateral_accel_mps2": float(np.abs(run.a_y).max()),
        "non_finite_samples": int((~est.finite).sum()),
        "time_course": course,
        **effectiveness_figures(case, run, est, alarms, onset_s),
    }


#: The effectiveness target: alpha_hat within this share of the truth this long after the loss ramp ends [s].
ALPHA_TOLERANCE = 0.03
ALPHA_AFTER_RAMP_S = 2.0
#: ... and the stage's total-fault RMSE at most this share of the additive design's, WARN within this long [s].
LOSS_RMSE_SHARE = 1.0 / 3.0
EFFECTIVENESS_WARN_WITHIN_S = 2.0


def effectiveness_figures(
    case: FaultCase, run: mb.MultibodyRun, est: Estimated, alarms: AlarmThresholds, onset_s: float
) -> dict[str, Any]:
    """For the effectiveness stage's runs: alpha_hat on the faulty channel ALPHA_AFTER_RAMP_S after a loss ramp
    ends (and the truth), at the end, and its largest distance from 1 between the warm-up and the onset."""
    if est.alpha is None:
        return {}
    c = CHANNEL_INDEX[case.channel]
    warm = (run.t >= alarms.warmup_s) & (run.t < onset_s)
    out: dict[str, Any] = {
        "alpha_max_deviation_before_onset": float(np.abs(est.alpha[warm, c] - 1.0).max(initial=0.0)),
        "alpha_at_end": float(est.alpha[-1, c]),
    }
    if case.kind == "loss_of_effectiveness":
        at = onset_s + (1.0 - LOSS_ALPHA_MIN) / LOSS_RATE_PER_S + ALPHA_AFTER_RAMP_S
        k = min(int(np.searchsorted(run.t, at - 1e-9)), len(run) - 1)
        out |= {"alpha_after_ramp": float(est.alpha[k, c]), "alpha_true": LOSS_ALPHA_MIN, "alpha_after_ramp_t_s": at}
    return out


def meets(case: FaultCase, seeds: Sequence[dict[str, Any]]) -> bool:
    """The case's must-show target holds in every seed (and the channel was OK before the onset)."""
    target = case.target
    if target is None or not seeds:
        return False
    for s in seeds:
        warn, fault = s["warn_delay_s"], s["fault_delay_s"]
        if s["level_before_onset"] != "OK" or warn is None or warn > target.warn_s:
            return False
        if target.fault_s is not None and (fault is None or fault > target.fault_s):
            return False
        if target.other_channel_ok and s["other_channel_level"] != "OK":
            return False
    return True


# --------------------------------------------------------------------------- calibration figures


#: The MB's values a calibrated parameter is compared with, and the tolerance the issue asks (None: reported).
REFERENCES: dict[str, tuple[str, float | None]] = {
    "effective_mass_kg": ("effective_mass_kg", EFFECTIVE_MASS_TOLERANCE),
    "front_cornering_stiffness_npr": ("front_cornering_stiffness_npr", CORNERING_STIFFNESS_TOLERANCE),
    "rear_cornering_stiffness_npr": ("rear_cornering_stiffness_npr", CORNERING_STIFFNESS_TOLERANCE),
    "yaw_inertia_kgm2": ("yaw_inertia_kgm2", None),
}
#: Parameters the MB has a value for that reference_values does not list: (value, what it is).
PLANT_VALUES: dict[str, tuple[float, str]] = {
    "steer_time_constant_s": (1.0 / mb.STEER_SERVO_GAIN_PER_S, "the steering servo's lag 1 / k_steer"),
    "longitudinal_drag_coeff": (0.0, "the MB has no aerodynamic drag"),
    "rolling_resistance_n": (0.0, "the MB has no rolling resistance"),
}


def calibration_figures(parameter_set: int, report: CalibrationReport, run: mb.MultibodyRun) -> dict[str, Any]:
    """The identified parameters against the MB's values, the noise, residuals, design and thresholds."""
    reference = mb.reference_values(parameter_set)
    parameters = []
    for name, e in report.calibration.estimates.items():
        row: dict[str, Any] = {"name": name, "value": e.value, "ci95": [e.low, e.high], "identified": e.identified}
        if name in REFERENCES:
            key, tolerance = REFERENCES[name]
            ref = reference[key]
            row |= {"reference": ref, "error": e.value / ref - 1.0, "tolerance": tolerance}
            if tolerance is not None:
                row["passed"] = abs(e.value / ref - 1.0) <= tolerance
        elif name in PLANT_VALUES:
            row |= {"plant_value": PLANT_VALUES[name][0], "plant_note": PLANT_VALUES[name][1]}
        parameters.append(row)
    gains = report.gains
    return {
        "drive": {"name": run.name, "noise_seed": run.seed, "duration_s": report.calibration.duration_s},
        "given": mb.base_profile(parameter_set)["params"],
        "parameters": parameters,
        "summary": report.summary(),
        "design": {
            "design": gains.options.design,
            "switched": gains.switched,
            "robust_decay_rate": gains.options.robust_decay_rate,
            "certified_decay_rate": gains.certificate.decay_rate,
            "gain_version": gains.version,
            "fault_order": gains.options.fault_order,
        },
        "bounds": report.profile.bounds.model_dump(mode="json"),
        "alarms": report.profile.alarms.model_dump(mode="json"),
    }


# --------------------------------------------------------------------------- sensitivity to the calibration drive


#: The identified parameters whose error against the MB's value a sensitivity row shows.
SENSITIVITY_PARAMETERS = ("effective_mass_kg", "front_cornering_stiffness_npr", "rear_cornering_stiffness_npr")


def calibrate(parameter_set: int, run: mb.MultibodyRun, payload_kg: float = 0.0) -> CalibrationReport:
    """:func:`calibrate_profile` on one drive with the set's data sheet, told the payload the vehicle carried on
    it; raises what it raises."""
    return calibrate_profile(
        [dataclasses.replace(recording(run), payload_kg=payload_kg)],
        mb.base_profile(parameter_set)["params"],
        description=f"CommonRoad parameter set {parameter_set}, calibrated by the real_vehicle benchmark ({run.name})",
    )


def sensitivity_row(
    parameter_set: int, run: mb.MultibodyRun, outcome: CalibrationReport | str, healthy: dict[str, Any] | None
) -> dict[str, Any]:
    """One calibration of the sensitivity table: its drive, the identification errors against the MB's values,
    the decay rate and thresholds chosen, and the alarms its observer raised on healthy driving (``healthy``:
    :func:`healthy_figures`); ``outcome`` is the report, or the reason calibration refused."""
    driving = driving_figures([run])
    row: dict[str, Any] = {
        "drive": run.name,
        "seed": run.seed,
        "duration_s": driving["minutes"] * 60.0,
        "peak_lateral_accel_mps2": driving["peak_lateral_accel_mps2"],
        "seconds_above_5_mps2": driving["seconds_above_5_mps2"],
    }
    if isinstance(outcome, str):
        return row | {"refused": outcome}
    reference = mb.reference_values(parameter_set)
    estimates = outcome.calibration.estimates
    alarms = outcome.profile.alarms
    channels = healthy["channels"] if healthy is not None else {}
    return row | {
        "refused": None,
        "errors": {
            name: estimates[name].value / reference[REFERENCES[name][0]] - 1.0 for name in SENSITIVITY_PARAMETERS
        },
        # the 95 % interval relative to the MB's value, as the errors
        "error_ci95": {
            name: [
                bound / reference[REFERENCES[name][0]] - 1.0 for bound in (estimates[name].low, estimates[name].high)
            ]
            for name in SENSITIVITY_PARAMETERS
        },
        "robust_decay_rate": outcome.gains.options.robust_decay_rate,
        "alarms": {
            "torque_warn_nm": alarms.torque_warn_nm,
            "torque_fault_nm": alarms.torque_fault_nm,
            "steer_warn_rad": alarms.steer_warn_rad,
            "steer_fault_rad": alarms.steer_fault_rad,
        },
        "healthy": {
            channel: {
                "warn_raised": c["warn_raised"],
                "fault_raised": c["fault_raised"],
                "held_peak_over_warn": c["held_peak_abs_estimate"] / c["warn_threshold"],
            }
            for channel, c in channels.items()
        },
        "drives_with_alarm": [] if healthy is None else healthy["drives_with_alarm"],
    }


def sensitivity_figures(
    parameter_set: int, calibration_runs: Sequence[mb.MultibodyRun], healthy_runs: Sequence[mb.MultibodyRun]
) -> list[dict[str, Any]]:
    """Calibrate from each drive in turn and run each calibrated observer over the same healthy drives."""
    rows = []
    for run in calibration_runs:
        print(f"  set {parameter_set}: sensitivity, calibrating from {run.name} ...", flush=True)
        try:
            report = calibrate(parameter_set, run)
        except SynthesisError as exc:  # the product's answer to this drive, reported
            rows.append(sensitivity_row(parameter_set, run, f"{type(exc).__name__}: {exc}", None))
            continue
        alarms = report.profile.alarms
        estimated = estimate_runs(observer_factory(report.gains), healthy_runs, alarms)
        healthy = healthy_figures(healthy_runs, estimated, alarms, report.profile.params.sample_period_s)
        rows.append(sensitivity_row(parameter_set, run, report, healthy))
    return rows


# --------------------------------------------------------------------------- one parameter set


@dataclass(frozen=True)
class SetRuns:
    """The drives of one set: the calibration drive, healthy drives, fault runs and the sensitivity check's
    random calibration drives."""

    calibration: mb.MultibodyRun
    healthy: list[mb.MultibodyRun]
    faults: list[mb.MultibodyRun]
    sensitivity: list[mb.MultibodyRun]
    payload: list[mb.MultibodyRun]  # the loaded healthy drives, then the loaded fault run
    hills: list[mb.MultibodyRun]  # the healthy drives on hills, then the fault run on hills


def evaluate_set(
    parameter_set: int, report: CalibrationReport, runs: SetRuns, paper_gains: ObserverGains, plan: Plan
) -> dict[str, Any]:
    """Everything measured on one parameter set, JSON-ready (NaN allowed; cleaned when written)."""
    ekf_channel, ekf_alarms = ekf_thresholds(report, runs.calibration)
    estimators: dict[str, tuple[EstimatorFactory, AlarmThresholds, float]] = {
        "calibrated": (observer_factory(report.gains), report.profile.alarms, report.profile.params.sample_period_s),
        "effectiveness": (
            effectiveness_factory(report.gains, report.profile.effectiveness.model_copy(update={"enabled": True})),
            effectiveness_alarms(report, runs.calibration),
            report.profile.params.sample_period_s,
        ),
        "EKF": (ekf_factory(report.gains), ekf_alarms, report.profile.params.sample_period_s),
        "paper": (observer_factory(paper_gains), AlarmThresholds(), paper_gains.params.sample_period_s),
    }
    healthy: dict[str, Any] = {"driving": driving_figures(runs.healthy)}
    for name, (factory, alarms, period) in estimators.items():
        print(f"  set {parameter_set}: healthy driving, {ESTIMATOR_LABELS[name]} ...", flush=True)
        healthy[name] = healthy_figures(runs.healthy, estimate_runs(factory, runs.healthy, alarms), alarms, period)
    faults: dict[str, Any] = {}
    per_estimator = {
        name: estimate_runs(factory, runs.faults, alarms)
        for name, (factory, alarms, _) in estimators.items()
        if name != "paper"
    }
    n_seeds = len(plan.fault_seeds)
    for i, case in enumerate(FAULT_CASES):
        case_runs = runs.faults[i * n_seeds : (i + 1) * n_seeds]
        entry: dict[str, Any] = {
            "label": case.label,
            "channel": case.channel,
            "kind": case.kind,
            "drive": DRIVE_DESCRIPTIONS[case.drive_kind],
            "magnitude": case.faults(report.nominal_torque_nm, plan.fault_onset_s)[0].model_dump(mode="json"),
            "target": None if case.target is None else vars(case.target),
        }
        for name, estimated in per_estimator.items():
            alarms = estimators[name][1]
            seeds = [
                fault_run_figures(case, run, est, alarms, plan.fault_onset_s)
                for run, est in zip(case_runs, estimated[i * n_seeds : (i + 1) * n_seeds], strict=True)
            ]
            entry[name] = {"seeds": seeds, "meets_target": meets(case, seeds) if case.target else None}
        faults[case.key] = entry
    calibration = calibration_figures(parameter_set, report, runs.calibration)
    calibration["ekf_thresholds"] = {name: vars(t) for name, t in ekf_channel.items()}
    calibration["ekf_alarms"] = ekf_alarms.model_dump(mode="json")
    sensitivity = {
        "primary": sensitivity_row(parameter_set, runs.calibration, report, healthy["calibrated"]),
        "random": sensitivity_figures(parameter_set, runs.sensitivity, runs.healthy),
    }
    print(f"  set {parameter_set}: a payload, calibrated empty ...", flush=True)
    result = {
        "parameter_set": parameter_set,
        "calibration": calibration,
        "healthy": healthy,
        "faults": faults,
        "sensitivity": sensitivity,
        "payload": payload_figures(parameter_set, report, runs.payload, plan),
    }
    print(f"  set {parameter_set}: hills, calibrated on level ground ...", flush=True)
    result["hills"] = hill_figures(parameter_set, report, runs.hills, plan)
    result["must_show"] = must_show(result)
    return result


# --------------------------------------------------------------------------- a payload, calibrated empty
#
# A load is more mass to accelerate, so an observer that does not know it reads every acceleration as a torque
# fault; told the payload (PUT /vehicles/{id}/payload), it takes the torque that moves the profile's vehicle as
# the loaded one moves (synth.model.payload_torque, docs/math.md 12.5). Each set drives the first PAYLOAD_DRIVES
# healthy drives of the plan with PAYLOAD_SHARE of its mass on board, and one torque-bias run; the calibrated
# observer estimates them without the payload and told it.

#: The payload, a share of the vehicle's mass (the MB's m): a tenth, a typical delivery load.
PAYLOAD_SHARE = 0.10
#: How many of the plan's healthy drives run loaded (all of them in quick mode, where there are few).
PAYLOAD_DRIVES = 6
#: The fault run: the first fault case (torque bias +10 %) on the plan's first fault seed.
PAYLOAD_FAULT_CASE = 0


def payload_kg(parameter_set: int) -> float:
    """The payload of ``parameter_set`` [kg]."""
    return PAYLOAD_SHARE * float(mb.vehicle_parameters(parameter_set).m)


def payload_jobs(parameter_set: int, plan: Plan, nominal_torque_nm: float) -> list[mb.MultibodyJob]:
    """The loaded healthy drives, the loaded fault run, then the loaded calibration drive."""
    load = payload_kg(parameter_set)
    healthy = [
        dataclasses.replace(job, payload_kg=load)
        for job in healthy_jobs(parameter_set, plan)[: 1 if plan.quick else PAYLOAD_DRIVES]
    ]
    case = FAULT_CASES[PAYLOAD_FAULT_CASE]
    seed = plan.fault_seeds[0]
    fault = mb.MultibodyJob(
        drive=fault_drive(case, seed, parameter_set, plan),
        parameter_set=parameter_set,
        faults=case.faults(nominal_torque_nm, plan.fault_onset_s),
        seed=seed,
        payload_kg=load,
    )
    return [*healthy, fault, dataclasses.replace(calibration_job(parameter_set), payload_kg=load)]


def payload_figures(
    parameter_set: int, report: CalibrationReport, runs: Sequence[mb.MultibodyRun], plan: Plan
) -> dict[str, Any]:
    """Alarms on the loaded healthy drives without the payload and told it, the told observer's delays on the
    loaded fault run, and the loaded calibration drive calibrated told the payload (the runs of
    :func:`payload_jobs`)."""
    load = payload_kg(parameter_set)
    blind = observer_factory(report.gains)
    told = payload_factory(blind, report.gains.params, load)
    *healthy, fault, calibration = runs
    out = told_and_blind(report, plan, (blind, healthy), (told, healthy), (told, fault))
    return {
        "payload_kg": load,
        "share_of_mass": PAYLOAD_SHARE,
        **out,
        "calibration": compared_calibration(parameter_set, report, calibration, load),
    }


def told_and_blind(
    report: CalibrationReport,
    plan: Plan,
    blind: tuple[EstimatorFactory, Sequence[mb.MultibodyRun]],
    told: tuple[EstimatorFactory, Sequence[mb.MultibodyRun]],
    fault: tuple[EstimatorFactory, mb.MultibodyRun],
) -> dict[str, Any]:
    """A condition the vehicle reports (a payload, the road's grade): alarms on its healthy drives estimated as
    if nothing were reported (``blind``) and as the service estimates them told it (``told``), and the told
    observer's delays on the fault run (the first fault case)."""
    alarms = report.profile.alarms
    period = report.profile.params.sample_period_s
    out: dict[str, Any] = {"driving": driving_figures(list(blind[1]))}
    for name, (factory, runs) in (("blind", blind), ("told", told)):
        out[name] = healthy_figures(list(runs), estimate_runs(factory, runs, alarms), alarms, period)
    case = FAULT_CASES[PAYLOAD_FAULT_CASE]
    (told_fault,) = estimate_runs(fault[0], [fault[1]], alarms)
    seeds = [fault_run_figures(case, fault[1], told_fault, alarms, plan.fault_onset_s)]
    out["fault"] = {"label": case.label, "seeds": seeds, "meets_target": meets(case, seeds)}
    return out


def payload_must_show(result: dict[str, Any]) -> list[dict[str, Any]]:
    """The loaded drives: told the payload, no alarm and the torque bias detected in time; without it, shown."""
    load = result["payload"]
    what = f"{load['payload_kg']:.0f} kg payload ({100 * load['share_of_mass']:g} % of the mass), calibrated empty"
    lines = told_and_blind_must_show(load, what, ("payload reported", "payload not reported"))
    target = (
        "calibration loaded, the payload stated: each identified parameter the MB has a value for within the empty "
        "calibration's 95 % interval"
    )
    return lines + calibration_must_show(load.get("calibration"), target)


def told_and_blind_must_show(entry: dict[str, Any], what: str, labels: tuple[str, str]) -> list[dict[str, Any]]:
    """The must-show lines of a :func:`told_and_blind` entry: told, no alarm and the fault in time; blind,
    shown. ``labels``: (told, blind)."""
    counts = {
        name: ", ".join(
            f"{SYMBOLS[c]} {entry[name]['channels'][c]['warn_raised']} WARN / "
            f"{entry[name]['channels'][c]['fault_raised']} FAULT"
            for c in CHANNELS
        )
        for name in ("blind", "told")
    }
    minutes = f"{entry['driving']['minutes']:.0f} min"
    told_quiet = all(
        entry["told"]["channels"][c]["warn_raised"] == 0 and entry["told"]["channels"][c]["fault_raised"] == 0
        for c in CHANNELS
    )
    fault = entry["fault"]
    case = FAULT_CASES[PAYLOAD_FAULT_CASE]
    return [
        {
            "target": f"{labels[0]}, healthy driving ({what}): no WARN and no FAULT",
            "figure": f"{minutes}: {counts['told']}",
            "passed": told_quiet,
        },
        {
            "target": f"{labels[1]}, healthy driving ({what}): what the report prevents",
            "figure": f"{minutes}: {counts['blind']}",
            "passed": None,
        },
        {
            "target": f"{labels[0]}, {fault['label']} ({what}): {_target_text(case)}",
            "figure": _delays_text(fault["seeds"], case),
            "passed": bool(fault["meets_target"]),
        },
    ]


def _payload_section(result: dict[str, Any]) -> list[str]:
    """The report's table of the loaded drives for one set."""
    load = result["payload"]
    intro = (
        f"The first {load['driving']['drives']} healthy drives again ({load['driving']['minutes']:.0f} min), the "
        f"vehicle carrying {load['payload_kg']:.0f} kg ({100 * load['share_of_mass']:g} % of its mass) spread like "
        "its body (`multibody.loaded_parameters`); the observer calibrated empty, without the payload and told it "
        "(`PUT /vehicles/{id}/payload`; `edge_client.simulation.payload_factory` here). Held peak / WARN as in "
        "the healthy-driving table.\n"
    )
    title = f"### Set {result['parameter_set']}: a payload, calibrated empty\n"
    lines = _told_and_blind_table(load, title, intro, ("payload not reported", "payload reported"))
    how = (
        "Calibrated loaded instead: the scripted calibration drive with the same payload (noise seed {seed}), "
        "the payload stated for the recording (`agv-fe calibrate --payload-kg`); calibration identifies the "
        "vehicle without it (`synth.calibration._fit_with_payloads`).\n"
    )
    return lines + _calibration_table(load.get("calibration"), "loaded", "empty", how)


def _told_and_blind_table(entry: dict[str, Any], title: str, intro: str, labels: tuple[str, str]) -> list[str]:
    """A :func:`told_and_blind` entry as a report section; ``labels``: (blind, told)."""
    lines = [
        title,
        intro,
        "| observer | T_f WARN / FAULT | T_f held peak / WARN | delta_f WARN / FAULT | delta_f held peak / WARN |",
        "|---|---|---|---|---|",
    ]
    for name, label in zip(("blind", "told"), labels, strict=True):
        cells = []
        for c in ("torque", "steer"):
            ch = entry[name]["channels"][c]
            cells += [
                f"{ch['warn_raised']} / {ch['fault_raised']}",
                f"{ch['held_peak_abs_estimate'] / ch['warn_threshold']:.2f}",
            ]
        lines.append(f"| {label} | {' | '.join(cells)} |")
    lines.append("")
    return lines


# --------------------------------------------------------------------------- hills, the grade reported
#
# A grade pulls the whole mass back with M_v g sin(theta), which an observer that does not know it reads as a
# torque fault; told the grade (flag bit 1 of the measurement), the service feeds the model the torque that moves
# the profile's vehicle on level ground as the vehicle moves on the hill (synth.model.payload_torque, docs/math.md
# 12.6). Each set drives the first HILL_DRIVES healthy drives of the plan again on a road that climbs and descends
# (multibody.on_hills), and one torque-bias run there; the vehicle reports the grade with the sensor's noise.

#: How many of the plan's healthy drives run on hills (one in quick mode).
HILL_DRIVES = 6
#: Added to a drive's seed for its road's grades (the road differs from drive to drive).
HILL_SEED_OFFSET = 500


def hill_jobs(parameter_set: int, plan: Plan, nominal_torque_nm: float) -> list[mb.MultibodyJob]:
    """The healthy drives on hills, then the fault run on hills."""
    healthy = [
        dataclasses.replace(job, drive=mb.on_hills(drive, np.random.default_rng(HILL_SEED_OFFSET + job.seed)))
        for job in healthy_jobs(parameter_set, plan)[: 1 if plan.quick else HILL_DRIVES]
        if isinstance(drive := job.drive, mb.Drive)
    ]
    case = FAULT_CASES[PAYLOAD_FAULT_CASE]
    seed = plan.fault_seeds[0]
    drive = fault_drive(case, seed, parameter_set, plan)
    fault = mb.MultibodyJob(
        drive=mb.on_hills(drive, np.random.default_rng(HILL_SEED_OFFSET + seed)),
        parameter_set=parameter_set,
        faults=case.faults(nominal_torque_nm, plan.fault_onset_s),
        seed=seed,
    )
    calibration = calibration_job(parameter_set)
    hilly = mb.on_hills(mb.calibration_drive(), np.random.default_rng(HILL_SEED_OFFSET + calibration.seed))
    return [*healthy, fault, dataclasses.replace(calibration, drive=hilly)]


def told_the_grade(run: mb.MultibodyRun, params: VehicleParams) -> mb.MultibodyRun:
    """``run`` with the demand the service gives the observer when the vehicle reports the grade
    (synth.model.model_inputs): T_d less R_w M_v g sin(theta) of the reported grade, and with a CG height the
    load-transfer angle of the torque sent."""
    if run.grade_rad is None:
        return run
    model_u, _, _ = model_inputs(run.y, run.u, None, run.grade_rad, params)
    return dataclasses.replace(run, u=model_u)


def hill_figures(
    parameter_set: int, report: CalibrationReport, runs: Sequence[mb.MultibodyRun], plan: Plan
) -> dict[str, Any]:
    """Alarms on the healthy drives on hills without the grade and told it, the told observer's delays on the
    fault run on hills, and the calibration drive on hills calibrated with the grade (the runs of
    :func:`hill_jobs`)."""
    *healthy, fault, calibration = runs
    observer = observer_factory(report.gains)
    told = [told_the_grade(run, report.gains.params) for run in [*healthy, fault]]
    grades = np.concatenate([run.grade_rad for run in healthy if run.grade_rad is not None])
    out = told_and_blind(report, plan, (observer, healthy), (observer, told[:-1]), (observer, told[-1]))
    return {
        "road_max_grade_rad": mb.HILL_GRADE_RAD,
        "max_reported_grade_rad": float(np.abs(grades).max()),
        "grade_sigma_rad": mb.DEFAULT_GRADE_SIGMA_RAD,
        **out,
        "calibration": compared_calibration(parameter_set, report, calibration),
    }


def compared_calibration(
    parameter_set: int, level: CalibrationReport, run: mb.MultibodyRun, payload_kg: float = 0.0
) -> dict[str, Any]:
    """The scripted calibration drive driven otherwise (on hills with the grade reported, or loaded with the
    payload stated), calibrated as the product does: each parameter of REFERENCES (``value``) against the
    calibration of the level, empty drive ``level`` (its value and 95 % interval) and the MB's value; or why it
    was refused."""
    try:
        other = calibrate(parameter_set, run, payload_kg)
    except SynthesisError as exc:
        return {"refused": f"{type(exc).__name__}: {exc}"}
    reference = mb.reference_values(parameter_set)
    parameters = [
        {
            "name": name,
            "value": other.calibration.estimates[name].value,
            "level": level.calibration.estimates[name].value,
            "level_ci95": [level.calibration.estimates[name].low, level.calibration.estimates[name].high],
            "reference": reference[REFERENCES[name][0]],
        }
        for name in REFERENCES
        if name in other.calibration.estimates and name in level.calibration.estimates
    ]
    return {"refused": None, "drive": run.name, "noise_seed": run.seed, "parameters": parameters}


def calibration_must_show(calibration: dict[str, Any] | None, target: str) -> list[dict[str, Any]]:
    """The must-show line of a :func:`compared_calibration` (none without one): every parameter within the level,
    empty calibration's 95 % interval."""
    if calibration is None:
        return []
    if calibration["refused"] is not None:
        return [{"target": target, "figure": calibration["refused"], "passed": False}]
    rows = calibration["parameters"]
    figure = ", ".join(
        f"{row['name']} {100 * (row['value'] / row['level'] - 1):+.2f} % (interval "
        f"{100 * (low / row['level'] - 1):+.1f} to {100 * (high / row['level'] - 1):+.1f} %)"
        for row in rows
        for low, high in [row["level_ci95"]]
    )
    passed = bool(rows) and all(row["level_ci95"][0] <= row["value"] <= row["level_ci95"][1] for row in rows)
    return [{"target": target, "figure": figure, "passed": passed}]


def _calibration_table(calibration: dict[str, Any] | None, label: str, level_label: str, how: str) -> list[str]:
    """The report's table of a :func:`compared_calibration`: ``how`` (with {seed}) introduces it; ``label`` names
    its drive, ``level_label`` the calibration it is held against."""
    if calibration is None:
        return []
    if calibration["refused"] is not None:
        return [f"Calibration {label} was refused: {calibration['refused']}\n"]
    return [
        how.format(seed=calibration["noise_seed"]),
        f"| parameter | {label} | {level_label} (95 % interval) | {label} / {level_label} - 1 | the MB's value | "
        f"{label} against it |",
        "|---|---|---|---|---|---|",
        *(
            f"| {row['name']} | {row['value']:.6g} | {row['level']:.6g} ({low:.6g} to {high:.6g}) | "
            f"{100 * (row['value'] / row['level'] - 1):+.2f} % | {row['reference']:.6g} | "
            f"{100 * (row['value'] / row['reference'] - 1):+.2f} % |"
            for row in calibration["parameters"]
            for low, high in [row["level_ci95"]]
        ),
        "",
    ]


def hill_must_show(result: dict[str, Any]) -> list[dict[str, Any]]:
    """On hills: told the grade, no alarm and the torque bias detected in time; without it, shown."""
    hills = result["hills"]
    what = f"grades within +-{100 * math.tan(hills['road_max_grade_rad']):.0f} %, calibrated on level ground"
    lines = told_and_blind_must_show(hills, what, ("grade reported", "grade not reported"))
    target = (
        "calibration on hills, the grade reported: each identified parameter the MB has a value for within the "
        "level-ground calibration's 95 % interval"
    )
    return lines + calibration_must_show(hills.get("calibration"), target)


def _hill_section(result: dict[str, Any]) -> list[str]:
    """The report's table of the drives on hills for one set."""
    hills = result["hills"]
    intro = (
        f"The first {hills['driving']['drives']} healthy drives again ({hills['driving']['minutes']:.0f} min) on "
        f"a road that climbs and descends (`multibody.on_hills`: grades uniform within +-"
        f"{100 * math.tan(hills['road_max_grade_rad']):.0f} %, each held 8 to 25 s and reached over 5 s); the vehicle "
        f"reports the grade with {hills['grade_sigma_rad']:g} rad of noise, and its speed controller compensates "
        "the grade. The observer calibrated on level ground, without the grade and told it (flag bit 1 of the "
        "measurement; `told_the_grade` here). Held peak / WARN as in the healthy-driving table.\n"
    )
    title = f"### Set {result['parameter_set']}: hills\n"
    lines = _told_and_blind_table(hills, title, intro, ("grade not reported", "grade reported"))
    how = (
        "Calibrated on hills instead: the scripted calibration drive on the same kind of road (noise seed {seed}), "
        "the grade reported as above; calibration takes it into its fits (`synth.calibration.level_ground`, the "
        "load transfer on dv_x/dt + g sin(theta)).\n"
    )
    return lines + _calibration_table(hills.get("calibration"), "on hills", "on level ground", how)


def refused_set(parameter_set: int, reason: str) -> dict[str, Any]:
    """The result of a set whose calibration raised: the reason, and the calibration target failed."""
    return {
        "parameter_set": parameter_set,
        "calibration_error": reason,
        "must_show": [
            {
                "target": "calibration from healthy driving gives a profile",
                "figure": reason,
                "passed": False,
            }
        ],
    }


def must_show(result: dict[str, Any]) -> list[dict[str, Any]]:
    """One line per target for one parameter set: what, the measured figure, pass."""
    lines: list[dict[str, Any]] = []
    rows = {row["name"]: row for row in result["calibration"]["parameters"]}
    for row in (rows[name] for name in REFERENCES if name in rows):
        if row.get("tolerance") is None:
            continue
        lines.append(
            {
                "target": f"{row['name']} within {100 * row['tolerance']:g} % of the MB's value",
                "figure": f"{row['value']:.6g} against {row['reference']:.6g}: {100 * row['error']:+.2f} %",
                "passed": bool(row["passed"]),
            }
        )
    driving = result["healthy"]["driving"]
    cal = result["healthy"]["calibrated"]["channels"]
    counts = ", ".join(f"{SYMBOLS[c]} {cal[c]['warn_raised']} WARN / {cal[c]['fault_raised']} FAULT" for c in CHANNELS)
    lines.append(
        {
            "target": "healthy driving: no WARN and no FAULT on either channel (calibrated observer)",
            "figure": f"{driving['minutes']:.0f} min, peak lateral acceleration "
            f"{driving['peak_lateral_accel_mps2']:.1f} m/s^2: {counts}",
            "passed": all(cal[c]["warn_raised"] == 0 and cal[c]["fault_raised"] == 0 for c in CHANNELS),
        }
    )
    violations = []
    for case in FAULT_CASES:
        entry = result["faults"][case.key]
        seeds = entry["calibrated"]["seeds"]
        if case.target is not None:
            lines.append(
                {
                    "target": f"{case.label}: {_target_text(case)}",
                    "figure": _delays_text(seeds, case),
                    "passed": bool(entry["calibrated"]["meets_target"]),
                }
            )
        violations += [
            f"{case.label} seed {s['seed']}: {SYMBOLS[case.other_channel]} {s['other_channel_level']}"
            for s in seeds
            if s["other_channel_level"] != "OK"
        ]
    lines += effectiveness_must_show(result)
    lines += payload_must_show(result)
    lines += hill_must_show(result)
    lines.append(
        {
            "target": "the other channel stays OK after the warm-up in every fault case and seed (calibrated observer)",
            "figure": "; ".join(violations) if violations else "OK in all",
            "passed": not violations,
        }
    )
    lines.append(sensitivity_line(result["sensitivity"]["random"], driving["minutes"]))
    return lines


def effectiveness_must_show(result: dict[str, Any]) -> list[dict[str, Any]]:
    """The loss-of-effectiveness targets, measured with the effectiveness stage: on the torque loss ramp its
    total-fault RMSE at most a third of the additive design's and WARN within 2 s of the onset in every seed;
    alpha_hat within 3 % of the truth 2 s after the ramp ends (torque; the steering loss is shown beside)."""
    lines: list[dict[str, Any]] = []
    for key in ("torque_loss", "steer_loss"):
        entry = result["faults"].get(key)
        if entry is None or "effectiveness" not in entry:
            continue
        stage, additive = entry["effectiveness"]["seeds"], entry["calibrated"]["seeds"]
        ratios = [s["rmse_after_onset"] / a["rmse_after_onset"] for s, a in zip(stage, additive, strict=True)]
        alphas = [s["alpha_after_ramp"] for s in stage]
        warn = [s["warn_delay_s"] for s in stage]
        label = "torque" if key == "torque_loss" else "steering (shown)"
        rmse_ok = all(r <= LOSS_RMSE_SHARE for r in ratios)
        warn_ok = all(w is not None and w <= EFFECTIVENESS_WARN_WITHIN_S for w in warn)
        alpha_ok = all(abs(a - LOSS_ALPHA_MIN) <= ALPHA_TOLERANCE * LOSS_ALPHA_MIN for a in alphas)
        lines.append(
            {
                "target": f"{label} loss of effectiveness, effectiveness stage: total-fault RMSE at most a third of "
                f"the additive design's, WARN within {EFFECTIVENESS_WARN_WITHIN_S:g} s of the onset",
                "figure": f"RMSE ratio {' / '.join(f'{r:.2f}' for r in ratios)}; WARN after "
                f"{' / '.join(_delay(w) for w in warn)} s",
                "passed": rmse_ok and warn_ok if key == "torque_loss" else None,
            }
        )
        lines.append(
            {
                "target": f"{label} loss of effectiveness: alpha_hat within {100 * ALPHA_TOLERANCE:g} % of the truth "
                f"({LOSS_ALPHA_MIN:g}) {ALPHA_AFTER_RAMP_S:g} s after the ramp ends",
                "figure": " / ".join(f"{a:.3f}" for a in alphas),
                "passed": alpha_ok if key == "torque_loss" else None,
            }
        )
    return lines


def sensitivity_line(rows: Sequence[dict[str, Any]], minutes: float) -> dict[str, Any]:
    """Must-show: no WARN and no FAULT on the healthy driving with any random-drive calibration; a refused
    calibration counts as not shown."""
    figures = []
    for row in rows:
        if row["refused"] is not None:
            figures.append(f"{row['drive']}: calibration refused, not shown")
            continue
        counts = ", ".join(
            f"{SYMBOLS[c]} {row['healthy'][c]['warn_raised']} WARN / {row['healthy'][c]['fault_raised']} FAULT"
            for c in CHANNELS
        )
        figures.append(f"{row['drive']}: {counts}")
    passed = bool(rows) and all(
        row["refused"] is None
        and all(row["healthy"][c]["warn_raised"] == 0 and row["healthy"][c]["fault_raised"] == 0 for c in CHANNELS)
        for row in rows
    )
    return {
        "target": "sensitivity: no alarm on healthy driving with any of the random-drive calibrations",
        "figure": f"{minutes:.0f} min each; " + "; ".join(figures),
        "passed": passed,
    }


def _target_text(case: FaultCase) -> str:
    target = case.target
    if target is None:
        return ""
    text = f"WARN within {target.warn_s:g} s"
    if target.fault_s is not None:
        text += f" and FAULT within {target.fault_s:g} s"
    text += " in every seed"
    if target.other_channel_ok:
        text += f", {SYMBOLS[case.other_channel]} OK"
    return text


def _delay(value: float | None) -> str:
    return "never" if value is None else f"{value:.2f}"


def _delays_text(seeds: Sequence[dict[str, Any]], case: FaultCase) -> str:
    warn = " / ".join(_delay(s["warn_delay_s"]) for s in seeds)
    fault = " / ".join(_delay(s["fault_delay_s"]) for s in seeds)
    text = f"WARN {warn} s; FAULT {fault} s"
    early = [str(s["seed"]) for s in seeds if s["level_before_onset"] != "OK"]
    if early:
        text += f"; alarm before the onset in seed(s) {', '.join(early)}"
    if case.target is not None and case.target.other_channel_ok:
        text += f"; {SYMBOLS[case.other_channel]} " + " / ".join(s["other_channel_level"] for s in seeds)
    return text


# --------------------------------------------------------------------------- the run


def run(
    out_dir: Path,
    parameter_sets: tuple[int, ...] = DEFAULT_PARAMETER_SETS,
    quick: bool = False,
    workers: int = WORKERS,
    healthy_seeds: Sequence[int] | None = None,
    healthy_duration_s: float | None = None,
    fault_seeds: Sequence[int] | None = None,
    sensitivity_seeds: Sequence[int] | None = None,
) -> Path:
    """Run the benchmark on ``parameter_sets``; write real_vehicle.md and real_vehicle.json to ``out_dir``.

    ``quick``: fewer and shorter healthy drives, one seed per fault case and one random calibration drive
    (for tests). ``healthy_seeds``, ``healthy_duration_s`` [s], ``fault_seeds`` and ``sensitivity_seeds``
    replace the plan's. A set whose calibration from the scripted drive is refused (or whose design fails)
    is reported with the reason, as a failed target, and not evaluated further.
    """
    plan = Plan.make(parameter_sets, quick, workers, healthy_seeds, healthy_duration_s, fault_seeds, sensitivity_seeds)
    document = measure(plan)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "real_vehicle.json").write_text(json.dumps(_clean(document), indent=1) + "\n")
    path = out_dir / "real_vehicle.md"
    path.write_text(render(document))
    return path


def measure(plan: Plan) -> dict[str, Any]:
    """Calibrate every set from its scripted drive, simulate its healthy and faulty drives and evaluate it: the
    run's document (what real_vehicle.json holds and :func:`render` reads)."""
    started = time.perf_counter()
    print(f"  simulating the calibration drives of set(s) {', '.join(map(str, plan.parameter_sets))} ...", flush=True)
    n_random = len(plan.sensitivity_seeds)
    calibration_jobs = [job for s in plan.parameter_sets for job in [calibration_job(s), *sensitivity_jobs(s, plan)]]
    calibration_runs = mb.simulate_many(calibration_jobs, plan.workers)
    scripted = calibration_runs[:: n_random + 1]
    random_runs = {
        s: calibration_runs[i * (n_random + 1) + 1 : (i + 1) * (n_random + 1)]
        for i, s in enumerate(plan.parameter_sets)
    }
    reports: dict[int, CalibrationReport] = {}
    refused: dict[int, str] = {}
    for s, cal_run in zip(plan.parameter_sets, scripted, strict=True):
        print(f"  set {s}: calibrating from {cal_run.name} ...", flush=True)
        try:
            reports[s] = calibrate(s, cal_run)
        except SynthesisError as exc:  # CalibrationRefused, Infeasible, ...: the product's answer, reported
            refused[s] = f"{type(exc).__name__}: {exc}"
    jobs: list[mb.MultibodyJob] = []
    spans: dict[int, tuple[int, int, int, int, int]] = {}
    for s in reports:
        start = len(jobs)
        jobs += healthy_jobs(s, plan)
        middle = len(jobs)
        jobs += fault_jobs(s, reports[s].nominal_torque_nm, plan)
        loaded = len(jobs)
        jobs += payload_jobs(s, plan, reports[s].nominal_torque_nm)
        hilly = len(jobs)
        jobs += hill_jobs(s, plan, reports[s].nominal_torque_nm)
        spans[s] = (start, middle, loaded, hilly, len(jobs))
    simulated_s = sum(job.drive.n_samples for job in jobs) * mb.SAMPLE_PERIOD_S
    print(f"  simulating {len(jobs)} drives ({simulated_s / 60:.0f} min) in {plan.workers} processes ...", flush=True)
    simulated = mb.simulate_many(jobs, plan.workers)
    paper_gains = synthesize(VehicleParams(), OperatingBounds(), DesignOptions())
    results = []
    for s, cal_run in zip(plan.parameter_sets, scripted, strict=True):
        if s in refused:
            results.append(refused_set(s, refused[s]))
            continue
        start, middle, loaded, hilly, end = spans[s]
        runs = SetRuns(
            calibration=cal_run,
            healthy=simulated[start:middle],
            faults=simulated[middle:loaded],
            sensitivity=random_runs[s],
            payload=simulated[loaded:hilly],
            hills=simulated[hilly:end],
        )
        results.append(evaluate_set(s, reports[s], runs, paper_gains, plan))
    return {
        "benchmark": "real_vehicle",
        "plan": _plan_document(plan, len(scripted[0]) * mb.SAMPLE_PERIOD_S),
        "paper_profile": {
            "gain_version": paper_gains.version,
            "alarms": AlarmThresholds().model_dump(mode="json"),
        },
        "sets": results,
        "uncommitted_files": uncommitted_files(),
        "runtime_s": time.perf_counter() - started,
    }


def _plan_document(plan: Plan, calibration_duration_s: float) -> dict[str, Any]:
    """The document's "plan": the sets, the drives' seeds and durations, the noise."""
    return {
        "parameter_sets": list(plan.parameter_sets),
        "quick": plan.quick,
        "calibration": {
            "drive": "calibration_drive",
            "noise_seeds": [CALIBRATION_SEED_OFFSET + s for s in plan.parameter_sets],
            "duration_s": calibration_duration_s,
        },
        "sensitivity": {"seeds": list(plan.sensitivity_seeds), "duration_s": plan.sensitivity_duration_s},
        "healthy": {"seeds": list(plan.healthy_seeds), "duration_s": plan.healthy_duration_s},
        "faults": {
            "seeds": list(plan.fault_seeds),
            "duration_s": plan.fault_duration_s,
            "onset_s": plan.fault_onset_s,
        },
        "noise": {"vx_sigma_mps": mb.DEFAULT_SPEED_SIGMA_MPS, "r_sigma_radps": mb.DEFAULT_YAW_RATE_SIGMA_RADPS},
        "max_lateral_accel_mps2": MAX_LATERAL_ACCEL_MPS2,
        "workers": plan.workers,
    }


def uncommitted_files() -> list[str]:
    """Tracked files with uncommitted changes when the benchmark ran: the figures come from them too."""
    try:
        status = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True, text=True, check=False
        ).stdout
    except OSError:
        return []
    return [line[3:] for line in status.splitlines() if len(line) > 3]


def _clean(value: Any) -> Any:
    """JSON-safe: NaN and infinities become null, numpy scalars plain numbers, tuples lists."""
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_clean(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


# --------------------------------------------------------------------------- the report


def render(document: dict[str, Any]) -> str:
    """The markdown report: must-show lines first, then the tables, then how it was measured."""
    plan = document["plan"]
    sets = document["sets"]
    lines = [
        report_header("Real vehicle: calibration, false alarms and detection on a multi-body plant", "real_vehicle"),
        f"Parameter set(s) {', '.join(str(s) for s in plan['parameter_sets'])} of CommonRoad's multi-body vehicle "
        f"model{' (quick mode: fewer and shorter drives)' if plan['quick'] else ''}; this run took "
        f"{document['runtime_s'] / 60:.1f} min with {plan['workers']} simulation processes."
        + _uncommitted_note(document.get("uncommitted_files", []))
        + "\n",
        "## Must show\n",
        "| set | target | measured | result |",
        "|---|---|---|---|",
    ]
    for result in sets:
        for line in result["must_show"]:
            verdict = "shown" if line["passed"] is None else "pass" if line["passed"] else "**FAIL**"
            lines.append(f"| {result['parameter_set']} | {line['target']} | {line['figure']} | {verdict} |")
    lines.append("")
    lines.append(_stiffness_note(sets))
    for result in sets:
        if "calibration_error" in result:
            lines += [
                f"## Parameter set {result['parameter_set']}\n",
                f"Calibration failed, so nothing else was evaluated on this set: {result['calibration_error']}\n",
            ]
            continue
        lines += _calibration_section(result)
        lines += _healthy_section(result)
        lines += _sensitivity_section(result)
        lines += _fault_section(result, plan)
        lines += _payload_section(result)
        lines += _hill_section(result)
    lines += _how_measured(plan)
    return "\n".join(lines) + "\n"


def _stiffness_note(sets: Sequence[dict[str, Any]]) -> str:
    """What the cornering stiffness is compared with, and how far it lands from the scripted and the random
    calibration drives (the ranges over the sets)."""
    names = SENSITIVITY_PARAMETERS[1:]
    scripted = [r["sensitivity"]["primary"]["errors"][n] for r in sets if "sensitivity" in r for n in names]
    random = [
        row["errors"][n]
        for r in sets
        if "sensitivity" in r
        for row in r["sensitivity"]["random"]
        if row["refused"] is None
        for n in names
    ]
    text = (
        "The cornering stiffness is compared with the tyre model's linear slope at the static load. Calibration "
        "identifies the 2-DOF model's effective axle stiffness: the one with which the model reproduces the "
        "measured yaw rate (its fit residual below is at the sensor noise). The multi-body chassis passes the "
        "tyre forces to the body through compliant suspension joints and adds roll-dependent camber forces, "
        "which the 2-DOF model lumps into its stiffnesses."
    )
    if scripted:
        text += f" From the scripted calibration drive the stiffnesses came out {_error_range(scripted)} of the slope"
        text += f", from the random calibration drives {_error_range(random)}" if random else ""
        text += (
            "; each is one drive with one sensor-noise realisation, and the stiffnesses' 95 % intervals are "
            f"{_half_width_range(sets)} wide (the sections 'Sensitivity to the calibration drive' below, per set)."
        )
    return (
        text + " docs/math.md, section 12.3, says what was measured on that (the demanded angle against the true "
        "road-wheel angle, with and without the steering lag).\n"
    )


def _half_width_range(sets: Sequence[dict[str, Any]]) -> str:
    """The stiffnesses' 95 % interval half-widths over every calibration that gave a profile [%]."""
    half = [
        50 * (high - low)
        for r in sets
        if "sensitivity" in r
        for row in (r["sensitivity"]["primary"], *r["sensitivity"]["random"])
        if row["refused"] is None
        for name in SENSITIVITY_PARAMETERS[1:]
        for low, high in [row["error_ci95"][name]]
    ]
    return f"+-{min(half):.1f} % to +-{max(half):.1f} %"


def _error_range(errors: Sequence[float]) -> str:
    low, high = min(errors), max(errors)
    return f"{100 * low:+.1f} %" if low == high else f"{100 * low:+.1f} % to {100 * high:+.1f} %"


def _uncommitted_note(files: Sequence[str]) -> str:
    if not files:
        return ""
    return f" The working tree had uncommitted changes to {len(files)} tracked file(s): {', '.join(files)}."


def _fmt(value: float | None, digits: int = 4) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{value:.{digits}g}"


def _calibration_section(result: dict[str, Any]) -> list[str]:
    s = result["parameter_set"]
    cal = result["calibration"]
    summary = cal["summary"]
    noise = summary["sensor_noise"]
    residuals = summary["residuals"]
    design = cal["design"]
    given = ", ".join(f"{k} {v:.6g}" for k, v in cal["given"].items())
    lines = [
        f"## Parameter set {s}\n",
        "### Calibration\n",
        f"The scripted calibration drive `{cal['drive']['name']}_drive()` (edge_client/multibody.py, the "
        f"recommended calibration procedure), {summary['duration_s']:.0f} s, sensor noise seed "
        f"{cal['drive']['noise_seed']}: speed changes between 10 and 20 m/s, steady turns both ways entered as "
        "briskly as the planner allows (step steers), lane changes and slaloms at 10 to 20 m/s; peak |v_x r| "
        f"{summary['peak_lateral_accel_mps2']:.1f} m/s^2. It is the drive every figure below is measured with "
        "because it excites the lateral dynamics the cornering stiffnesses are identified from; what random "
        "drives give instead is in 'Sensitivity to the calibration drive'. Through `calibrate_profile` with the "
        f"data sheet of `base_profile({s})`: {given}.\n",
        "| parameter | identified | 95 % interval | MB value | MB value in the interval | error | target |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in cal["parameters"]:
        low, high = row["ci95"]
        inside = "-"
        if "reference" in row:
            ref, err = _fmt(row["reference"], 6), f"{100 * row['error']:+.2f} %"
            inside = "yes" if low <= row["reference"] <= high else "no"
            tol = row["tolerance"]
            target = "-" if tol is None else f"within {100 * tol:g} %: {'pass' if row['passed'] else '**FAIL**'}"
        elif "plant_value" in row:
            ref, err, target = f"{_fmt(row['plant_value'], 4)} ({row['plant_note']})", "-", "-"
            inside = "yes" if low <= row["plant_value"] <= high else "no"
        else:
            ref, err, target = "-", "-", "-"
        lines.append(
            f"| {row['name']} | {_fmt(row['value'], 6)} | {_fmt(low, 5)} to {_fmt(high, 5)} | {ref} | {inside} "
            f"| {err} | {target} |"
        )
    lines += [
        "",
        f"Sensor noise found: v_x {noise['vx_sigma_mps']:.4f} m/s, r {noise['r_sigma_radps']:.5f} rad/s "
        "(simulated: 0.05 m/s, 0.005 rad/s). Fit residuals over what the sensor noise explains: yaw rate "
        f"{residuals['yaw_rate_rms_over_noise']:.3f}, speed change {residuals['speed_change_rms_over_noise']:.3f} "
        f"({residuals['longitudinal_windows']:.0f} longitudinal windows). Fitted steering offset "
        f"{summary['steer_offset_rad']:+.5f} rad. Design: '{design['design']}'"
        f"{', switched gain sets' if design['switched'] else ''}, decay rate chosen {design['robust_decay_rate']:g}, "
        f"certified decay rate {design['certified_decay_rate']:.5f}, gains version {design['gain_version']}. "
        f"Nominal drive torque {summary['nominal_torque_nm']:.1f} N m; false-alarm rate "
        f"{summary['false_alarms_per_1000_h']:g} per 1,000 h.\n",
        "| thresholds | channel | healthy sigma | held peak | held in the gust | certified RMS | WARN | FAULT "
        "| WARN set by | smallest bias to WARN / FAULT | required bias |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for who, table in (("calibrated observer", summary["thresholds"]), ("EKF", cal["ekf_thresholds"])):
        for channel in CHANNELS:
            t = table[channel]
            unit = UNITS[channel]
            lines.append(
                f"| {who} | {SYMBOLS[channel]} [{unit}] | {_fmt(t['sigma'])} | {_fmt(t['healthy_peak'])} "
                f"| {_fmt(t['gust_peak'])} | {_fmt(t['certified_rms'])} | {_fmt(t['warn'])} | {_fmt(t['fault'])} "
                f"| {t['set_by']} "
                f"| {_fmt(t['smallest_warn_bias'])} / {_fmt(t['smallest_fault_bias'])} | {_fmt(t['required_bias'])} |"
            )
    warnings = summary["warnings"]
    lines += [
        "",
        "Calibration warnings: " + ("; ".join(warnings) if warnings else "none") + ".",
        "Notes: " + ("; ".join(summary["notes"]) if summary["notes"] else "none") + ".\n",
    ]
    return lines


def _healthy_section(result: dict[str, Any]) -> list[str]:
    healthy = result["healthy"]
    driving = healthy["driving"]
    lines = [
        "### Healthy driving\n",
        f"{driving['drives']} random drives, {driving['minutes']:.1f} min, speeds "
        f"{driving['speed_range_mps'][0]:.1f} to {driving['speed_range_mps'][1]:.1f} m/s, peak |a_y| "
        f"{driving['peak_lateral_accel_mps2']:.2f} m/s^2 ({driving['seconds_above_5_mps2']:.0f} s above 5 m/s^2). "
        f"Every {_ordinal(URBAN_EVERY)} drive is in town ({URBAN_SPEED_MPS[0]:g} to {URBAN_SPEED_MPS[1]:g} m/s, "
        f"yaw rates to {URBAN_YAW_RATE_RADPS:g} rad/s: corners tighter than the calibration drive's), each "
        f"drive after those brakes and accelerates in turns (|a_y| {COMBINED_LATERAL_ACCEL_MPS2[0]:g} to "
        f"{COMBINED_LATERAL_ACCEL_MPS2[1]:g} m/s^2 with |a_x| to {COMBINED_ACCEL_MPS2:g} m/s^2, 10 to 22 m/s: the "
        "load transfer, docs/math.md 12.4; every other one of those hard, |a_y| "
        f"{HARD_COMBINED_LATERAL_ACCEL_MPS2[0]:g} to {HARD_COMBINED_LATERAL_ACCEL_MPS2[1]:g} m/s^2 with |a_x| to "
        f"{HARD_COMBINED_ACCEL_MPS2:g} m/s^2: "
        "beyond the grip limits), the others on open roads (8 to 22 m/s, 0.5 rad/s). "
        "Raised: times a level went from OK to WARN or higher / reached FAULT, after the warm-up. Judged by the "
        "levels: the share of samples after the warm-up, which runs again after each sample outside the certified "
        "domain (docs/math.md section 8), and not within the profile's grip_hold_s of a combined acceleration "
        "beyond its grip limits (docs/math.md 12.4; held by the grip gate: that share); peaks and RMS are taken "
        "over those. Held peak: the "
        "largest |estimate| held for the alarm's persistence time; a level can only be raised where it reaches the "
        "threshold (held peak / WARN >= 1). The EKF's thresholds come from its own "
        "estimates on the calibration drive; the `paper` profile's are the defaults.\n",
        "| estimator | channel | WARN / FAULT threshold | WARN raised | FAULT raised "
        "| peak / held peak of the magnitude | held peak / WARN | held peak at: drive seed, t, peak a_y in it "
        "| RMS estimate | drives with an alarm | premise in domain | judged by the levels | held by the grip gate |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name in ("calibrated", "EKF", "paper"):
        figures = healthy[name]
        for channel in CHANNELS:
            c = figures["channels"][channel]
            unit = UNITS[channel]
            lines.append(
                f"| {ESTIMATOR_LABELS[name]} | {SYMBOLS[channel]} [{unit}] | {_fmt(c['warn_threshold'])} / "
                f"{_fmt(c['fault_threshold'])} | {c['warn_raised']} | {c['fault_raised']} "
                f"| {_fmt(c['peak_abs_estimate'])} / {_fmt(c['held_peak_abs_estimate'])} "
                f"| {c['held_peak_abs_estimate'] / c['warn_threshold']:.2f} | {_held_at(c['held_peak_at'])} "
                f"| {_fmt(c['rms_estimate'])} "
                f"| {len(figures['drives_with_alarm'])} of {driving['drives']} "
                f"| {100 * figures['in_domain_share']:.1f} % "
                f"| {100 * figures.get('assessed_share', math.nan):.1f} % "
                f"| {100 * figures.get('grip_held_share', math.nan):.1f} % |"
            )
    lines.append("")
    for name in ("calibrated", "EKF"):
        events = healthy[name]["events"]
        if not events:
            continue
        lines += [
            f"Alarms raised on healthy driving by the {ESTIMATOR_LABELS[name]} "
            f"({healthy[name].get('events_total', len(events))} in all"
            f"{f', the first {LISTED_ALARMS}' if len(events) > LISTED_ALARMS else ''}):\n",
            "| drive seed | channel | t [s] | level | estimate | a_y [m/s^2] | v_x [m/s] |",
            "|---|---|---|---|---|---|---|",
        ]
        lines += [
            f"| {e['seed']} | {SYMBOLS[e['channel']]} | {e['t_s']:.2f} | {e['level']} | {_fmt(e['estimate'])} "
            f"| {e['lateral_accel_mps2']:+.2f} | {e['speed_mps']:.1f} |"
            for e in events[:LISTED_ALARMS]
        ]
        lines.append("")
    non_finite = {name: healthy[name]["non_finite_samples"] for name in ("calibrated", "EKF", "paper")}
    if any(non_finite.values()):
        lines.append(f"Non-finite estimates (not fed to the alarm levels): {non_finite}.\n")
    return lines


def _ordinal(n: int) -> str:
    return {1: "", 2: "second", 3: "third", 4: "fourth"}.get(n, f"{n}th")


def _sensitivity_section(result: dict[str, Any]) -> list[str]:
    sensitivity = result["sensitivity"]
    minutes = result["healthy"]["driving"]["minutes"]
    seeds = ", ".join(str(row["seed"]) for row in sensitivity["random"])
    lines = [
        "### Sensitivity to the calibration drive\n",
        f"Calibrations from random drives instead of the scripted one: random_drive(seed {seeds}, "
        f"{sensitivity['random'][0]['duration_s']:.0f} s), the seed also that of the sensor noise, each through "
        "`calibrate_profile` as above; each calibrated observer then ran over the same "
        f"{minutes:.0f} min of healthy driving with its own thresholds. First row: the scripted calibration above. "
        "Errors against the MB's values (the stiffnesses against the tyres' slope), with the calibration's 95 % "
        "interval on the same scale; held peak / WARN as in the healthy-driving table (an alarm needs >= 1). "
        "A drive differs from the others in its content and in its sensor-noise realisation. A refused "
        "calibration gives no profile and counts as not shown in the must-show line.\n",
        "| calibration drive | peak a_y [m/s^2], s above 5 m/s^2 | m_eff error (95 % interval) "
        "| C_f error (95 % interval) | C_r error (95 % interval) "
        "| decay rate chosen | T_f WARN [N m] | delta_f WARN [rad] | T_f WARN / FAULT raised "
        "| delta_f WARN / FAULT raised | held peak / WARN: T_f, delta_f | refused |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    primary = sensitivity["primary"]
    labelled = [(f"{primary['drive']} (scripted, seed {primary['seed']})", primary)]
    labelled += [(row["drive"], row) for row in sensitivity["random"]]
    for label, row in labelled:
        driving = f"{row['peak_lateral_accel_mps2']:.1f}, {row['seconds_above_5_mps2']:.0f} s"
        if row["refused"] is not None:
            reason = str(row["refused"]).replace("|", "/")
            lines.append(f"| {label} | {driving} | - | - | - | - | - | - | - | - | - | {reason} |")
            continue
        errors = " | ".join(
            f"{100 * row['errors'][name]:+.2f} % ({100 * low:+.1f} to {100 * high:+.1f})"
            for name in SENSITIVITY_PARAMETERS
            for low, high in [row["error_ci95"][name]]
        )
        raised = " | ".join(
            f"{row['healthy'][c]['warn_raised']} / {row['healthy'][c]['fault_raised']}" for c in CHANNELS
        )
        margins = ", ".join(f"{row['healthy'][c]['held_peak_over_warn']:.2f}" for c in CHANNELS)
        alarms = row["alarms"]
        lines.append(
            f"| {label} | {driving} | {errors} | {row['robust_decay_rate']:g} | {_fmt(alarms['torque_warn_nm'])} "
            f"| {_fmt(alarms['steer_warn_rad'])} | {raised} | {margins} | - |"
        )
    lines.append("")
    return lines


def _held_at(where: dict[str, float] | None) -> str:
    if where is None:
        return "-"
    return f"{where['seed']:.0f}, {where['t_s']:.2f} s, {where['peak_lateral_accel_mps2']:.1f} m/s^2"


def _fault_section(result: dict[str, Any], plan: dict[str, Any]) -> list[str]:
    faults = plan["faults"]
    lines = [
        "### Faults\n",
        f"Onset at {faults['onset_s']:g} s of {faults['duration_s']:g} s drives, seeds "
        f"{', '.join(map(str, faults['seeds']))} (drive and sensor noise). Delays from the onset to the first "
        "sample at WARN or higher and at FAULT on the faulty channel, per seed; 'never' = not within the "
        "drive. Before onset: the faulty channel's highest level between the warm-up and the onset. Other "
        "channel: its highest level after the warm-up. RMSE: faulty channel's estimate against the true fault "
        "(applied minus demanded) after the onset. Demand: RMS of the faulty channel's demand after the onset "
        "(the driver's, closed loop).\n",
        "| fault | drive, demand RMS after onset | estimator | WARN delay [s] | FAULT delay [s] | before onset "
        "| other channel | RMSE after onset | target |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    failed: list[tuple[str, dict[str, Any]]] = []
    for case in FAULT_CASES:
        entry = result["faults"][case.key]
        unit = UNITS[case.channel]
        for name in ("calibrated", "effectiveness", "EKF"):
            if name not in entry:
                continue
            seeds = entry[name]["seeds"]
            demand = " / ".join(_fmt(s["demand_rms_after_onset"], 3) for s in seeds)
            verdict = entry[name]["meets_target"]
            target = "-" if verdict is None else ("pass" if verdict else "**FAIL**")
            lines.append(
                f"| {case.label} | {entry['drive']}; {demand} {unit} | {ESTIMATOR_LABELS[name]} "
                f"| {' / '.join(_delay(s['warn_delay_s']) for s in seeds)} "
                f"| {' / '.join(_delay(s['fault_delay_s']) for s in seeds)} "
                f"| {' / '.join(s['level_before_onset'] for s in seeds)} "
                f"| {' / '.join(s['other_channel_level'] for s in seeds)} "
                f"| {' / '.join(_fmt(s['rmse_after_onset'], 3) for s in seeds)} {unit} | {target} |"
            )
            if name == "calibrated" and case.target is not None:
                failed += [(case.label, s) for s in seeds if not meets(case, [s])]
    lines.append("")
    if failed:
        lines += [
            "Runs of the calibrated observer that missed a must-show target: the faulty channel's estimate, the "
            "true fault and the level around the onset.\n",
            "| fault | seed | " + " | ".join(f"{o:+g} s" for o in TIME_COURSE_OFFSETS_S) + " |",
            "|---|---|" + "---|" * len(TIME_COURSE_OFFSETS_S),
        ]
        for label, s in failed:
            cells = [f"{_fmt(p['estimate'], 3)} (true {_fmt(p['true'], 3)}, {p['level']})" for p in s["time_course"]]
            lines.append(f"| {label} | {s['seed']} | " + " | ".join(cells) + " |")
        lines.append("")
    return lines


def _how_measured(plan: dict[str, Any]) -> list[str]:
    cal, healthy, faults, sensitivity = plan["calibration"], plan["healthy"], plan["faults"], plan["sensitivity"]
    sets = ", ".join(map(str, plan["parameter_sets"]))
    seeds = healthy["seeds"]
    return [
        "## How it was measured\n",
        "Command: `agv-fe bench --only real_vehicle` (`make bench` runs it with the others). The plant is "
        "CommonRoad's multi-body vehicle model (`vehiclemodels.vehicle_dynamics_mb`, 29 states, unchanged) of "
        f"parameter set(s) {sets}, with a torque actuator, a steering servo (lag 1 / k_steer = "
        f"{1000 / mb.STEER_SERVO_GAIN_PER_S:.0f} ms), "
        "a closed-loop driver (speed PI with feed-forward, yaw-rate path follower with an integral) and Gaussian "
        f"sensor noise (sigma v_x {plan['noise']['vx_sigma_mps']:g} m/s, r {plan['noise']['r_sigma_radps']:g} "
        "rad/s), sampled at 100 Hz (edge_client/multibody.py); the estimator's 2-DOF model was not derived from "
        f"it. {_set_two_note(plan['parameter_sets'])} "
        f"Calibration: the scripted calibration_drive() ({cal['duration_s']:g} s; sensor noise seeds "
        f"{', '.join(map(str, cal['noise_seeds']))}), one per set, through `calibrate_profile` with the set's data "
        "sheet (`base_profile`); every figure but the sensitivity check's is measured with this profile. "
        f"Sensitivity: random_drive(seeds {', '.join(map(str, sensitivity['seeds']))}, "
        f"{sensitivity['duration_s']:g} s) per set, calibrated the same way. All random drives have a "
        f"{plan['max_lateral_accel_mps2']:g} m/s^2 manoeuvre limit. Healthy driving: random_drive(seeds "
        f"{seeds[0]}-{seeds[-1]}, {healthy['duration_s']:g} s each) per set. Faults: onset at "
        f"{faults['onset_s']:g} s of {faults['duration_s']:g} s drives, seeds {', '.join(map(str, faults['seeds']))}; "
        "biases and sines on random drives; the torque loss on a drive that accelerates and brakes between two "
        "speeds from the onset on (the MB has no drag, so cruising needs no torque and a loss of effectiveness, "
        "f = (alpha - 1) T_d, only shows under a demand); the steering loss in a steady turn. "
        "Estimators: the calibrated profile's observer (`FuzzyObserver` with the calibration's gains, u0 = "
        "first demand); the same observer with its loss-of-effectiveness stage (synth/effectiveness.py, the "
        "profile's effectiveness options: a Kalman filter on the observer's reported faults against its own "
        "response to the demand; its faults are the totals, bias plus (alpha - 1) demand, and the alarm rule "
        "runs on them with the thresholds `agv-fe calibrate --effectiveness` sets from the stage's totals on the "
        "calibration drive and in its gust); the augmented EKF (synth/ekf.py) with the same parameters, bounds "
        "and noise model; the "
        "`paper` profile (VehicleParams(), OperatingBounds(), DesignOptions(), AlarmThresholds()). Each starts "
        "from its drive's first measurement at t = 0; drives of equal length run as one batch. Alarm levels: "
        "`service.fleet.alarms.FaultLevels` with the profile's thresholds, warm-up, persistence and hysteresis, "
        "on time stamps t_ns = round(t * 1e9), as the service and `agv-fe replay` do. Every figure is in "
        "real_vehicle.json beside this file.",
    ]


def _set_two_note(parameter_sets: Sequence[int]) -> str:
    if 2 in parameter_sets:
        return "This run includes parameter set 2, which the benchmark's defaults leave out."
    return "Parameter set 2 is never used here: it is kept for checks the benchmark and the product were not tuned on."


__all__ = ["DEFAULT_PARAMETER_SETS", "FAULT_CASES", "Plan", "estimate_runs", "render", "run"]
