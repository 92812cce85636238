"""Detection at fleet scale: false alarms per 1,000 vehicle-hours and the delay to catch a fault of a given size.

A fleet operator judges a fault detector by two figures: how often it raises an
alarm on a healthy vehicle, counted per 1,000 vehicle-hours, and how soon it
catches a fault of a given size. This benchmark measures both with the
service's own alarm rule (:class:`service.fleet.alarms.FaultLevels`: warm-up,
persistence, hysteresis) and a calibrated profile:

1. **Calibration**: a physical car (:data:`CAR`) driven for two minutes by the
   project's plant (:class:`edge_client.plant.PlantSimulator`, realistic sensor
   noise), through :func:`service.calibration.calibrate_profile` with the data
   sheet's mass, axle distances, wheel radius and yaw inertia; the profile's
   gains and alarms are used for everything below. The EKF's thresholds are
   set from its own estimates on the same drive, as in the real_vehicle
   benchmark (:func:`agv_fe.benchmarks.real_vehicle.ekf_thresholds`);
2. **Healthy fleet**: at least 1,000 vehicle-hours of random driving covering
   the calibrated operating box (speed changes, turns up to 7 m/s^2, lane
   changes, slaloms, wind gusts), simulated and estimated vectorised over the
   vehicles and streamed through the estimators and alarm levels (no per-sample
   history is kept); raised WARN and FAULT levels counted per channel;
3. **Multi-body plant**: the same count on CommonRoad's multi-body vehicle
   (:mod:`edge_client.multibody`, sets 1 and 3 by default), each set with its
   own calibration, with a 95 % upper bound on the rate;
4. **Detection delay against fault size**: biases, losses of effectiveness and
   sinusoids of 5, 10 and 20 % on each channel, random onsets, delays to WARN
   and FAULT (p50, p95, worst, never), the other channel's false alarms;
5. **Operating curve**: both channels' thresholds scaled by
   :data:`THRESHOLD_FACTORS`, false alarms per 1,000 h against the p95 WARN
   delay of a 10 % bias;
6. **The effectiveness alarm rule**: the observer's estimates also go through
   the loss-of-effectiveness stage (:mod:`synth.effectiveness`, the profile's
   stage options) and its alpha_hat through the service's effectiveness levels
   (:class:`service.fleet.alarms.EffectivenessLevels`: WARN below
   ``effectiveness_warn``, FAULT below ``effectiveness_fault``, each held
   ``effectiveness_after_s``): false alarms on the healthy fleet, delays on
   every fault run.

The benchmark measures; it adjusts nothing.
"""

from __future__ import annotations

import functools
import json
import math
import multiprocessing
import os
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import scipy.stats
from numpy.typing import NDArray

from agv_fe.benchmarks import REFERENCE_CAR, report_header
from agv_fe.benchmarks import real_vehicle as rv
from edge_client import multibody as mb
from edge_client.faults import BiasFault, Channel, Fault, LossOfEffectivenessFault, SinusoidalFault
from edge_client.fleet_mix import random_gusts
from edge_client.plant import PlantSimulator
from edge_client.random_drive import lateral_steady_state_gains
from edge_client.scenario import Gust, Manoeuvre, Scenario, SensorNoise, SpeedPoint
from edge_client.simulation import BatchEstimator, ekf_factory, estimate, observer_factory, simulate_plant
from service.calibration import (
    CHANNELS,
    GUST_S,
    PEAK_MARGIN,
    UNITS,
    CalibrationReport,
    ChannelThresholds,
    calibrate_profile,
)
from service.fleet.alarms import FAULT, OK, WARN, EffectivenessLevels, FaultLevels
from service.profiles import AlarmThresholds
from synth.calibration import Drive as Recording
from synth.effectiveness import EffectivenessEstimator
from synth.errors import SynthesisError
from synth.gains import ObserverGains
from synth.model import FloatArray
from synth.observer import FuzzyObserver
from synth.options import EffectivenessOptions
from synth.params import OperatingBounds, VehicleParams

# --------------------------------------------------------------------------- what is run

#: The physical car (the calibration tests' car, tests/calibration_data.py): everything calibration identifies
#: switched on, a steering actuator with a lag.
CAR = REFERENCE_CAR
#: What the car's data sheet gives calibration.
BASE_FIELDS = ("mass_kg", "front_axle_distance_m", "rear_axle_distance_m", "wheel_radius_m", "yaw_inertia_kgm2")
#: Realistic sensor noise: sigma v_x [m/s], r [rad/s].
NOISE = SensorNoise(vx_sigma_mps=0.05, r_sigma_radps=0.005)
CALIBRATION_DURATION_S = 120.0
CALIBRATION_SEED = 11
#: RK4 substeps per 10 ms sample: the calibration drive with the plant's default, the fleet and fault runs with
#: fewer (the difference is measured and reported, :func:`substep_check`).
CALIBRATION_SUBSTEPS = 10
FLEET_SUBSTEPS = 2
#: Random driving: speeds [m/s], the largest lateral acceleration [m/s^2], the share of the calibrated box's
#: |r| and |v_y| bounds a steady state may use, the speed changes' peak accelerations [m/s^2].
SPEED_RANGE_MPS = (6.0, 28.0)
MAX_LATERAL_ACCEL_MPS2 = 7.0
BOX_SHARE = 0.85
ACCEL_RANGE_MPS2 = (0.5, 3.0)
BRAKE_RANGE_MPS2 = (0.5, 4.0)
#: Every random drive ends with at least this long a straight cruise at its final speed [s].
END_CRUISE_S = 2.0
#: The healthy fleet: vehicles x duration [s] (31 min: 1,031 vehicle-hours after the 3 s warm-ups), driven in
#: segments [s] (each a new scenario, the vehicle's state, estimators and alarm levels carried on), in WORKERS
#: processes; the EKF runs on the first EKF_SHARE of each process's vehicles (the report gives the run's time
#: per stage).
HEALTHY_VEHICLES = 2000
HEALTHY_DURATION_S = 1860.0
SEGMENT_S = 310.0
EKF_SHARE = 1.0
WORKERS = 2
FLEET_SEED = 20_000
QUICK_HEALTHY_VEHICLES = 8
QUICK_HEALTHY_DURATION_S = 30.0
QUICK_SEGMENT_S = 15.0
#: Fault runs: sizes as shares of the nominal torque (calibration's nominal_torque_nm) and of NOMINAL_STEER_RAD,
#: vehicles per (channel, kind, size), run length and onset range [s].
FAULT_SIZES = (0.05, 0.10, 0.20)
NOMINAL_STEER_RAD = 0.2
VEHICLES_PER_CASE = 120
QUICK_VEHICLES_PER_CASE = 2
FAULT_RUN_S = 40.0
QUICK_FAULT_RUN_S = 24.0
ONSET_RANGE_S = (5.0, 15.0)
FAULT_SEED = 30_000
SINE_OMEGA_RADPS = 0.5
#: A loss of effectiveness steps alpha from 1 to 1 - size at this rate [1/s] (0.1 s to alpha 0.8).
LOSS_RATE_PER_S = 2.0
#: Steering faults run on random drives at these speeds [m/s], the manoeuvres' steering budget reduced by the
#: fault: the open-loop steering does not correct a steering fault, so at 28 m/s a 0.04 rad bias alone would
#: turn the car at 11 m/s^2 and out of the calibrated box.
STEER_FAULT_SPEED_RANGE_MPS = (6.0, 16.0)
#: Torque loss: accelerating and braking at this acceleration [m/s^2] between these speeds [m/s].
LOSS_ACCEL_MPS2 = 2.0
LOSS_SPEEDS_MPS = (10.0, 24.0)
#: Steering loss: a steady turn at a speed in this range [m/s], at the lateral limit, entered at 1 s.
LOSS_TURN_SPEED_MPS = (9.0, 12.0)
#: The operating curve's factors on both channels' WARN and FAULT thresholds.
THRESHOLD_FACTORS = (0.5, 0.7, 0.85, 1.0, 1.2, 1.5, 2.0)
#: The multi-body plant: healthy random drives per set, each this long [s].
MB_DRIVES = 48
MB_DRIVE_S = 120.0
MB_SEED = 5_000
QUICK_MB_DRIVES = 2
QUICK_MB_DRIVE_S = 20.0
#: Must-show targets.
FALSE_WARN_PER_1000_H = 1.0
BIAS_P95_WARN_S = 1.5
#: An alarm raised within this long of a gust [s] counts as near a gust (reported apart, counted in).
GUST_WINDOW_S = 2.0
#: Alarm events kept per estimator in the JSON (the counts cover them all), listed in the report.
KEPT_EVENTS = 40
LISTED_EVENTS = 10

#: What set a WARN threshold (service.calibration.fault_thresholds), in words.
SET_BY = {
    "noise": "the healthy estimates' Gaussian tail",
    "held peak": "the healthy estimates' held peak",
    "gust": "the 800 N gust (held {gust})",
    "floor": "the floor: 25 % of the required fault",
}

FaultKind = Literal["bias", "loss_of_effectiveness", "sinusoidal"]
FAULT_KINDS: tuple[FaultKind, ...] = ("bias", "loss_of_effectiveness", "sinusoidal")
SYMBOLS = {"torque": "T_f", "steer": "delta_f"}
ESTIMATOR_LABELS = {"observer": "calibrated observer", "EKF": "augmented EKF"}
#: The observer's estimates through the effectiveness stage, alpha_hat through the effectiveness alarm rule.
ALPHA = "effectiveness"
ALPHA_LABEL = "calibrated observer, alpha rule"
CountArray = NDArray[np.int64]
LevelArray = NDArray[np.int8]


def base_params() -> dict[str, float]:
    """What the car's data sheet gives calibration (:data:`BASE_FIELDS` of :data:`CAR`)."""
    return {name: float(getattr(CAR, name)) for name in BASE_FIELDS}


# --------------------------------------------------------------------------- drives of the project's plant


@dataclass(frozen=True)
class LateralPlanner:
    """How hard a manoeuvre may steer at a speed: the car's steady-state (v_y, r) per radian of steering on a
    speed grid (:func:`edge_client.random_drive.lateral_steady_state_gains`), and the limits |a_y| = v |r| <=
    MAX_LATERAL_ACCEL_MPS2, |r| and |v_y| within BOX_SHARE of the box's bounds."""

    params: VehicleParams
    bounds: OperatingBounds
    speeds_mps: FloatArray
    vy_gain: FloatArray
    r_gain: FloatArray

    @classmethod
    def build(cls, params: VehicleParams, bounds: OperatingBounds) -> LateralPlanner:
        speeds = np.arange(4.0, 32.01, 0.25)
        gains = np.array([lateral_steady_state_gains(params, float(v)) for v in speeds])
        return cls(params, bounds, speeds, gains[:, 0], gains[:, 1])

    def _gains(self, speed_mps: float) -> tuple[float, float]:
        """Steady-state (v_y, r) per radian of steering at ``speed_mps``: ([m/s / rad], [rad/s / rad])."""
        vy_gain = float(np.interp(speed_mps, self.speeds_mps, self.vy_gain))
        return vy_gain, float(np.interp(speed_mps, self.speeds_mps, self.r_gain))

    def steer_limit_rad(self, speed_mps: float) -> float:
        """The largest steady |delta_d| [rad] a manoeuvre may demand at ``speed_mps``: |a_y| = v |r| <=
        MAX_LATERAL_ACCEL_MPS2, and |r|, |v_y| and |delta| within BOX_SHARE of the box's bounds."""
        b = self.bounds
        vy_gain, r_gain = self._gains(speed_mps)
        r_limit = min(MAX_LATERAL_ACCEL_MPS2 / speed_mps, BOX_SHARE * min(-b.r_min_radps, b.r_max_radps))
        vy_limit = BOX_SHARE * min(-b.vy_min_mps, b.vy_max_mps)
        return min(r_limit / abs(r_gain), vy_limit / max(abs(vy_gain), 1e-9), BOX_SHARE * b.steer_max_rad)

    def steer_rad(self, speed_mps: float, yaw_rate_radps: float) -> float:
        """The steady steering angle [rad] of a yaw rate [rad/s] at ``speed_mps``."""
        return yaw_rate_radps / self._gains(speed_mps)[1]


@dataclass
class DrivePlan:
    """A speed reference and open-loop manoeuvres appended one after another, for a :class:`Scenario`.

    Lateral manoeuvres run at constant speed and straights carry the speed changes, so that each
    manoeuvre's steering follows from its speed (:class:`LateralPlanner`).
    """

    planner: LateralPlanner
    speed_mps: float
    t_s: float = 0.0
    points: list[SpeedPoint] = field(default_factory=list)
    manoeuvres: list[Manoeuvre] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.points.append(SpeedPoint(t_s=0.0, speed_mps=round(self.speed_mps, 3)))

    def cruise(self, duration_s: float) -> None:
        self.t_s += duration_s
        self.points.append(SpeedPoint(t_s=round(self.t_s, 3), speed_mps=round(self.speed_mps, 3)))

    def change_speed(self, target_mps: float, accel_mps2: float) -> None:
        """A linear ramp of the speed reference at ``accel_mps2`` [m/s^2] to ``target_mps``."""
        self.t_s += max(abs(target_mps - self.speed_mps) / accel_mps2, 0.1)
        self.speed_mps = target_mps
        self.points.append(SpeedPoint(t_s=round(self.t_s, 3), speed_mps=round(target_mps, 3)))

    def lateral(self, kind: str, steer_rad: float, duration_s: float, period_s: float = 4.0) -> None:
        """A turn, lane change or slalom of open-loop steering amplitude ``steer_rad`` [rad]."""
        self.manoeuvres.append(
            Manoeuvre(
                kind=kind,
                start_s=round(self.t_s, 3),
                duration_s=round(duration_s, 3),
                amplitude_rad=steer_rad,
                period_s=period_s,
            )
        )
        self.cruise(duration_s)

    def scenario(
        self, name: str, duration_s: float, seed: int, faults: Sequence[Fault] = (), gusts: Sequence[Gust] = ()
    ) -> Scenario:
        """The plan as a scenario of the car with the realistic sensor noise."""
        return Scenario(
            name=name[:64],
            duration_s=duration_s,
            initial_speed_mps=self.points[0].speed_mps,
            speed_profile=tuple(self.points),
            manoeuvres=tuple(self.manoeuvres),
            faults=tuple(faults),
            gusts=tuple(gusts),
            noise=NOISE,
            vehicle=CAR,
            seed=seed,
        )


def random_plan(
    planner: LateralPlanner,
    rng: np.random.Generator,
    duration_s: float,
    start_speed_mps: float,
    speed_range_mps: tuple[float, float] = SPEED_RANGE_MPS,
    reserved_steer_rad: float = 0.0,
) -> DrivePlan:
    """Random driving for ``duration_s`` from ``start_speed_mps``: cruises, speed changes, turns (2-8 s held),
    lane changes and slaloms at up to the planner's limits (amplitudes uniform in 0.3-1 of them, the steering
    reduced by ``reserved_steer_rad`` [rad]). Every action ends END_CRUISE_S before ``duration_s`` (one that
    would not is drawn again, up to five times), so a drive ends cruising straight at the speed it ends with
    (``plan.speed_mps``): the next segment of a vehicle starts from there."""
    low, high = speed_range_mps
    plan = DrivePlan(planner, start_speed_mps)
    kinds = ("cruise", "accelerate", "brake", "turn", "lane_change", "slalom")
    weights = np.array([0.12, 0.14, 0.14, 0.2, 0.2, 0.2])
    end_s = duration_s - END_CRUISE_S
    misses = 0
    while misses < 5:
        kind = str(rng.choice(kinds, p=weights))
        speed = plan.speed_mps
        if kind in ("accelerate", "brake"):
            room_up, room_down = high - speed, speed - low
            going_up = room_up > room_down if min(room_up, room_down) < 2.0 else kind == "accelerate"
            target = float(
                rng.uniform(speed + 0.5 * room_up, high) if going_up else rng.uniform(low, speed - 0.5 * room_down)
            )
            accel = float(rng.uniform(*(ACCEL_RANGE_MPS2 if going_up else BRAKE_RANGE_MPS2)))
            fits = plan.t_s + max(abs(target - speed) / accel, 0.1) <= end_s
            if fits:
                plan.change_speed(target, accel)
        elif kind == "cruise":
            length = float(rng.uniform(1.0, 5.0))
            fits = plan.t_s + length <= end_s
            if fits:
                plan.cruise(length)
        else:
            limit = max(planner.steer_limit_rad(speed) - reserved_steer_rad, 0.0)
            steer = float(rng.uniform(0.3, 1.0) * limit * rng.choice([-1.0, 1.0]))
            period = 4.0
            if kind == "turn":
                length = float(rng.uniform(2.0, 8.0)) + 2.0
            elif kind == "lane_change":
                length = float(rng.uniform(4.0, 8.0))
            else:
                period = float(rng.uniform(3.0, 6.0))
                length = period * int(rng.integers(1, 4))
            pause = float(rng.uniform(0.5, 2.0))
            fits = plan.t_s + length + pause <= end_s
            if fits:
                plan.lateral(kind, steer, length, period)
                plan.cruise(pause)
        misses = 0 if fits else misses + 1
    plan.cruise(max(duration_s - plan.t_s, END_CRUISE_S))
    return plan


def segment_gusts(rng: np.random.Generator, duration_s: float) -> tuple[Gust, ...]:
    """:func:`edge_client.fleet_mix.random_gusts` that end 1 s before ``duration_s`` (a segment's end)."""
    return tuple(g for g in random_gusts(rng, duration_s) if g.start_s + g.duration_s <= duration_s - 1.0)


def calibration_plan(planner: LateralPlanner) -> DrivePlan:
    """Two minutes of the car's ordinary driving, the same every time: speed changes between 8 and 24 m/s
    (1.5-3 m/s^2), turns both ways at 3 to 6 m/s^2, lane changes and slaloms at 10, 15, 20 and 12 m/s."""
    plan = DrivePlan(planner, 10.0)
    plan.cruise(2.0)
    for speed, accel in ((10.0, 0.0), (15.0, 2.0), (22.0, 1.5), (12.0, 3.0)):
        if accel:
            plan.change_speed(speed, accel)
            plan.cruise(1.0)
        for kind, a_y, duration in (("turn", 3.0, 4.0), ("turn", -6.0, 4.0), ("lane_change", 4.0, 5.0)):
            plan.lateral(kind, planner.steer_rad(speed, a_y / speed), duration)
            plan.cruise(1.0)
        plan.lateral("slalom", planner.steer_rad(speed, -4.0 / speed), 6.0, 3.0)
        plan.cruise(1.0)
    plan.change_speed(8.0, 2.0)
    plan.change_speed(18.0, 2.5)
    plan.cruise(max(CALIBRATION_DURATION_S - plan.t_s, 1.0))
    return plan


def calibration_scenario() -> Scenario:
    """The calibration drive as a scenario (planned with the paper's operating box: no profile exists yet)."""
    plan = calibration_plan(LateralPlanner.build(CAR, OperatingBounds()))
    return plan.scenario("calibration", CALIBRATION_DURATION_S, CALIBRATION_SEED)


# --------------------------------------------------------------------------- counting alarms


class RaiseCounter:
    """The service's alarm levels (:class:`FaultLevels`) over a batch of n vehicles, counting raised levels.

    Raised, as in the real_vehicle benchmark (:func:`agv_fe.benchmarks.real_vehicle.raises`): a channel's level
    went from OK to WARN or higher (``warn_raised``), or from below FAULT to FAULT (``fault_raised``); both
    (n, 2) per vehicle and channel [torque, steer]. ``level`` (n, 2) holds the levels after the last update.
    ``effectiveness``: the levels are the effectiveness rule's (:class:`EffectivenessLevels`), fed alpha_hat
    and its posterior standard deviation (n, 2) each [-]; as in the service they have no warm-up (the stage holds
    alpha_hat at 1, and its sigma at the prior, for its start delay).
    """

    def __init__(self, n_vehicles: int, alarms: AlarmThresholds, effectiveness: bool = False) -> None:
        self.alarms = alarms
        self.levels: FaultLevels | EffectivenessLevels = (
            EffectivenessLevels(n_vehicles, alarms) if effectiveness else FaultLevels(n_vehicles, alarms)
        )
        self.rows = np.arange(n_vehicles, dtype=np.intp)
        self.level: LevelArray = np.zeros((n_vehicles, 2), dtype=np.int8)
        self.warn_raised: CountArray = np.zeros((n_vehicles, 2), dtype=np.int64)
        self.fault_raised: CountArray = np.zeros((n_vehicles, 2), dtype=np.int64)
        self._t_ns = np.zeros(n_vehicles, dtype=np.int64)

    @property
    def n_vehicles(self) -> int:
        return int(self.rows.size)

    def restart(self, t_ns: int) -> None:
        """Every vehicle's estimator (re)starts at ``t_ns`` [ns]: the warm-up runs from there."""
        self._t_ns.fill(t_ns)
        if isinstance(self.levels, FaultLevels):
            self.levels.restart(self.rows, self._t_ns)
        else:
            self.levels.reset(self.rows)

    def update(
        self,
        f_hat: FloatArray,
        t_ns: int,
        usable: NDArray[np.bool_] | None = None,
        alpha_sigma: FloatArray | None = None,
        certified: NDArray[np.bool_] | None = None,
        measured: FloatArray | None = None,
    ) -> tuple[NDArray[np.intp], NDArray[np.bool_], NDArray[np.bool_]]:
        """Feed one sample's fault estimates f_hat (n, 2) [N m, rad] at ``t_ns`` [ns] (``usable``: finite rows;
        ``certified``: the rows the design's certificate covers, as the service's levels take them; ``measured``
        (n, 2) [v_x m/s, r rad/s] for the grip gate, as the service's levels take them); alpha_hat
        (n, 2) [-] and ``alpha_sigma`` (n, 2) [-] for the effectiveness rule (a non-finite alpha_hat raises
        nothing).

        Returns the vehicles whose level changed (m,) and, for them, where WARN and FAULT were raised (m, 2).
        """
        self._t_ns.fill(t_ns)
        if isinstance(self.levels, FaultLevels):
            changed = self.levels.update(self.rows, f_hat, self._t_ns, usable, certified, measured)
        else:
            sigma = np.zeros_like(f_hat) if alpha_sigma is None else alpha_sigma
            changed = self.levels.update(self.rows, f_hat, sigma, self._t_ns)
        if not changed.size:
            return changed, np.zeros((0, 2), dtype=bool), np.zeros((0, 2), dtype=bool)
        rows = np.unique(changed)
        new = np.column_stack([self.levels.torque.level[rows], self.levels.steer.level[rows]])
        old = self.level[rows]
        to_warn = (old == OK) & (new >= WARN)
        to_fault = (old < FAULT) & (new == FAULT)
        self.warn_raised[rows] += to_warn
        self.fault_raised[rows] += to_fault
        self.level[rows] = new
        return rows, to_warn, to_fault


def count_raises(f_hat: FloatArray, alarms: AlarmThresholds, sample_period_s: float) -> RaiseCounter:
    """The counting path over a whole sequence f_hat (K, n, 2) starting at t = 0 (the estimators' start)."""
    period_ns = round(sample_period_s * 1e9)
    counter = RaiseCounter(f_hat.shape[1], alarms)
    counter.restart(0)
    for k in range(f_hat.shape[0]):
        counter.update(f_hat[k], k * period_ns, usable_rows(f_hat[k]))
    return counter


def usable_rows(f_hat: FloatArray) -> NDArray[np.bool_] | None:
    """The rows of f_hat (n, 2) with finite estimates, None when all are (the levels' fast path): a non-finite
    estimate is not fed to the alarm levels, as in the service."""
    finite = np.asarray(np.isfinite(f_hat).all(axis=1), dtype=bool)
    return None if finite.all() else finite


@dataclass(frozen=True)
class Rule:
    """An alarm rule the estimates go through: a label, the factor on the profile's four thresholds, and the
    resulting :class:`AlarmThresholds`."""

    key: str
    factor: float
    alarms: AlarmThresholds


def scaled(alarms: AlarmThresholds, factor: float) -> AlarmThresholds:
    """The alarm settings with both channels' WARN and FAULT thresholds multiplied by ``factor``."""
    return alarms.model_copy(
        update={
            "torque_warn_nm": alarms.torque_warn_nm * factor,
            "torque_fault_nm": alarms.torque_fault_nm * factor,
            "steer_warn_rad": alarms.steer_warn_rad * factor,
            "steer_fault_rad": alarms.steer_fault_rad * factor,
        }
    )


def rule_set(alarms: AlarmThresholds, factors: Sequence[float] = THRESHOLD_FACTORS) -> list[Rule]:
    """The profile's rule (key "default", factor 1) first, then the operating curve's scaled thresholds."""
    rules = [Rule("default", 1.0, alarms)]
    rules += [Rule(f"x{f:g}", f, scaled(alarms, f)) for f in factors if f != 1.0]
    return rules


# --------------------------------------------------------------------------- the healthy fleet (project's plant)


@dataclass(frozen=True)
class FleetJob:
    """A share of the healthy fleet for one process: ``vehicles`` (global ids) drive ``duration_s`` in segments
    of ``segment_s``; the observer sees all of them, the EKF the first ``n_ekf``; each estimate goes through
    every rule."""

    gains: ObserverGains
    observer_rules: tuple[Rule, ...]
    ekf_rules: tuple[Rule, ...]
    vehicles: tuple[int, ...]
    n_ekf: int
    duration_s: float
    segment_s: float
    stage: EffectivenessOptions
    alpha_rules: tuple[Rule, ...]
    substeps: int = FLEET_SUBSTEPS
    seed: int = FLEET_SEED


@dataclass
class Tally:
    """What one estimator did over the healthy driving of a job: per rule the raised levels per vehicle and
    channel; the alarm events of the default rule; peak, sum of squares and count of the estimates after the
    warm-up per channel; samples in the premise domain; non-finite samples. ``effectiveness``: the estimates
    are alpha_hat through the effectiveness rule, and peak and sum of squares are of the loss 1 - alpha_hat."""

    rules: tuple[Rule, ...]
    counters: list[RaiseCounter]
    effectiveness: bool = False
    #: per rule, the raised levels (2,) [WARN, FAULT] x channel of vehicles that met a gust within GUST_WINDOW_S
    near_gust: list[CountArray] = field(default_factory=list)
    events: list[dict[str, Any]] = field(default_factory=list)
    peak_abs: FloatArray = field(default_factory=lambda: np.zeros(2))
    sum_squares: FloatArray = field(default_factory=lambda: np.zeros(2))
    samples_after_warmup: int = 0
    samples: int = 0
    in_domain: int = 0
    #: samples outside the certified domain (premise, v_y_hat or the applied angle out of the box)
    uncertified: int = 0
    non_finite: int = 0

    @classmethod
    def make(cls, n_vehicles: int, rules: Sequence[Rule], effectiveness: bool = False) -> Tally:
        return cls(
            tuple(rules),
            [RaiseCounter(n_vehicles, r.alarms, effectiveness) for r in rules],
            effectiveness,
            [np.zeros((2, 2), dtype=np.int64) for _ in rules],
        )

    def restart(self, t_ns: int) -> None:
        for counter in self.counters:
            counter.restart(t_ns)

    def update(
        self,
        f_hat: FloatArray,
        in_domain: NDArray[np.bool_],
        t_ns: int,
        warm: bool,
        near_gust: NDArray[np.bool_],
        context: Callable[[int], dict[str, Any]],
        alpha_sigma: FloatArray | None = None,
        certified: NDArray[np.bool_] | None = None,
        measured: FloatArray | None = None,
    ) -> None:
        """One sample of the batch, n vehicles: f_hat (n, 2), in_domain (n,), near_gust (n,) a gust within
        GUST_WINDOW_S; ``warm``: after the warm-up; ``context(vehicle)`` describes an alarm's vehicle;
        ``alpha_sigma`` (n, 2): alpha_hat's standard deviation, for the effectiveness rule; ``certified`` (n,):
        the rows the design's certificate covers (None: all); ``measured`` (n, 2) [v_x, r] for the grip gate."""
        usable = usable_rows(f_hat)
        finite = slice(None) if usable is None else usable
        if usable is not None:
            self.non_finite += int((~usable).sum())
        self.samples += f_hat.shape[0]
        self.in_domain += int(np.count_nonzero(in_domain))
        if certified is not None:
            self.uncertified += int(certified.size - np.count_nonzero(certified))
        if warm:
            magnitude = np.abs(1.0 - f_hat[finite] if self.effectiveness else f_hat[finite])
            if magnitude.size:
                np.maximum(self.peak_abs, magnitude.max(axis=0), out=self.peak_abs)
                self.sum_squares += np.einsum("ij,ij->j", magnitude, magnitude)
                self.samples_after_warmup += magnitude.shape[0]
        for i, counter in enumerate(self.counters):
            rows, to_warn, to_fault = counter.update(f_hat, t_ns, usable, alpha_sigma, certified, measured)
            if not rows.size:
                continue
            gust = near_gust[rows, None]
            self.near_gust[i][0] += (to_warn & gust).sum(axis=0)
            self.near_gust[i][1] += (to_fault & gust).sum(axis=0)
            if i == 0 and (to_warn.any() or to_fault.any()) and len(self.events) < KEPT_EVENTS:
                for j, row in enumerate(rows):
                    for c, channel in enumerate(CHANNELS):
                        if to_warn[j, c] or to_fault[j, c]:
                            level = "FAULT" if counter.level[row, c] == FAULT else "WARN"
                            self.events.append(
                                {"channel": channel, "level": level, "estimate": float(f_hat[row, c])}
                                | context(int(row))
                                | {"near_gust": bool(near_gust[row])}
                            )

    def summary(self) -> dict[str, Any]:
        """Plain data: per rule the totals per channel and the vehicles with a raised level."""
        rules = {}
        for rule, counter, gust in zip(self.rules, self.counters, self.near_gust, strict=True):
            rules[rule.key] = {
                "factor": rule.factor,
                "warn_raised": counter.warn_raised.sum(axis=0).tolist(),
                "fault_raised": counter.fault_raised.sum(axis=0).tolist(),
                "warn_raised_near_gust": gust[0].tolist(),
                "fault_raised_near_gust": gust[1].tolist(),
                "vehicles_with_warn": np.count_nonzero(counter.warn_raised, axis=0).tolist(),
            }
        return {
            "rules": rules,
            "events": self.events,
            "peak_abs": self.peak_abs.tolist(),
            "sum_squares": self.sum_squares.tolist(),
            "samples_after_warmup": self.samples_after_warmup,
            "samples": self.samples,
            "in_domain": self.in_domain,
            "uncertified": self.uncertified,
            "non_finite": self.non_finite,
        }


@dataclass
class DrivingStats:
    """How the fleet drove (true state): speed range [m/s], peak |v_x r| [m/s^2] (where: vehicle, t [s]) and
    samples above 5 m/s^2, peak |r| [rad/s] and |v_y| [m/s], samples outside the calibrated box (v_x, v_y or
    r beyond its bounds), peak |F_w| [N] and samples with a gust."""

    speed_min_mps: float = math.inf
    speed_max_mps: float = 0.0
    peak_lateral_accel_mps2: float = 0.0
    peak_lateral_accel_at: tuple[int, float] = (-1, 0.0)
    samples_above_5_mps2: int = 0
    peak_yaw_rate_radps: float = 0.0
    peak_lateral_speed_mps: float = 0.0
    samples_outside_box: int = 0
    peak_wind_n: float = 0.0
    samples_with_gust: int = 0

    def update(
        self, x: FloatArray, wind: FloatArray, bounds: OperatingBounds, vehicles: Sequence[int], t_s: float
    ) -> None:
        """One sample of the batch: x (n, 3) true [v_x, v_y, r], wind (n,) [N]; vehicles (n,) their ids."""
        a_y = np.abs(x[:, 0] * x[:, 2])
        peak = int(np.argmax(a_y))
        if a_y[peak] > self.peak_lateral_accel_mps2:
            self.peak_lateral_accel_mps2 = float(a_y[peak])
            self.peak_lateral_accel_at = (int(vehicles[peak]), t_s)
        self.speed_min_mps = min(self.speed_min_mps, float(x[:, 0].min()))
        self.speed_max_mps = max(self.speed_max_mps, float(x[:, 0].max()))
        self.samples_above_5_mps2 += int(np.count_nonzero(a_y > 5.0))
        self.peak_yaw_rate_radps = max(self.peak_yaw_rate_radps, float(np.abs(x[:, 2]).max()))
        self.peak_lateral_speed_mps = max(self.peak_lateral_speed_mps, float(np.abs(x[:, 1]).max()))
        low = np.array([bounds.vx_min_mps, bounds.vy_min_mps, bounds.r_min_radps])
        high = np.array([bounds.vx_max_mps, bounds.vy_max_mps, bounds.r_max_radps])
        self.samples_outside_box += int(np.count_nonzero(((x < low) | (x > high)).any(axis=1)))
        self.peak_wind_n = max(self.peak_wind_n, float(np.abs(wind).max()))
        self.samples_with_gust += int(np.count_nonzero(wind))

    def merge(self, other: DrivingStats) -> None:
        if other.peak_lateral_accel_mps2 > self.peak_lateral_accel_mps2:
            self.peak_lateral_accel_mps2 = other.peak_lateral_accel_mps2
            self.peak_lateral_accel_at = other.peak_lateral_accel_at
        self.speed_min_mps = min(self.speed_min_mps, other.speed_min_mps)
        self.speed_max_mps = max(self.speed_max_mps, other.speed_max_mps)
        self.samples_above_5_mps2 += other.samples_above_5_mps2
        self.peak_yaw_rate_radps = max(self.peak_yaw_rate_radps, other.peak_yaw_rate_radps)
        self.peak_lateral_speed_mps = max(self.peak_lateral_speed_mps, other.peak_lateral_speed_mps)
        self.samples_outside_box += other.samples_outside_box
        self.peak_wind_n = max(self.peak_wind_n, other.peak_wind_n)
        self.samples_with_gust += other.samples_with_gust

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DrivingStats:
        return cls(**(data | {"peak_lateral_accel_at": tuple(data["peak_lateral_accel_at"])}))


def fleet_segment(
    planner: LateralPlanner,
    rngs: Sequence[np.random.Generator],
    start_speeds_mps: list[float],
    vehicles: Sequence[int],
    segment: int,
    duration_s: float,
    seed: int,
) -> list[Scenario]:
    """One segment's scenarios: a random drive from each vehicle's current speed, with gusts; the speeds are
    updated to where the drives end."""
    scenarios = []
    for i, (rng, vehicle) in enumerate(zip(rngs, vehicles, strict=True)):
        plan = random_plan(planner, rng, duration_s, start_speeds_mps[i])
        start_speeds_mps[i] = plan.speed_mps
        gusts = segment_gusts(rng, duration_s)
        scenarios.append(
            plan.scenario(f"veh-{vehicle}-{segment}", duration_s, seed + 7919 * vehicle + segment, (), gusts)
        )
    return scenarios


def _alarm_context(vehicles: Sequence[int], sample: Any, t_ns: int, row: int) -> dict[str, Any]:
    """What a vehicle of the fleet was doing when one of its levels was raised: ``row`` of the plant's sample."""
    return {
        "vehicle": vehicles[row],
        "t_s": t_ns / 1e9,
        "speed_mps": float(sample.x[row, 0]),
        "lateral_accel_mps2": float(sample.x[row, 0] * sample.x[row, 2]),
        "wind_n": float(sample.wind[row]),
    }


def run_fleet_job(job: FleetJob) -> dict[str, Any]:
    """Drive the job's vehicles through their segments with the project's plant, stream every sample through
    the observer (all vehicles) and the EKF (the first ``n_ekf``) and their rules; return plain data."""
    started = time.perf_counter()
    period_s = CAR.sample_period_s
    period_ns = round(period_s * 1e9)
    n = len(job.vehicles)
    planner = LateralPlanner.build(CAR, job.gains.bounds)
    rngs = [np.random.default_rng([job.seed, v]) for v in job.vehicles]
    speeds = [float(rng.uniform(*SPEED_RANGE_MPS)) for rng in rngs]
    tallies = {
        "observer": Tally.make(n, job.observer_rules),
        "EKF": Tally.make(job.n_ekf, job.ekf_rules),
        ALPHA: Tally.make(n, job.alpha_rules, effectiveness=True),
    }
    driving = DrivingStats()
    estimators: dict[str, BatchEstimator] = {}
    observer: FuzzyObserver | None = None
    stage: EffectivenessEstimator | None = None
    warmup_ns = round(job.observer_rules[0].alarms.warmup_s * 1e9)
    state: NDArray[np.float64] | None = None
    steer: FloatArray | None = None
    gust_window_ns = round(GUST_WINDOW_S * 1e9)
    last_gust_ns = np.full(n, -gust_window_ns - 1, dtype=np.int64)
    k_total = 0
    n_segments = max(1, math.ceil(job.duration_s / job.segment_s - 1e-9))
    for segment in range(n_segments):
        length_s = min(job.segment_s, job.duration_s - segment * job.segment_s)
        scenarios = fleet_segment(planner, rngs, speeds, job.vehicles, segment, length_s, job.seed)
        plant = PlantSimulator(scenarios, params=CAR, substeps=job.substeps, prefetch=False)
        if state is not None:
            plant.state, plant.steer_angle = state, steer
        for _ in range(int(plant.n_samples.max())):
            sample = plant.step()
            t_ns = k_total * period_ns
            if observer is None or stage is None:
                observer = FuzzyObserver(job.gains, sample.y, None, sample.u)
                stage = EffectivenessEstimator(job.gains, job.stage, n, sample.u)
                estimators["EKF"] = ekf_factory(job.gains)(sample.y[: job.n_ekf], None, sample.u[: job.n_ekf])
                for tally in tallies.values():
                    tally.restart(t_ns)
            warm = t_ns >= warmup_ns
            driving.update(sample.x, sample.wind, job.gains.bounds, job.vehicles, t_ns / 1e9)
            last_gust_ns[sample.wind != 0.0] = t_ns
            near_gust = t_ns - last_gust_ns <= gust_window_ns
            context = functools.partial(_alarm_context, job.vehicles, sample, t_ns)
            result = observer.step(sample.y, sample.u)
            certified = result.certified
            tallies["observer"].update(
                result.faults, result.in_domain, t_ns, warm, near_gust, context, certified=certified, measured=sample.y
            )
            second = stage.step(result, sample.y, sample.u)
            tallies[ALPHA].update(second.alpha, result.in_domain, t_ns, warm, near_gust, context, second.alpha_sigma)
            if job.n_ekf:
                out = estimators["EKF"].step(sample.y[: job.n_ekf], sample.u[: job.n_ekf])
                tallies["EKF"].update(
                    out.faults,
                    out.in_domain,
                    t_ns,
                    warm,
                    near_gust[: job.n_ekf],
                    context,
                    certified=out.certified,
                    measured=sample.y[: job.n_ekf],
                )
            k_total += 1
        state, steer = plant.state, plant.steer_angle
    return {
        "vehicles": n,
        "ekf_vehicles": job.n_ekf,
        "samples_per_vehicle": k_total,
        "warmup_samples": math.ceil(warmup_ns / period_ns),
        "driving": vars(driving),
        "observer": tallies["observer"].summary(),
        "EKF": tallies["EKF"].summary(),
        ALPHA: tallies[ALPHA].summary() | {"jump_detections": [] if stage is None else stage.jumps.sum(0).tolist()},
        "wall_s": time.perf_counter() - started,
    }


# --------------------------------------------------------------------------- fault runs (detection delay)


@dataclass(frozen=True)
class FaultCase:
    """Faults of one (channel, kind, size): ``size`` is a share of the nominal torque or of NOMINAL_STEER_RAD
    (bias, sine amplitude), or the effectiveness lost, alpha = 1 - size (loss of effectiveness)."""

    channel: Channel
    kind: FaultKind
    size: float

    @property
    def key(self) -> str:
        return f"{self.channel}_{self.kind}_{round(100 * self.size)}"

    @property
    def other(self) -> int:
        return 1 - CHANNELS.index(self.channel)

    def magnitude(self, nominal_torque_nm: float) -> float:
        """The bias or amplitude [N m] or [rad] (the loss's 1 - alpha for a loss of effectiveness)."""
        if self.kind == "loss_of_effectiveness":
            return self.size
        return self.size * (nominal_torque_nm if self.channel == "torque" else NOMINAL_STEER_RAD)

    def label(self, nominal_torque_nm: float) -> str:
        percent = f"{100 * self.size:g} %"
        if self.kind == "loss_of_effectiveness":
            return f"{SYMBOLS[self.channel]} loss of effectiveness, alpha {1 - self.size:g}"
        unit = UNITS[self.channel]
        value = f"{self.magnitude(nominal_torque_nm):.3g} {unit}"
        what = "bias" if self.kind == "bias" else f"sine at {SINE_OMEGA_RADPS:g} rad/s"
        return f"{SYMBOLS[self.channel]} {what} {percent} ({value})"

    def fault(self, onset_s: float, sign: float, nominal_torque_nm: float) -> Fault:
        """The fault of one run, from ``onset_s`` [s], of sign ``sign`` (biases and sines)."""
        value = sign * self.magnitude(nominal_torque_nm)
        if self.kind == "bias":
            return BiasFault(channel=self.channel, onset_s=onset_s, magnitude=value)
        if self.kind == "sinusoidal":
            return SinusoidalFault(channel=self.channel, onset_s=onset_s, amplitude=value, omega_radps=SINE_OMEGA_RADPS)
        return LossOfEffectivenessFault(
            channel=self.channel, onset_s=onset_s, rate_per_s=LOSS_RATE_PER_S, alpha_min=1.0 - self.size
        )


_CHANNELS: tuple[Channel, ...] = ("torque", "steer")
FAULT_CASES = tuple(
    FaultCase(channel, kind, size) for channel in _CHANNELS for kind in FAULT_KINDS for size in FAULT_SIZES
)


def accelerate_brake_plan(planner: LateralPlanner, rng: np.random.Generator, duration_s: float) -> DrivePlan:
    """Straight, accelerating and braking at LOSS_ACCEL_MPS2 between LOSS_SPEEDS_MPS with 0.5 s holds, from a
    random phase: the drive torque's demand |T_d| is about m_eff R_w LOSS_ACCEL_MPS2 most of the time."""
    low, high = LOSS_SPEEDS_MPS
    plan = DrivePlan(planner, float(rng.uniform(low, high)))
    going_up = bool(rng.random() < 0.5)
    while plan.t_s < duration_s:
        plan.change_speed(high if going_up else low, LOSS_ACCEL_MPS2)
        plan.cruise(0.5)
        going_up = not going_up
    return plan


def steady_turn_plan(planner: LateralPlanner, rng: np.random.Generator, duration_s: float) -> DrivePlan:
    """A straight second, then a steady turn (1 s ramp) held to the end at the planner's steering limit, at a
    speed in LOSS_TURN_SPEED_MPS, either way: the largest sustained steering demand the box allows."""
    speed = float(rng.uniform(*LOSS_TURN_SPEED_MPS))
    plan = DrivePlan(planner, speed)
    plan.cruise(1.0)
    steer = float(rng.choice([-1.0, 1.0])) * planner.steer_limit_rad(speed)
    plan.lateral("turn", steer, duration_s)
    return plan


def fault_scenario(
    case: FaultCase, planner: LateralPlanner, index: int, vehicle: int, nominal_torque_nm: float, duration_s: float
) -> tuple[Scenario, float]:
    """One fault run: its scenario and its onset [s] (uniform in ONSET_RANGE_S), seeded by (case, vehicle)."""
    rng = np.random.default_rng([FAULT_SEED, index, vehicle])
    onset = round(float(rng.uniform(*ONSET_RANGE_S)), 2)
    sign = float(rng.choice([-1.0, 1.0]))
    if case.kind == "loss_of_effectiveness":
        plan = (accelerate_brake_plan if case.channel == "torque" else steady_turn_plan)(planner, rng, duration_s)
    elif case.channel == "steer":
        low, high = STEER_FAULT_SPEED_RANGE_MPS
        reserved = case.magnitude(nominal_torque_nm)
        plan = random_plan(planner, rng, duration_s, float(rng.uniform(low, high)), (low, high), reserved)
    else:
        plan = random_plan(planner, rng, duration_s, float(rng.uniform(*SPEED_RANGE_MPS)))
    fault = case.fault(onset, sign, nominal_torque_nm)
    seed = FAULT_SEED + 1000 * index + vehicle
    return plan.scenario(f"{case.key}-{vehicle}", duration_s, seed, (fault,)), onset


class DelayTracker:
    """Per fault run (n): the first time at or after the onset when the faulty channel's level reached WARN and
    FAULT [s] (NaN: not yet), and whether it was at WARN or higher after the warm-up but before the onset."""

    def __init__(self, onset_s: FloatArray, channel: NDArray[np.intp]) -> None:
        n = onset_s.size
        self.onset_s = onset_s
        self.channel = channel
        self.rows = np.arange(n, dtype=np.intp)
        self.warn_at_s = np.full(n, np.nan)
        self.fault_at_s = np.full(n, np.nan)
        self.before_onset = np.zeros(n, dtype=bool)

    def update(self, t_s: float, level: LevelArray) -> None:
        """The levels (n, 2) after the sample at ``t_s`` [s]."""
        faulty = level[self.rows, self.channel]
        after = t_s >= self.onset_s
        warn = faulty >= WARN
        self.before_onset |= warn & ~after
        hit = after & warn & np.isnan(self.warn_at_s)
        self.warn_at_s[hit] = t_s
        hit = after & (faulty == FAULT) & np.isnan(self.fault_at_s)
        self.fault_at_s[hit] = t_s

    @property
    def warn_delay_s(self) -> FloatArray:
        """Delay from the onset to WARN (n,) [s], NaN where never within the run."""
        return self.warn_at_s - self.onset_s

    @property
    def fault_delay_s(self) -> FloatArray:
        return self.fault_at_s - self.onset_s


@dataclass(frozen=True)
class FaultJob:
    """Fault runs for one process: (case index, vehicle) pairs; the estimators and rules as in a FleetJob."""

    gains: ObserverGains
    observer_rules: tuple[Rule, ...]
    ekf_rules: tuple[Rule, ...]
    runs: tuple[tuple[int, int], ...]
    nominal_torque_nm: float
    duration_s: float
    stage: EffectivenessOptions
    alpha_rules: tuple[Rule, ...]
    substeps: int = FLEET_SUBSTEPS
    #: False: the EKF does not run (its figures are those of an estimate of zero), for the effectiveness part
    with_ekf: bool = True


def run_fault_job(job: FaultJob) -> dict[str, Any]:
    """Simulate the job's fault runs as one batch and stream them through both estimators and every rule;
    per run and rule: the WARN and FAULT delays [s] (None: never), an alarm before the onset, and the other
    channel's raised WARN and FAULT levels."""
    started = time.perf_counter()
    planner = LateralPlanner.build(CAR, job.gains.bounds)
    made = [fault_scenario(FAULT_CASES[i], planner, i, v, job.nominal_torque_nm, job.duration_s) for i, v in job.runs]
    onset = np.array([o for _, o in made])
    channel = np.array([CHANNELS.index(FAULT_CASES[i].channel) for i, _ in job.runs], dtype=np.intp)
    plant = PlantSimulator([s for s, _ in made], params=CAR, substeps=job.substeps, prefetch=False)
    n = len(made)
    period_ns = round(CAR.sample_period_s * 1e9)
    counters = {
        "observer": [RaiseCounter(n, r.alarms) for r in job.observer_rules],
        "EKF": [RaiseCounter(n, r.alarms) for r in job.ekf_rules],
        ALPHA: [RaiseCounter(n, r.alarms, effectiveness=True) for r in job.alpha_rules],
    }
    trackers = {name: [DelayTracker(onset, channel) for _ in rules] for name, rules in counters.items()}
    observer: FuzzyObserver | None = None
    stage: EffectivenessEstimator | None = None
    ekf: BatchEstimator | None = None
    for k in range(int(plant.n_samples.max())):
        sample = plant.step()
        if observer is None or stage is None or (ekf is None and job.with_ekf):
            observer = FuzzyObserver(job.gains, sample.y, None, sample.u)
            stage = EffectivenessEstimator(job.gains, job.stage, n, sample.u)
            ekf = ekf_factory(job.gains)(sample.y, None, sample.u) if job.with_ekf else None
            for rule_counters in counters.values():
                for counter in rule_counters:
                    counter.restart(0)
        result = observer.step(sample.y, sample.u)
        second = stage.step(result, sample.y, sample.u)
        ekf_out = ekf.step(sample.y, sample.u) if ekf is not None else None
        outputs = {
            "observer": (result.faults, result.certified),
            "EKF": (np.zeros_like(result.faults), None) if ekf_out is None else (ekf_out.faults, ekf_out.certified),
            ALPHA: (second.alpha, None),
        }
        for name, (values, certified) in outputs.items():
            usable = usable_rows(values)
            sigma = second.alpha_sigma if name == ALPHA else None
            for counter, tracker in zip(counters[name], trackers[name], strict=True):
                counter.update(values, k * period_ns, usable, sigma, certified, None if name == ALPHA else sample.y)
                tracker.update(sample.t, counter.level)
    results: dict[str, Any] = {"runs": [list(r) for r in job.runs], "onset_s": onset.tolist()}
    other = 1 - channel
    rows = np.arange(n)
    for name, rules in (("observer", job.observer_rules), ("EKF", job.ekf_rules), (ALPHA, job.alpha_rules)):
        results[name] = {
            rule.key: {
                "warn_delay_s": _nan_to_none(tracker.warn_delay_s),
                "fault_delay_s": _nan_to_none(tracker.fault_delay_s),
                "before_onset": tracker.before_onset.tolist(),
                "other_warn_raised": counter.warn_raised[rows, other].tolist(),
                "other_fault_raised": counter.fault_raised[rows, other].tolist(),
            }
            for rule, counter, tracker in zip(rules, counters[name], trackers[name], strict=True)
        }
    results["wall_s"] = time.perf_counter() - started
    return results


def _nan_to_none(values: FloatArray) -> list[float | None]:
    return [None if not math.isfinite(v) else round(float(v), 6) for v in values]


# --------------------------------------------------------------------------- the calibration run, the substep check


def plant_run(
    t: FloatArray, x: FloatArray, y: FloatArray, u: FloatArray, f: FloatArray, name: str, seed: int
) -> mb.MultibodyRun:
    """One vehicle of the project's plant in the multi-body plant's record type, so that the real_vehicle
    benchmark's functions (:func:`~agv_fe.benchmarks.real_vehicle.ekf_thresholds`) take it: t (K,) [s], x (K, 3)
    true state, y, u, f (K, 2); parameter set 0 stands for the project's plant. The applied steering angle is
    the actuator's target (the plant does not record its lag state)."""
    v_x, v_y, r = x[:, 0], x[:, 1], x[:, 2]
    period = float(t[1] - t[0]) if t.size > 1 else CAR.sample_period_s
    return mb.MultibodyRun(
        name=name,
        parameter_set=0,
        seed=seed,
        t=t,
        y=y,
        u=u,
        x_true=x,
        torque_nm=u[:, 0] + f[:, 0],
        steer_rad=u[:, 1] + f[:, 1],
        f=f,
        a_x=np.gradient(v_x, period) - r * v_y,
        a_y=np.gradient(v_y, period) + r * v_x,
    )


@dataclass(frozen=True)
class Calibrated:
    """The calibrated profile of the car, its calibration run, and the EKF's thresholds set from it."""

    report: CalibrationReport
    run: mb.MultibodyRun
    ekf_channels: dict[str, ChannelThresholds]
    ekf_alarms: AlarmThresholds


def calibrate_car() -> Calibrated:
    """Simulate the calibration drive with the project's plant, calibrate a profile from it, and set the EKF's
    thresholds from its estimates on the same drive (:func:`agv_fe.benchmarks.real_vehicle.ekf_thresholds`)."""
    record = simulate_plant([calibration_scenario()], substeps=CALIBRATION_SUBSTEPS)
    run = plant_run(
        record.t, record.x[:, 0], record.y[:, 0], record.u[:, 0], record.f[:, 0], "calibration", CALIBRATION_SEED
    )
    drive = Recording(t=run.t, y=run.y, u=run.u, name="calibration")
    report = calibrate_profile(
        [drive], base_params(), description="the detection benchmark's car, calibrated from its calibration drive"
    )
    ekf_channels, ekf_alarms = rv.ekf_thresholds(report, run)
    return Calibrated(report, run, ekf_channels, ekf_alarms)


def substep_check(calibrated: Calibrated, vehicles: int, duration_s: float) -> dict[str, Any]:
    """The fleet's RK4 substeps against the plant's default on the same random drives (gusts included, same
    sensor noise): the largest differences of the true state and of the observer's fault estimates."""
    gains = calibrated.report.gains
    planner = LateralPlanner.build(CAR, gains.bounds)
    scenarios = []
    for i in range(vehicles):
        rng = np.random.default_rng([FLEET_SEED + 1, i])
        plan = random_plan(planner, rng, duration_s, float(rng.uniform(*SPEED_RANGE_MPS)))
        scenarios.append(
            plan.scenario(f"substeps-{i}", duration_s, FLEET_SEED + 1 + i, (), segment_gusts(rng, duration_s))
        )
    fine = estimate(simulate_plant(scenarios, substeps=CALIBRATION_SUBSTEPS), observer_factory(gains))
    coarse = estimate(simulate_plant(scenarios, substeps=FLEET_SUBSTEPS), observer_factory(gains))
    state = np.abs(fine.x - coarse.x).max(axis=(0, 1))
    faults = np.abs(fine.f_hat - coarse.f_hat).max(axis=(0, 1))
    return {
        "vehicles": vehicles,
        "duration_s": duration_s,
        "substeps": [CALIBRATION_SUBSTEPS, FLEET_SUBSTEPS],
        "max_state_difference": {"v_x_mps": float(state[0]), "v_y_mps": float(state[1]), "r_radps": float(state[2])},
        "max_estimate_difference": {"torque": float(faults[0]), "steer": float(faults[1])},
    }


# --------------------------------------------------------------------------- the multi-body plant


def multibody_figures(
    parameter_sets: Sequence[int], drives: int, drive_s: float, workers: int, quick: bool
) -> list[dict[str, Any]]:
    """Per set: the calibration from ``mb.calibration_drive()`` (as the real_vehicle benchmark), then ``drives``
    random drives of ``drive_s`` through the calibrated observer and the EKF with the service's levels."""
    seeds = tuple(range(MB_SEED, MB_SEED + drives))
    plans = {
        s: rv.Plan.make((s,), quick, workers, healthy_seeds=seeds, healthy_duration_s=drive_s) for s in parameter_sets
    }
    jobs = [rv.calibration_job(s) for s in parameter_sets]
    jobs += [job for s in parameter_sets for job in rv.healthy_jobs(s, plans[s])]
    print(
        f"  multi-body: simulating {len(jobs)} drives of set(s) {', '.join(map(str, parameter_sets))} ...", flush=True
    )
    started = time.perf_counter()
    runs = mb.simulate_many(jobs, workers)
    simulated_s = time.perf_counter() - started
    results = []
    for i, s in enumerate(parameter_sets):
        cal_run = runs[i]
        healthy = runs[len(parameter_sets) + i * drives : len(parameter_sets) + (i + 1) * drives]
        print(f"  multi-body set {s}: calibrating ...", flush=True)
        try:
            report = rv.calibrate(s, cal_run)
        except SynthesisError as exc:  # the product's answer to this drive, reported
            results.append({"parameter_set": s, "refused": f"{type(exc).__name__}: {exc}"})
            continue
        _, ekf_alarms = rv.ekf_thresholds(report, cal_run)
        period = report.profile.params.sample_period_s
        warmup = report.profile.alarms.warmup_s
        hours = sum(max(len(run) * period - warmup, 0.0) for run in healthy) / 3600.0
        result: dict[str, Any] = {
            "parameter_set": s,
            "refused": None,
            "drives": len(healthy),
            "drive_s": drive_s,
            "hours_after_warmup": hours,
            "driving": rv.driving_figures(healthy),
            "simulation_wall_s": simulated_s,
        }
        for name, factory, alarms in (
            ("observer", observer_factory(report.gains), report.profile.alarms),
            ("EKF", ekf_factory(report.gains), ekf_alarms),
        ):
            figures = rv.healthy_figures(healthy, rv.estimate_runs(factory, healthy, alarms), alarms, period)
            result[name] = {
                "channels": {
                    c: _rates(figures["channels"][c]["warn_raised"], figures["channels"][c]["fault_raised"], hours)
                    | {
                        "warn_threshold": figures["channels"][c]["warn_threshold"],
                        "fault_threshold": figures["channels"][c]["fault_threshold"],
                        "held_peak_over_warn": figures["channels"][c]["held_peak_abs_estimate"]
                        / figures["channels"][c]["warn_threshold"],
                    }
                    for c in CHANNELS
                },
                "drives_with_alarm": figures["drives_with_alarm"],
                "events": figures["events"][:KEPT_EVENTS],
                "in_domain_share": figures["in_domain_share"],
            }
        results.append(result)
    return results


# --------------------------------------------------------------------------- rates and delays


def poisson_upper_95(count: int) -> float:
    """One-sided 95 % upper bound of a Poisson mean from ``count`` events (3.0 for none: the rule of three)."""
    return float(scipy.stats.chi2.ppf(0.95, 2 * (count + 1)) / 2.0)


def _rates(warn: int, fault: int, hours: float) -> dict[str, Any]:
    """Raised WARN and FAULT levels in ``hours`` of observed driving, per 1,000 h, with 95 % upper bounds."""
    per = 1000.0 / hours if hours > 0 else math.nan
    return {
        "warn_raised": int(warn),
        "fault_raised": int(fault),
        "hours": hours,
        "warn_per_1000_h": warn * per,
        "fault_per_1000_h": fault * per,
        "warn_upper95_per_1000_h": poisson_upper_95(int(warn)) * per,
        "fault_upper95_per_1000_h": poisson_upper_95(int(fault)) * per,
    }


def delay_stats(delays: Sequence[float | None]) -> dict[str, Any]:
    """Delays [s] of n runs (None: never within the run): p50 and p95 by nearest rank with the undetected runs
    ranked last (None when the rank falls on one), the worst detected delay and the share never detected."""
    n = len(delays)
    detected = np.sort(np.array([d for d in delays if d is not None], dtype=float))

    def rank(q: float) -> float | None:
        k = max(math.ceil(q * n), 1) - 1  # nearest rank, 0-based
        return float(detected[k]) if k < detected.size else None

    return {
        "runs": n,
        "p50_s": rank(0.5) if n else None,
        "p95_s": rank(0.95) if n else None,
        "worst_detected_s": float(detected[-1]) if detected.size else None,
        "never_share": (n - detected.size) / n if n else math.nan,
    }


# --------------------------------------------------------------------------- the rules, the processes


def cusum_rule(alarms: AlarmThresholds) -> Rule | None:
    """The service's CUSUM rule (``rule`` 'cusum', :mod:`service.fleet.cusum`) on the same thresholds and the
    calibrated block sigmas; None when the settings have no block sigmas."""
    try:
        settings = AlarmThresholds.model_validate(alarms.model_dump() | {"rule": "cusum"})
    except ValueError:
        return None
    return Rule("cusum", 1.0, settings)


def alpha_rules(alarms: AlarmThresholds) -> tuple[Rule, ...]:
    """The profile's effectiveness rule (``effectiveness_warn``, ``effectiveness_fault``, ``effectiveness_after_s``)."""
    return (Rule("default", 1.0, alarms),)


def stage_options(calibrated: Calibrated) -> EffectivenessOptions:
    """The profile's loss-of-effectiveness stage options (calibration measured its sigmas), enabled."""
    return calibrated.report.profile.effectiveness.model_copy(update={"enabled": True})


def rules_for(alarms: AlarmThresholds) -> tuple[Rule, ...]:
    """The default rule, the operating curve's scaled thresholds, and the CUSUM rule when there is one."""
    rules = rule_set(alarms)
    extra = cusum_rule(alarms)
    return tuple(rules + ([extra] if extra is not None else []))


_THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _map_in_processes(
    function: Callable[[Any], dict[str, Any]], jobs: Sequence[Any], workers: int
) -> list[dict[str, Any]]:
    """``function`` over ``jobs`` in up to ``workers`` spawned processes, each with single-threaded BLAS (the
    processes share the cores); results in job order. One worker runs them here."""
    if workers == 1 or len(jobs) <= 1:
        return [function(job) for job in jobs]
    saved = {name: os.environ.get(name) for name in _THREAD_VARIABLES}
    os.environ.update(dict.fromkeys(_THREAD_VARIABLES, "1"))
    try:
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=min(workers, len(jobs)), mp_context=context) as pool:
            return list(pool.map(function, jobs))
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def _split(items: Sequence[Any], parts: int) -> list[tuple[Any, ...]]:
    """``items`` dealt into ``parts`` interleaved shares (empty shares dropped)."""
    return [tuple(items[i::parts]) for i in range(parts) if items[i::parts]]


# --------------------------------------------------------------------------- healthy fleet figures


def healthy_fleet(
    calibrated: Calibrated, vehicles: int, duration_s: float, segment_s: float, ekf_share: float, workers: int
) -> dict[str, Any]:
    """Run the healthy fleet in ``workers`` processes and merge their figures."""
    report = calibrated.report
    observer_rules = rules_for(report.profile.alarms)
    ekf_rules = rules_for(calibrated.ekf_alarms)
    jobs = [
        FleetJob(
            gains=report.gains,
            observer_rules=observer_rules,
            ekf_rules=ekf_rules,
            vehicles=share,
            n_ekf=round(ekf_share * len(share)),
            duration_s=duration_s,
            segment_s=segment_s,
            stage=stage_options(calibrated),
            alpha_rules=alpha_rules(report.profile.alarms),
        )
        for share in _split(list(range(vehicles)), workers)
    ]
    started = time.perf_counter()
    results = _map_in_processes(run_fleet_job, jobs, workers)
    wall = time.perf_counter() - started
    return merge_fleet(results, observer_rules, ekf_rules, wall, jobs[0].alpha_rules)


def merge_fleet(
    results: Sequence[dict[str, Any]],
    observer_rules: Sequence[Rule],
    ekf_rules: Sequence[Rule],
    wall_s: float,
    alpha_rule_set: Sequence[Rule] = (),
) -> dict[str, Any]:
    """The processes' figures as one fleet: per estimator and rule the raised levels per channel, rates per
    1,000 h of driving after the warm-up with 95 % upper bounds, alarms near gusts, the estimates' peaks and RMS
    (for the effectiveness rule, :data:`ALPHA`: of the loss 1 - alpha_hat; its alarms counted from the start,
    the rate over the same hours)."""
    period = CAR.sample_period_s
    driving = DrivingStats()
    for r in results:
        driving.merge(DrivingStats.from_dict(r["driving"]))
    observed_samples = sum(r["samples_per_vehicle"] - r["warmup_samples"] for r in results[:1])
    merged: dict[str, Any] = {
        "vehicles": sum(r["vehicles"] for r in results),
        "duration_s": results[0]["samples_per_vehicle"] * period,
        "warmup_s": results[0]["warmup_samples"] * period,
        "wall_s": wall_s,
        "process_wall_s": [r["wall_s"] for r in results],
        "driving": vars(driving) | {"seconds_above_5_mps2": driving.samples_above_5_mps2 * period},
    }
    estimators = [("observer", observer_rules, "vehicles"), ("EKF", ekf_rules, "ekf_vehicles")]
    if alpha_rule_set:
        estimators.append((ALPHA, alpha_rule_set, "vehicles"))
    for name, rules, size in estimators:
        vehicles = sum(r[size] for r in results)
        hours = vehicles * observed_samples * period / 3600.0
        tallies = [r[name] for r in results if r[size]]
        samples_after = sum(t["samples_after_warmup"] for t in tallies)
        squares = np.sum([t["sum_squares"] for t in tallies], axis=0) if tallies else np.zeros(2)
        peaks = np.max([t["peak_abs"] for t in tallies], axis=0) if tallies else np.zeros(2)
        figures: dict[str, Any] = {
            "vehicles": vehicles,
            "hours": hours,
            "rules": {},
            "peak_abs_estimate": peaks.tolist(),
            "rms_estimate": np.sqrt(squares / max(samples_after, 1)).tolist(),
            "in_domain_share": sum(t["in_domain"] for t in tallies) / max(sum(t["samples"] for t in tallies), 1),
            "out_of_domain_samples": sum(t["samples"] - t["in_domain"] for t in tallies),
            "uncertified_samples": sum(t.get("uncertified", 0) for t in tallies),
            "non_finite_samples": sum(t["non_finite"] for t in tallies),
        }
        for rule in rules:
            counts = [t["rules"][rule.key] for t in tallies]
            channels = {}
            for c, channel in enumerate(CHANNELS):
                warn = sum(x["warn_raised"][c] for x in counts)
                fault = sum(x["fault_raised"][c] for x in counts)
                channels[channel] = _rates(warn, fault, hours) | {
                    "warn_raised_near_gust": sum(x["warn_raised_near_gust"][c] for x in counts),
                    "fault_raised_near_gust": sum(x["fault_raised_near_gust"][c] for x in counts),
                    "vehicles_with_warn": sum(x["vehicles_with_warn"][c] for x in counts),
                    "warn_threshold": _threshold(rule.alarms, channel, name == ALPHA)[0],
                    "fault_threshold": _threshold(rule.alarms, channel, name == ALPHA)[1],
                }
            figures["rules"][rule.key] = {"factor": rule.factor, "channels": channels}
        events = sorted((e for t in tallies for e in t["events"]), key=lambda e: (e["t_s"], e["vehicle"]))
        figures["events"] = events[:KEPT_EVENTS]
        detections = [t["jump_detections"] for t in tallies if t.get("jump_detections")]
        if detections:  # the effectiveness stage's bias-jump test (docs/math.md section 14), per channel
            figures["jump_detections"] = np.sum(detections, axis=0).tolist()
        merged[name] = figures
    return merged


def _threshold(alarms: AlarmThresholds, channel: str, effectiveness: bool = False) -> tuple[float, float]:
    """A channel's WARN and FAULT thresholds [N m] or [rad]; the effectiveness rule's alpha thresholds [-]."""
    if effectiveness:
        return alarms.effectiveness_warn, alarms.effectiveness_fault
    return rv.channel_thresholds(alarms)[channel]


# --------------------------------------------------------------------------- detection figures


def fault_runs(
    calibrated: Calibrated,
    vehicles_per_case: int,
    duration_s: float,
    workers: int,
    kinds: Sequence[FaultKind] = FAULT_KINDS,
    with_ekf: bool = True,
) -> dict[str, Any]:
    """The fault cases of ``kinds``: their runs through both estimators (the EKF only ``with_ekf``) and every
    rule, in ``workers`` processes."""
    report = calibrated.report
    observer_rules = rules_for(report.profile.alarms)
    ekf_rules = rules_for(calibrated.ekf_alarms)
    cases = [i for i, case in enumerate(FAULT_CASES) if case.kind in kinds]
    runs = [(i, v) for i in cases for v in range(vehicles_per_case)]
    alpha = alpha_rules(report.profile.alarms)
    jobs = [
        FaultJob(
            report.gains,
            observer_rules,
            ekf_rules,
            share,
            report.nominal_torque_nm,
            duration_s,
            stage_options(calibrated),
            alpha,
            with_ekf=with_ekf,
        )
        for share in _split(runs, workers)
    ]
    started = time.perf_counter()
    results = _map_in_processes(run_fault_job, jobs, workers)
    wall = time.perf_counter() - started
    return summarise_faults(results, observer_rules, ekf_rules, report.nominal_torque_nm, wall, alpha)


def summarise_faults(
    results: Sequence[dict[str, Any]],
    observer_rules: Sequence[Rule],
    ekf_rules: Sequence[Rule],
    nominal_torque_nm: float,
    wall_s: float,
    alpha_rule_set: Sequence[Rule] = (),
) -> dict[str, Any]:
    """Per case, estimator and rule: delay statistics to WARN and FAULT, runs with the faulty channel at WARN
    before the onset, and the other channel's raised levels."""
    per_run: dict[tuple[int, int], dict[str, Any]] = {}
    for r in results:
        for j, (case, vehicle) in enumerate(r["runs"]):
            entry: dict[str, Any] = {"onset_s": r["onset_s"][j]}
            for name in [*ESTIMATOR_LABELS, *([ALPHA] if alpha_rule_set else [])]:
                entry[name] = {key: {field: values[j] for field, values in v.items()} for key, v in r[name].items()}
            per_run[(case, vehicle)] = entry
    cases = {}
    for i, case in enumerate(FAULT_CASES):
        runs = [per_run[key] for key in sorted(per_run) if key[0] == i]
        if not runs:  # a case not run (the effectiveness part runs the losses only)
            continue
        entry = {
            "channel": case.channel,
            "kind": case.kind,
            "size": case.size,
            "magnitude": case.magnitude(nominal_torque_nm),
            "label": case.label(nominal_torque_nm),
            "runs": len(runs),
            "onset_range_s": [min(r["onset_s"] for r in runs), max(r["onset_s"] for r in runs)] if runs else None,
        }
        estimators = [("observer", observer_rules), ("EKF", ekf_rules)]
        for name, rules in estimators + ([(ALPHA, alpha_rule_set)] if alpha_rule_set else []):
            entry[name] = {}
            for rule in rules:
                rows = [r[name][rule.key] for r in runs]
                entry[name][rule.key] = {
                    "warn": delay_stats([x["warn_delay_s"] for x in rows]),
                    "fault": delay_stats([x["fault_delay_s"] for x in rows]),
                    "warn_before_onset": sum(bool(x["before_onset"]) for x in rows),
                    "other_warn_raised": sum(int(x["other_warn_raised"]) for x in rows),
                    "other_fault_raised": sum(int(x["other_fault_raised"]) for x in rows),
                    "runs_with_other_alarm": sum(int(x["other_warn_raised"]) > 0 for x in rows),
                }
        cases[case.key] = entry
    return {"cases": cases, "wall_s": wall_s}


def operating_curve(healthy: dict[str, Any], faults: dict[str, Any]) -> dict[str, Any]:
    """Per estimator and channel, for every threshold factor: false WARN (and FAULT) per 1,000 h on the
    healthy fleet against the p95 WARN delay of a 10 % bias on that channel."""
    curve: dict[str, Any] = {}
    for name in ESTIMATOR_LABELS:
        curve[name] = {}
        for channel in CHANNELS:
            bias = faults["cases"][f"{channel}_bias_10"][name]
            points = []
            for key, rule in healthy[name]["rules"].items():
                if key == "cusum":
                    continue
                rates = rule["channels"][channel]
                points.append(
                    {
                        "factor": rule["factor"],
                        "warn_threshold": rates["warn_threshold"],
                        "warn_per_1000_h": rates["warn_per_1000_h"],
                        "warn_raised": rates["warn_raised"],
                        "fault_per_1000_h": rates["fault_per_1000_h"],
                        "warn_upper95_per_1000_h": rates["warn_upper95_per_1000_h"],
                        "bias_p95_warn_s": bias[key]["warn"]["p95_s"],
                        "bias_never_share": bias[key]["warn"]["never_share"],
                    }
                )
            curve[name][channel] = sorted(points, key=lambda p: p["factor"])
    return curve


def must_show(healthy: dict[str, Any], faults: dict[str, Any]) -> list[dict[str, Any]]:
    """The two targets, measured for the observer (judged) and shown for the EKF (and the CUSUM rule)."""
    lines = []
    rule_keys = ["default"] + (["cusum"] if "cusum" in healthy["observer"]["rules"] else [])
    for name in ESTIMATOR_LABELS:
        for key in rule_keys:
            channels = healthy[name]["rules"][key]["channels"]
            passed = all(
                channels[c]["warn_per_1000_h"] <= FALSE_WARN_PER_1000_H and channels[c]["fault_raised"] == 0
                for c in CHANNELS
            )
            figure = "; ".join(
                f"{SYMBOLS[c]} {channels[c]['warn_raised']} WARN / {channels[c]['fault_raised']} FAULT in "
                f"{_hours(channels[c]['hours'])} h = {channels[c]['warn_per_1000_h']:.3g} / "
                f"{channels[c]['fault_per_1000_h']:.3g} per 1,000 h (95 % bound "
                f"{channels[c]['warn_upper95_per_1000_h']:.3g}"
                f" / {channels[c]['fault_upper95_per_1000_h']:.3g})"
                + (
                    f", {channels[c]['warn_raised_near_gust']} WARN within {GUST_WINDOW_S:g} s of a gust"
                    if channels[c]["warn_raised"]
                    else ""
                )
                for c in CHANNELS
            )
            lines.append(
                {
                    "estimator": name,
                    "rule": key,
                    "target": f"at most {FALSE_WARN_PER_1000_H:g} false WARN per 1,000 vehicle-hours on each channel, "
                    "none at FAULT (calibrated profile)",
                    "figure": figure,
                    "passed": passed,
                    "judged": name == "observer" and key == "default",
                }
            )
        for key in rule_keys:
            stats = {c: faults["cases"][f"{c}_bias_10"][name][key]["warn"] for c in CHANNELS}
            passed = all(s["p95_s"] is not None and s["p95_s"] <= BIAS_P95_WARN_S for s in stats.values())
            figure = "; ".join(
                f"{SYMBOLS[c]}: p95 {_delay(s['p95_s'])} s (p50 {_delay(s['p50_s'])}, worst "
                f"{_delay(s['worst_detected_s'])}, "
                f"never {100 * s['never_share']:.0f} %, {s['runs']} runs)"
                for c, s in stats.items()
            )
            lines.append(
                {
                    "estimator": name,
                    "rule": key,
                    "target": f"a 10 % bias caught at WARN with p95 delay <= {BIAS_P95_WARN_S:g} s",
                    "figure": figure,
                    "passed": passed,
                    "judged": name == "observer" and key == "default",
                }
            )
    # the false-alarm target first, the judged row first within each
    return sorted(lines, key=lambda line: (not line["target"].startswith("at most"), not line["judged"]))


def _delay(value: float | None) -> str:
    return "never" if value is None else f"{value:.2f}"


def _hours(value: float) -> str:
    return f"{value:,.0f}" if value >= 100 else f"{value:.3g}"


# --------------------------------------------------------------------------- the run


DEFAULT_PARAMETER_SETS = rv.DEFAULT_PARAMETER_SETS


@dataclass(frozen=True)
class DetectionPlan:
    """The sizes of one run, resolved from the options of :func:`run`."""

    sets: tuple[int, ...]
    quick: bool
    workers: int
    vehicles: int
    duration_s: float
    fault_s: float
    segment_s: float
    per_case: int
    mb_drives: int
    mb_drive_s: float
    ekf_share: float


def run(
    out_dir: Path,
    parameter_sets: Sequence[int] = DEFAULT_PARAMETER_SETS,
    quick: bool = False,
    workers: int = WORKERS,
    healthy_vehicles: int | None = None,
    healthy_duration_s: float | None = None,
    vehicles_per_case: int | None = None,
    multibody_drives: int | None = None,
    multibody_drive_s: float | None = None,
    ekf_share: float = EKF_SHARE,
) -> Path:
    """Run the benchmark; write detection.md, detection.json and detection.png to ``out_dir``.

    ``quick``: a few vehicle-minutes of healthy driving, QUICK_VEHICLES_PER_CASE fault runs per case and short
    multi-body drives (for tests). ``parameter_sets``: the multi-body sets (any CommonRoad set with multi-body
    data; empty: no multi-body section). The other options replace the plan's sizes; ``ekf_share`` of the
    healthy vehicles also run through the EKF.
    """
    duration = healthy_duration_s or (QUICK_HEALTHY_DURATION_S if quick else HEALTHY_DURATION_S)
    plan = DetectionPlan(
        sets=tuple(int(s) for s in parameter_sets),
        quick=quick,
        workers=workers,
        vehicles=healthy_vehicles or (QUICK_HEALTHY_VEHICLES if quick else HEALTHY_VEHICLES),
        duration_s=duration,
        fault_s=QUICK_FAULT_RUN_S if quick else FAULT_RUN_S,
        segment_s=min(QUICK_SEGMENT_S if quick else SEGMENT_S, duration),
        per_case=vehicles_per_case or (QUICK_VEHICLES_PER_CASE if quick else VEHICLES_PER_CASE),
        mb_drives=multibody_drives or (QUICK_MB_DRIVES if quick else MB_DRIVES),
        mb_drive_s=multibody_drive_s or (QUICK_MB_DRIVE_S if quick else MB_DRIVE_S),
        ekf_share=ekf_share,
    )
    if plan.vehicles < 1 or plan.per_case < 1 or plan.mb_drives < 1 or workers < 1 or not 0.0 <= ekf_share <= 1.0:
        raise ValueError(
            f"vehicles, vehicles_per_case, multibody_drives and workers must be >= 1 and ekf_share in [0, 1], got "
            f"{plan.vehicles}, {plan.per_case}, {plan.mb_drives}, {workers}, {ekf_share}"
        )
    if len(set(plan.sets)) != len(plan.sets):
        raise ValueError(f"parameter_sets must be distinct set ids, got {parameter_sets!r}")
    document = measure(plan)
    out_dir.mkdir(parents=True, exist_ok=True)
    plot_operating_curve(document["operating_curve"], out_dir / "detection.png", plan.fault_s - ONSET_RANGE_S[1])
    (out_dir / "detection.json").write_text(json.dumps(rv._clean(document), indent=1) + "\n")
    path = out_dir / "detection.md"
    path.write_text(render(document))
    return path


def measure(plan: DetectionPlan) -> dict[str, Any]:
    """Calibrate the car, run the healthy fleet, the fault runs and the multi-body drives: the run's document
    (what detection.json holds and :func:`render` reads)."""
    started = time.perf_counter()
    timings: dict[str, float] = {}
    print("  calibrating the car from its two-minute drive ...", flush=True)
    calibrated = calibrate_car()
    timings["calibration_s"] = time.perf_counter() - started
    mark = time.perf_counter()
    check = substep_check(calibrated, 2 if plan.quick else 20, 10.0 if plan.quick else 60.0)
    timings["substep_check_s"] = time.perf_counter() - mark
    print(
        f"  healthy fleet: {plan.vehicles} vehicles x {plan.duration_s / 60:.0f} min in {plan.workers} processes ...",
        flush=True,
    )
    mark = time.perf_counter()
    healthy = healthy_fleet(calibrated, plan.vehicles, plan.duration_s, plan.segment_s, plan.ekf_share, plan.workers)
    timings["healthy_fleet_s"] = time.perf_counter() - mark
    print(f"  fault runs: {plan.per_case} per case, {len(FAULT_CASES)} cases ...", flush=True)
    mark = time.perf_counter()
    faults = fault_runs(calibrated, plan.per_case, plan.fault_s, plan.workers)
    timings["fault_runs_s"] = time.perf_counter() - mark
    mark = time.perf_counter()
    multibody = (
        multibody_figures(plan.sets, plan.mb_drives, plan.mb_drive_s, plan.workers, plan.quick) if plan.sets else []
    )
    timings["multibody_s"] = time.perf_counter() - mark
    document: dict[str, Any] = {
        "benchmark": "detection",
        "plan": _plan_document(plan, calibrated, "cusum" in healthy["observer"]["rules"]),
        "calibration": calibration_figures(calibrated),
        "substep_check": check,
        "healthy": healthy,
        "faults": faults,
        "operating_curve": operating_curve(healthy, faults),
        "multibody": multibody,
        "uncommitted_files": rv.uncommitted_files(),
    }
    document["must_show"] = must_show(healthy, faults)
    timings["total_s"] = time.perf_counter() - started
    document["timings"] = timings
    return document


#: The effectiveness part (:func:`run_effectiveness`): healthy vehicle-hours by default, each vehicle driving
#: EFFECTIVENESS_DRIVE_S (two segments); the fault runs are the losses of effectiveness only, without the EKF.
EFFECTIVENESS_HOURS = 100.0
EFFECTIVENESS_DRIVE_S = 2 * SEGMENT_S


def run_effectiveness(
    out_dir: Path,
    vehicle_hours: float = EFFECTIVENESS_HOURS,
    vehicles_per_case: int = VEHICLES_PER_CASE,
    workers: int = WORKERS,
    confidence_k: float | None = None,
) -> Path:
    """Only what the effectiveness alarm rule needs, at a chosen scale: the calibration, ``vehicle_hours`` of the
    healthy fleet (observer, stage and rules; no EKF) and ``vehicles_per_case`` runs of each loss of effectiveness;
    writes detection_effectiveness.json and .md to ``out_dir`` (detection.md is left as it is).
    ``confidence_k`` replaces the profile's ``effectiveness_confidence_k`` (0: the rule on alpha_hat itself)."""
    if vehicle_hours <= 0 or vehicles_per_case < 1 or workers < 1:
        raise ValueError(
            f"vehicle_hours must be > 0, vehicles_per_case and workers >= 1, got {vehicle_hours}, "
            f"{vehicles_per_case}, {workers}"
        )
    started = time.perf_counter()
    print("  calibrating the car from its two-minute drive ...", flush=True)
    calibrated = calibrate_car()
    if confidence_k is not None:
        calibrated = with_confidence_k(calibrated, confidence_k)
    warmup_s = calibrated.report.profile.alarms.warmup_s
    vehicles = max(1, math.ceil(vehicle_hours * 3600.0 / (EFFECTIVENESS_DRIVE_S - warmup_s)))
    print(f"  healthy fleet: {vehicles} vehicles x {EFFECTIVENESS_DRIVE_S / 60:.1f} min, no EKF ...", flush=True)
    healthy = healthy_fleet(calibrated, vehicles, EFFECTIVENESS_DRIVE_S, SEGMENT_S, 0.0, workers)
    print(f"  losses of effectiveness: {vehicles_per_case} runs per case ...", flush=True)
    faults = fault_runs(calibrated, vehicles_per_case, FAULT_RUN_S, workers, ("loss_of_effectiveness",), False)
    plan = DetectionPlan((), False, workers, vehicles, EFFECTIVENESS_DRIVE_S, FAULT_RUN_S, SEGMENT_S,
                         vehicles_per_case, 0, 0.0, 0.0)  # fmt: skip
    document = {
        "benchmark": "detection_effectiveness",
        "plan": _plan_document(plan, calibrated, False),
        "healthy": {"hours": healthy[ALPHA]["hours"], ALPHA: healthy[ALPHA], "wall_s": healthy["wall_s"]},
        "faults": {k: {"label": c["label"], "runs": c["runs"], ALPHA: c[ALPHA]} for k, c in faults["cases"].items()},
        "uncommitted_files": rv.uncommitted_files(),
        "total_s": time.perf_counter() - started,
    }
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "detection_effectiveness.json").write_text(json.dumps(rv._clean(document), indent=1) + "\n")
    path = out_dir / "detection_effectiveness.md"
    path.write_text(render_effectiveness(document))
    return path


def with_confidence_k(calibrated: Calibrated, k: float) -> Calibrated:
    """The calibrated car with the profile's ``effectiveness_confidence_k`` set to ``k`` (validated)."""
    profile = calibrated.report.profile
    alarms = AlarmThresholds.model_validate(profile.alarms.model_dump() | {"effectiveness_confidence_k": k})
    report = replace(calibrated.report, profile=profile.model_copy(update={"alarms": alarms}))
    return replace(calibrated, report=report)


def render_effectiveness(document: dict[str, Any]) -> str:
    """The effectiveness part's report: the rule, its false alarms on the healthy fleet, its delays on the losses."""
    figures = document["healthy"][ALPHA]["rules"]["default"]["channels"]
    lines = [
        report_header("Detection: the effectiveness alarm rule alone", "detection --detection-part effectiveness"),
        f"Rule: {_alpha_rule_text(document)}; {document['plan']['healthy']['vehicles']} healthy vehicles "
        f"x {document['plan']['healthy']['duration_s']:g} s ({_hours(document['healthy']['hours'])} vehicle-hours "
        f"after the warm-up), {document['plan']['faults']['vehicles_per_case']} runs per loss; "
        f"{document['total_s'] / 60:.1f} min.\n",
        "| channel | false WARN | per 1,000 h (95 % bound) | false FAULT | per 1,000 h | WARN within "
        f"{GUST_WINDOW_S:g} s of a gust | vehicles with a WARN |",
        "|---|---|---|---|---|---|---|",
    ]
    for channel in CHANNELS:
        c = figures[channel]
        lines.append(
            f"| {SYMBOLS[channel]} | {c['warn_raised']} | {c['warn_per_1000_h']:.3g} "
            f"({c['warn_upper95_per_1000_h']:.3g}) | {c['fault_raised']} | {c['fault_per_1000_h']:.3g} | "
            f"{c['warn_raised_near_gust']} | "
            f"{c['vehicles_with_warn']} |"
        )
    lines += [
        "",
        "| fault | rule | WARN p50 / p95 / worst [s] | never | FAULT p50 / p95 / worst [s] | never | WARN before "
        "onset | other channel WARN / FAULT (runs) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    lines += [_delay_row(case["label"], "alpha rule", case[ALPHA]["default"]) for case in document["faults"].values()]
    return "\n".join([*lines, *_jump_lines(document)]) + "\n"


def _jump_lines(document: dict[str, Any]) -> list[str]:
    """The stage's bias-jump test on the healthy fleet: its options and detections per vehicle-hour."""
    detections = document["healthy"][ALPHA].get("jump_detections")
    stage = document["plan"]["effectiveness"]["stage"]
    if detections is None or "steer_jump_rad" not in stage:
        return []
    hours = document["healthy"]["hours"]
    sizes = f"J {stage['torque_jump_nm']:g} N m / {stage['steer_jump_rad']:g} rad (0: no test)"
    design = 3600.0 / stage["jump_false_alarm_interval_s"]
    rates = " / ".join(f"{n / hours:.0f}" for n in detections)
    return [
        "",
        f"The stage's bias-jump test (docs/math.md section 14; {sizes}, window {stage['jump_window_s']:g} s, loss "
        f"prior {stage['jump_loss_prior']:g}) on the healthy fleet: {rates} detections per vehicle-hour T_f / delta_f "
        f"({' / '.join(str(n) for n in detections)}), designed for {design:g} per hour on white innovations.",
    ]


def _plan_document(plan: DetectionPlan, calibrated: Calibrated, cusum_rule: bool) -> dict[str, Any]:
    """The document's "plan": the run's sizes, the car, the noise, the fault cases, the rules."""
    return {
        "quick": plan.quick,
        "workers": plan.workers,
        "car": CAR.model_dump(mode="json"),
        "base": base_params(),
        "noise": {"vx_sigma_mps": NOISE.vx_sigma_mps, "r_sigma_radps": NOISE.r_sigma_radps},
        "calibration": {"duration_s": CALIBRATION_DURATION_S, "seed": CALIBRATION_SEED},
        "healthy": {
            "vehicles": plan.vehicles,
            "duration_s": plan.duration_s,
            "segment_s": plan.segment_s,
            "ekf_share": plan.ekf_share,
            "speed_range_mps": list(SPEED_RANGE_MPS),
            "max_lateral_accel_mps2": MAX_LATERAL_ACCEL_MPS2,
            "box_share": BOX_SHARE,
            "substeps": FLEET_SUBSTEPS,
        },
        "faults": {
            "vehicles_per_case": plan.per_case,
            "duration_s": plan.fault_s,
            "onset_range_s": list(ONSET_RANGE_S),
            "sizes": list(FAULT_SIZES),
            "nominal_torque_nm": calibrated.report.nominal_torque_nm,
            "nominal_steer_rad": NOMINAL_STEER_RAD,
            "sine_omega_radps": SINE_OMEGA_RADPS,
            "loss_rate_per_s": LOSS_RATE_PER_S,
            "steer_fault_speed_range_mps": list(STEER_FAULT_SPEED_RANGE_MPS),
            "loss_accel_mps2": LOSS_ACCEL_MPS2,
            "loss_speeds_mps": list(LOSS_SPEEDS_MPS),
            "loss_turn_speed_mps": list(LOSS_TURN_SPEED_MPS),
        },
        "threshold_factors": list(THRESHOLD_FACTORS),
        "multibody": {"parameter_sets": list(plan.sets), "drives": plan.mb_drives, "drive_s": plan.mb_drive_s},
        "cusum_rule": cusum_rule,
        "effectiveness": {
            "stage": stage_options(calibrated).model_dump(mode="json"),
            "warn_below": calibrated.report.profile.alarms.effectiveness_warn,
            "fault_below": calibrated.report.profile.alarms.effectiveness_fault,
            "after_s": calibrated.report.profile.alarms.effectiveness_after_s,
            "confidence_k": calibrated.report.profile.alarms.effectiveness_confidence_k,
        },
    }


def calibration_figures(calibrated: Calibrated) -> dict[str, Any]:
    """The identified parameters against the car's, the box, the thresholds of the observer and the EKF."""
    report = calibrated.report
    parameters = {
        name: {"value": e.value, "ci95": [e.low, e.high], "true": float(getattr(CAR, name))}
        for name, e in report.calibration.estimates.items()
    }
    return {
        "parameters": parameters,
        "bounds": report.profile.bounds.model_dump(mode="json"),
        "alarms": report.profile.alarms.model_dump(mode="json"),
        "ekf_alarms": calibrated.ekf_alarms.model_dump(mode="json"),
        "thresholds": {c: vars(t) for c, t in report.thresholds.items()},
        "ekf_thresholds": {c: vars(t) for c, t in calibrated.ekf_channels.items()},
        "nominal_torque_nm": report.nominal_torque_nm,
        "peak_lateral_accel_mps2": report.calibration.peak_lateral_accel_mps2,
        "decay_rate": report.gains.options.robust_decay_rate,
        "switched": report.gains.switched,
        "gain_version": report.gains.version,
        "warnings": list(report.warnings),
        "gust": {"force_n": report.gust_n, "duration_s": GUST_S},
    }


# --------------------------------------------------------------------------- the figure


def plot_operating_curve(curve: dict[str, Any], path: Path, never_s: float) -> None:
    """False WARN per 1,000 h against the p95 WARN delay of a 10 % bias, per channel; factor 1 marked; a p95
    that falls on an undetected run is drawn at ``never_s`` [s] (the shortest time after an onset)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5), constrained_layout=True)
    styles = {"observer": ("tab:blue", "o", 5), "EKF": ("tab:orange", "s", -11)}
    for ax, channel in zip(axes, CHANNELS, strict=True):
        xs: list[float] = []
        top = 1.0
        for name, (colour, marker, dy) in styles.items():
            points = curve[name][channel]
            x = [never_s if p["bias_p95_warn_s"] is None else p["bias_p95_warn_s"] for p in points]
            y = [p["warn_per_1000_h"] for p in points]
            upper = [p["warn_upper95_per_1000_h"] - p["warn_per_1000_h"] for p in points]
            xs += x
            top = max(top, *[a + b for a, b in zip(y, upper, strict=True)])
            ax.errorbar(
                x,
                y,
                yerr=[np.zeros(len(y)), upper],
                color=colour,
                marker=marker,
                capsize=2,
                label=f"{ESTIMATOR_LABELS[name]} (bars: 95 % upper bound)",
            )
            for p, xi, yi in zip(points, x, y, strict=True):
                ax.annotate(
                    f"x{p['factor']:g}", (xi, yi), textcoords="offset points", xytext=(4, dy), fontsize=7, color=colour
                )
                if p["factor"] == 1.0:
                    ax.plot([xi], [yi], marker="*", markersize=16, color=colour, markeredgecolor="black", zorder=5)
        low, high = min(xs), max(xs)
        pad = max(0.1 * (high - low), 0.02)
        ax.set_xlim(low - pad, high + 2 * pad)
        ax.set_yscale("symlog", linthresh=1.0)
        ax.set_ylim(0.0, 3.0 * top)
        ax.axhline(FALSE_WARN_PER_1000_H, color="grey", linestyle="--", linewidth=0.8, label="target: 1 per 1,000 h")
        if low - pad <= BIAS_P95_WARN_S <= high + 2 * pad:
            ax.axvline(BIAS_P95_WARN_S, color="grey", linestyle=":", linewidth=0.8, label="target: p95 1.5 s")
        ax.set_xlabel(f"p95 delay to WARN of a 10 % {SYMBOLS[channel]} bias [s] (target <= {BIAS_P95_WARN_S:g} s)")
        ax.set_ylabel("false WARN per 1,000 vehicle-hours")
        ax.set_title(f"{SYMBOLS[channel]}: both thresholds x factor (star: factor 1, the profile's)")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=7, loc="upper right")
    fig.savefig(path, dpi=110)
    plt.close(fig)


# --------------------------------------------------------------------------- the report


def render(document: dict[str, Any]) -> str:
    """The markdown report: the must-show lines and headline figures first, then the tables, then how."""
    plan, timings = document["plan"], document["timings"]
    lines = [
        report_header(
            "Detection at fleet scale: false alarms per 1,000 vehicle-hours and delay against fault size", "detection"
        ),
        f"{'Quick mode (a few vehicle-minutes; for tests). ' if plan['quick'] else ''}This run took "
        f"{timings['total_s'] / 60:.1f} min with {plan['workers']} processes: calibration "
        f"{timings['calibration_s']:.0f} s, healthy fleet {timings['healthy_fleet_s'] / 60:.1f} min, fault runs "
        f"{timings['fault_runs_s']:.0f} s, multi-body {timings['multibody_s'] / 60:.1f} min."
        + rv._uncommitted_note(document.get("uncommitted_files", []))
        + "\n",
    ]
    lines += _must_show_section(document)
    lines += _headline_section(document)
    lines += _calibration_section(document)
    lines += _healthy_section(document)
    lines += _multibody_section(document)
    lines += _delay_section(document)
    lines += _alpha_section(document)
    lines += _curve_section(document)
    lines += _how_measured(document)
    lines += ["", EARLIER_RUNS]
    return "\n".join(lines) + "\n"


def _fmt(value: float | None, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{value:.{digits}g}"


def _rule_label(name: str, key: str) -> str:
    if key == "default":
        return ESTIMATOR_LABELS[name]
    if key == "cusum":
        return f"{ESTIMATOR_LABELS[name]}, CUSUM rule"
    return f"{ESTIMATOR_LABELS[name]}, thresholds {key}"


def _main_rules(document: dict[str, Any]) -> list[str]:
    return ["default"] + (["cusum"] if document["plan"]["cusum_rule"] else [])


def _must_show_section(document: dict[str, Any]) -> list[str]:
    lines = [
        "## Must show\n",
        "Judged for the calibrated observer with the profile's alarm rule; the other rows are shown beside it. "
        "A rate is the count over the vehicle-hours after each estimator's warm-up; the 95 % bound is the "
        "one-sided Poisson upper bound of that count (3 / H for none in H hours).\n",
        "| target | estimator | measured | result |",
        "|---|---|---|---|",
    ]
    for line in document["must_show"]:
        verdict = "pass" if line["passed"] else "**FAIL**"
        if not line["judged"]:
            verdict = f"shown: {'pass' if line['passed'] else 'fail'}"
        lines.append(
            f"| {line['target']} | {_rule_label(line['estimator'], line['rule'])} | {line['figure']} | {verdict} |"
        )
    lines.append("")
    return lines


def _headline_section(document: dict[str, Any]) -> list[str]:
    healthy, faults = document["healthy"], document["faults"]["cases"]
    lines = [
        "## Current figures\n",
        "| estimator | channel | vehicle-hours | false WARN per 1,000 h (95 % bound) | false FAULT per 1,000 h "
        "(95 % bound) | of the WARN, near a gust | 10 % bias: p50 / p95 to WARN [s] | to FAULT [s] |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name in ESTIMATOR_LABELS:
        for key in _main_rules(document):
            for channel in CHANNELS:
                c = healthy[name]["rules"][key]["channels"][channel]
                bias = faults[f"{channel}_bias_10"][name][key]
                lines.append(
                    f"| {_rule_label(name, key)} | {SYMBOLS[channel]} | {_hours(c['hours'])} | "
                    f"{c['warn_per_1000_h']:.3g} ({c['warn_upper95_per_1000_h']:.3g}) | "
                    f"{c['fault_per_1000_h']:.3g} ({c['fault_upper95_per_1000_h']:.3g}) | "
                    f"{c['warn_raised_near_gust']} of {c['warn_raised']} | "
                    f"{_delay(bias['warn']['p50_s'])} / {_delay(bias['warn']['p95_s'])} | "
                    f"{_delay(bias['fault']['p50_s'])} / {_delay(bias['fault']['p95_s'])} |"
                )
    lines.append("")
    lines += _alpha_headline(document)
    for result in document["multibody"]:
        if result["refused"] is not None:
            lines.append(f"Multi-body set {result['parameter_set']}: calibration refused ({result['refused']}).")
            continue
        counts = "; ".join(
            f"{ESTIMATOR_LABELS[name]} "
            + ", ".join(
                f"{SYMBOLS[c]} {result[name]['channels'][c]['warn_raised']} WARN / "
                f"{result[name]['channels'][c]['fault_raised']} FAULT (rate at most "
                f"{result[name]['channels'][c]['warn_upper95_per_1000_h']:.3g} WARN per 1,000 h at 95 %)"
                for c in CHANNELS
            )
            for name in ESTIMATOR_LABELS
        )
        lines.append(
            f"Multi-body plant, set {result['parameter_set']}: {result['hours_after_warmup']:.2f} vehicle-hours: "
            f"{counts}."
        )
    lines.append("")
    return lines


def _alpha_rule_text(document: dict[str, Any]) -> str:
    rule = document["plan"]["effectiveness"]
    k = rule.get("confidence_k", 0.0)  # absent: a run before the confidence bound (alpha_hat itself)
    value = "alpha_hat" if not k else f"the upper bound alpha_hat + {k:g} sigma_alpha"
    return (
        f"{value} held below {rule['warn_below']:g} for {rule['after_s']:g} s raises WARN, below "
        f"{rule['fault_below']:g} FAULT"
    )


def _alpha_headline(document: dict[str, Any]) -> list[str]:
    """The effectiveness alarm rule's current figures: false alarms, and the losses it is for."""
    healthy, cases = document["healthy"][ALPHA], document["faults"]["cases"]
    sizes = [
        size
        for size in document["plan"]["faults"]["sizes"]
        if f"torque_loss_of_effectiveness_{round(100 * size)}" in cases
    ]
    lines = [
        f"Effectiveness alarm rule (the observer's estimates through the loss-of-effectiveness stage, "
        f"{_alpha_rule_text(document)}; section 'Loss of effectiveness: the alpha rule' below):\n",
        "| channel | vehicle-hours | false WARN per 1,000 h (95 % bound) | false FAULT per 1,000 h (95 % bound) | "
        "largest healthy loss 1 - alpha_hat | "
        + " | ".join(f"alpha {1 - size:g}: p50 / p95 to WARN [s], never" for size in sizes)
        + " |",
        "|---|---|---|---|---|" + "---|" * len(sizes),
    ]
    for c, channel in enumerate(CHANNELS):
        rates = healthy["rules"]["default"]["channels"][channel]
        delays = []
        for size in sizes:
            w = cases[f"{channel}_loss_of_effectiveness_{round(100 * size)}"][ALPHA]["default"]["warn"]
            delays.append(f"{_delay(w['p50_s'])} / {_delay(w['p95_s'])}, {100 * w['never_share']:.0f} %")
        lines.append(
            f"| {SYMBOLS[channel]} | {_hours(rates['hours'])} | {rates['warn_per_1000_h']:.3g} "
            f"({rates['warn_upper95_per_1000_h']:.3g}) | {rates['fault_per_1000_h']:.3g} "
            f"({rates['fault_upper95_per_1000_h']:.3g}) | {_fmt(healthy['peak_abs_estimate'][c])} | "
            + " | ".join(delays)
            + " |"
        )
    lines.append("")
    return lines


def _alpha_section(document: dict[str, Any]) -> list[str]:
    """Every fault run through the effectiveness rule, beside the threshold rule on the observer's estimates."""
    cases = document["faults"]["cases"]
    stage = document["plan"]["effectiveness"]["stage"]
    lines = [
        "## Loss of effectiveness: the alpha rule\n",
        "The same fault runs (section above), the observer's estimates also through the loss-of-effectiveness stage "
        f"(synth/effectiveness.py, the profile's options: sigma T_f {stage['torque_sigma_nm']:.3g} N m, delta_f "
        f"{stage['steer_sigma_rad']:.3g} rad, start after {stage['start_after_s']:g} s) and its alpha_hat through "
        f"the service's effectiveness levels ({_alpha_rule_text(document)}). A run counts as detected when the "
        "faulty channel's alpha level reaches WARN (FAULT); on a bias or a sine a detection by this rule is a "
        "fault taken for a loss. The stage tells a loss from a bias only by changes of the demand (docs/math.md "
        "section 14): the steering loss runs in a steady turn, whose demand is constant after its entry.\n",
        "| fault | rule | WARN p50 / p95 / worst [s] | never WARN | FAULT p50 / p95 / worst [s] | never FAULT "
        "| WARN before onset | other channel WARN / FAULT (runs) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for case in cases.values():
        for name, label in (("observer", ESTIMATOR_LABELS["observer"]), (ALPHA, ALPHA_LABEL)):
            if name == "observer" and case["kind"] != "loss_of_effectiveness":
                continue
            lines.append(_delay_row(case["label"], label, case[name]["default"]))
    lines.append("")
    return lines


def _delay_row(case_label: str, rule_label: str, e: dict[str, Any]) -> str:
    """A row of a detection-delay table: WARN and FAULT delays p50 / p95 / worst and never-detected share, WARN
    before the onset, the other channel's alarms."""
    w, f = e["warn"], e["fault"]
    return (
        f"| {case_label} | {rule_label} | {_delay(w['p50_s'])} / {_delay(w['p95_s'])} / "
        f"{_delay(w['worst_detected_s'])} | {100 * w['never_share']:.0f} % | {_delay(f['p50_s'])} / "
        f"{_delay(f['p95_s'])} / {_delay(f['worst_detected_s'])} | {100 * f['never_share']:.0f} % | "
        f"{e['warn_before_onset']} | {e['other_warn_raised']} / {e['other_fault_raised']} "
        f"({e['runs_with_other_alarm']}) |"
    )


def _calibration_section(document: dict[str, Any]) -> list[str]:
    cal, plan = document["calibration"], document["plan"]
    bounds = cal["bounds"]
    lines = [
        "## Calibrated profile\n",
        f"The car of the calibration tests (mass {plan['car']['mass_kg']:g} kg, m_eff "
        f"{plan['car']['effective_mass_kg']:g} kg, C_f / C_r {plan['car']['front_cornering_stiffness_npr']:g} / "
        f"{plan['car']['rear_cornering_stiffness_npr']:g} N/rad, drag, rolling resistance, cornering drag and a "
        f"{1000 * plan['car']['steer_time_constant_s']:g} ms steering lag) drove the two-minute calibration drive "
        "(speed changes between 8 and 24 m/s, turns both ways at 3 and 6 m/s^2, lane changes and slaloms; peak "
        f"|v_x r| {cal['peak_lateral_accel_mps2']:.1f} m/s^2) with the project's plant and sensor noise sigma v_x "
        f"{plan['noise']['vx_sigma_mps']:g} m/s, r {plan['noise']['r_sigma_radps']:g} rad/s; `calibrate_profile` "
        f"with the data sheet ({', '.join(f'{k} {v:g}' for k, v in plan['base'].items())}) gave:\n",
        "| parameter | identified | 95 % interval | true | error |",
        "|---|---|---|---|---|",
    ]
    for name, p in cal["parameters"].items():
        low, high = p["ci95"]
        error = p["value"] / p["true"] - 1.0 if p["true"] else math.nan
        lines.append(
            f"| {name} | {p['value']:.5g} | {low:.5g} to {high:.5g} | {p['true']:.5g} | {100 * error:+.2f} % |"
        )
    lines += [
        "",
        f"Operating box: v_x {bounds['vx_min_mps']:g} to {bounds['vx_max_mps']:g} m/s, |v_y| <= "
        f"{bounds['vy_max_mps']:g} "
        f"m/s, |r| <= {bounds['r_max_radps']:g} rad/s, |delta| <= {bounds['steer_max_rad']:g} rad. Design: decay rate "
        f"{cal['decay_rate']:g}{', switched gain sets' if cal['switched'] else ''}, gains {cal['gain_version']}. "
        f"Nominal drive torque {cal['nominal_torque_nm']:.1f} N m (m_eff R_w 2 m/s^2). Warnings: "
        f"{'; '.join(cal['warnings']) if cal['warnings'] else 'none'}.\n",
        "| thresholds | channel | healthy sigma | held peak | WARN | FAULT | set by |",
        "|---|---|---|---|---|---|---|",
    ]
    for who, table in (("calibrated observer", cal["thresholds"]), ("EKF", cal["ekf_thresholds"])):
        for channel in CHANNELS:
            t = table[channel]
            by = SET_BY[t["set_by"]].format(gust=_fmt(t["gust_peak"]))
            lines.append(
                f"| {who} | {SYMBOLS[channel]} [{UNITS[channel]}] | {_fmt(t['sigma'])} | {_fmt(t['healthy_peak'])} | "
                f"{_fmt(t['warn'])} | {_fmt(t['fault'])} | {by} |"
            )
    alarms = cal["alarms"]
    lines += [
        "",
        f"Alarm rule (both estimators): raised after {alarms['raise_after_s']:g} s at or above the threshold, cleared "
        f"after {alarms['clear_after_s']:g} s below {alarms['hysteresis']:g} x it, no fault alarms in the "
        f"{alarms['warmup_s']:g} s after an estimator starts.\n",
    ]
    return lines


def _healthy_section(document: dict[str, Any]) -> list[str]:
    healthy, plan = document["healthy"], document["plan"]
    d = healthy["driving"]
    check = document["substep_check"]
    lines = [
        "## Healthy fleet on the project's plant\n",
        f"{healthy['vehicles']:,} vehicles x {healthy['duration_s'] / 60:g} min of random driving (the first "
        f"{healthy['warmup_s']:g} s of each is the estimators' warm-up and not counted): speeds "
        f"{d['speed_min_mps']:.1f} to {d['speed_max_mps']:.1f} m/s, peak |v_x r| {d['peak_lateral_accel_mps2']:.1f} "
        f"m/s^2 (vehicle {d['peak_lateral_accel_at'][0]} at {d['peak_lateral_accel_at'][1]:.0f} s; "
        f"{d['seconds_above_5_mps2'] / 3600:.1f} vehicle-hours above 5 m/s^2), peak |r| "
        f"{d['peak_yaw_rate_radps']:.2f} rad/s, peak |v_y| {d['peak_lateral_speed_mps']:.2f} m/s; "
        f"{d['samples_outside_box'] * CAR.sample_period_s:.0f} vehicle-seconds with the true state outside the "
        f"calibrated box; gusts up to {d['peak_wind_n']:.0f} N "
        f"({d['samples_with_gust'] * CAR.sample_period_s / 3600:.0f} vehicle-hours in a gust). "
        f"The EKF ran on {100 * plan['healthy']['ekf_share']:g} % of the vehicles. Raised: a channel's level went "
        "from OK to WARN or higher, or to FAULT (service.fleet.alarms.FaultLevels). Near a gust: raised within "
        f"{GUST_WINDOW_S:g} s of a lateral wind force on that vehicle (counted in the totals too). Simulated and "
        f"estimated in {healthy['wall_s'] / 60:.1f} min.\n",
        "| estimator | channel | vehicle-hours | WARN / FAULT threshold | WARN raised | FAULT raised | WARN per "
        "1,000 h "
        "(95 % bound) | FAULT per 1,000 h (95 % bound) | WARN near a gust | vehicles with a WARN | peak abs estimate "
        "/ WARN | RMS estimate | premise out of domain [vehicle-s] |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name in ESTIMATOR_LABELS:
        figures = healthy[name]
        for key in _main_rules(document):
            for c, channel in enumerate(CHANNELS):
                r = figures["rules"][key]["channels"][channel]
                lines.append(
                    f"| {_rule_label(name, key)} | {SYMBOLS[channel]} [{UNITS[channel]}] | {_hours(r['hours'])} | "
                    f"{_fmt(r['warn_threshold'])} / {_fmt(r['fault_threshold'])} | {r['warn_raised']} | "
                    f"{r['fault_raised']} | "
                    f"{r['warn_per_1000_h']:.3g} ({r['warn_upper95_per_1000_h']:.3g}) | "
                    f"{r['fault_per_1000_h']:.3g} ({r['fault_upper95_per_1000_h']:.3g}) | "
                    f"{r['warn_raised_near_gust']} | "
                    f"{r['vehicles_with_warn']} | {figures['peak_abs_estimate'][c] / r['warn_threshold']:.2f} | "
                    f"{_fmt(figures['rms_estimate'][c])} | "
                    f"{figures['out_of_domain_samples'] * CAR.sample_period_s:.1f} |"
                )
    lines += ["", *_gust_note(document), ""]
    for name in ESTIMATOR_LABELS:
        events = healthy[name]["events"]
        if not events:
            continue
        lines += [
            f"The first alarms raised by the {ESTIMATOR_LABELS[name]} (of "
            f"{sum(healthy[name]['rules']['default']['channels'][c]['warn_raised'] for c in CHANNELS)} WARN):\n",
            "| vehicle | t [s] | channel | level | estimate | v_x [m/s] | v_x r [m/s^2] | F_w at the raise [N] | "
            "near a gust |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        lines += [
            f"| {e['vehicle']} | {e['t_s']:.2f} | {SYMBOLS[e['channel']]} | {e['level']} | {_fmt(e['estimate'])} | "
            f"{e['speed_mps']:.1f} | {e['lateral_accel_mps2']:+.2f} | {e['wind_n']:+.0f} | "
            f"{'yes' if e['near_gust'] else 'no'} |"
            for e in events[:LISTED_EVENTS]
        ]
        lines.append("")
    diff = check["max_estimate_difference"]
    state = check["max_state_difference"]
    lines.append(
        f"RK4 substeps: the fleet and fault runs integrate with {check['substeps'][1]} substeps per 10 ms sample "
        f"instead of the plant's default {check['substeps'][0]} (five times faster). On {check['vehicles']} random "
        f"drives of {check['duration_s']:g} s with gusts and the same sensor noise the largest differences were v_x "
        f"{state['v_x_mps']:.1e} m/s, v_y {state['v_y_mps']:.1e} m/s, r {state['r_radps']:.1e} rad/s, and in the "
        f"observer's estimates T_f {diff['torque']:.1e} N m, delta_f {diff['steer']:.1e} rad (WARN: "
        f"{_fmt(document['calibration']['alarms']['torque_warn_nm'])} N m, "
        f"{_fmt(document['calibration']['alarms']['steer_warn_rad'])} rad).\n"
    )
    return lines


def _gust_note(document: dict[str, Any]) -> list[str]:
    """What the gusts did: the alarms away from them, and the steering threshold as a yaw moment."""
    healthy = document["healthy"]
    cal = document["calibration"]
    lines = []
    for name in ESTIMATOR_LABELS:
        for channel in CHANNELS:
            c = healthy[name]["rules"]["default"]["channels"][channel]
            if not c["warn_raised"]:
                continue
            away = c["warn_raised"] - c["warn_raised_near_gust"]
            rates = _rates(away, 0, c["hours"])
            lines.append(
                f"{ESTIMATOR_LABELS[name]}, {SYMBOLS[channel]}: {c['warn_raised_near_gust']} of the "
                f"{c['warn_raised']} WARN were raised within {GUST_WINDOW_S:g} s of a gust; away from gusts "
                f"{away} in {_hours(c['hours'])} h ({rates['warn_per_1000_h']:.3g} per 1,000 h, 95 % bound "
                f"{rates['warn_upper95_per_1000_h']:.3g})."
            )
    if not lines:
        return []
    steer = cal["thresholds"]["steer"]
    gust = cal["gust"]
    lines.append(
        "In the model a gust F_w acts on the yaw rate only (dr/dt gains F_w / I_z: F_w in N on a 1 m arm), a "
        "steering fault through the front tyres; with v_x and r measured, a gust that lasts shows on the steering "
        "channel as the steering fault that turns the car as much. Calibration states the gust a healthy vehicle "
        f"must ride through ({gust['force_n']:g} N for {gust['duration_s']:g} s, `--gust`) and keeps WARN "
        f"{PEAK_MARGIN:g} times above what the observer held in it on the identified model: held "
        f"{_fmt(steer['gust_peak'])} rad, WARN {_fmt(steer['warn'])} rad (set by: {steer['set_by']}); so a gust of "
        f"about {gust['force_n'] * steer['warn'] / max(steer['gust_peak'], 1e-12):.0f} N held for the persistence "
        "time reaches WARN. "
        "The operating curve below shows what another steering threshold costs in delay."
    )
    return lines


def _multibody_section(document: dict[str, Any]) -> list[str]:
    results = document["multibody"]
    lines = ["## Healthy driving on the multi-body plant\n"]
    if not results:
        return [*lines, "Not run (no parameter set given).\n"]
    lines += [
        "CommonRoad's multi-body vehicle (edge_client/multibody.py), which the estimator was not derived from. Per "
        "set its own calibration from `mb.calibration_drive()` and thresholds, as in the real_vehicle benchmark; "
        f"random drives (multibody.random_drive, up to {rv.MAX_LATERAL_ACCEL_MPS2:g} m/s^2). As many drives as "
        "fit in about three minutes of simulation on two cores. With k alarms in H hours the rate is at most the "
        "bound in the table with 95 % confidence (3 / H for none).\n",
        "| set | vehicle-hours | estimator | channel | WARN / FAULT threshold | WARN raised | FAULT raised "
        "| WARN per 1,000 h, 95 % bound | FAULT per 1,000 h, 95 % bound | held peak / WARN | drives with an alarm |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for result in results:
        if result["refused"] is not None:
            reason = str(result["refused"]).replace("|", "/")
            lines.append(
                f"| {result['parameter_set']} | - | calibration refused: {reason} | - | - | - | - | - | - | - | - |"
            )
            continue
        for name in ESTIMATOR_LABELS:
            for channel in CHANNELS:
                c = result[name]["channels"][channel]
                lines.append(
                    f"| {result['parameter_set']} | {result['hours_after_warmup']:.2f} | {ESTIMATOR_LABELS[name]} | "
                    f"{SYMBOLS[channel]} | {_fmt(c['warn_threshold'])} / {_fmt(c['fault_threshold'])} | "
                    f"{c['warn_raised']} | {c['fault_raised']} | {c['warn_per_1000_h']:.3g}, "
                    f"{c['warn_upper95_per_1000_h']:.3g} | "
                    f"{c['fault_per_1000_h']:.3g}, {c['fault_upper95_per_1000_h']:.3g} | "
                    f"{c['held_peak_over_warn']:.2f} | "
                    f"{len(result[name]['drives_with_alarm'])} of {result['drives']} |"
                )
    lines.append("")
    for result in results:
        if result["refused"] is None:
            d = result["driving"]
            lines.append(
                f"Set {result['parameter_set']}: {result['drives']} drives of {result['drive_s']:g} s, speeds "
                f"{d['speed_range_mps'][0]:.1f} to {d['speed_range_mps'][1]:.1f} m/s, peak |a_y| "
                f"{d['peak_lateral_accel_mps2']:.1f} m/s^2 ({d['seconds_above_5_mps2']:.0f} s above 5 m/s^2), "
                "premise in "
                f"domain {100 * result['observer']['in_domain_share']:.1f} %; simulated in "
                f"{result['simulation_wall_s'] / 60:.1f} min (both sets together)."
            )
    lines.append(f"\n{rv._set_two_note(document['plan']['multibody']['parameter_sets'])}\n")
    return lines


def _delay_section(document: dict[str, Any]) -> list[str]:
    plan = document["plan"]["faults"]
    cases = document["faults"]["cases"]
    lines = [
        "## Detection delay against fault size\n",
        f"{plan['vehicles_per_case']} runs per fault, {plan['duration_s']:g} s each, onset uniform in "
        f"{plan['onset_range_s'][0]:g} to {plan['onset_range_s'][1]:g} s (after the "
        f"{document['calibration']['alarms']['warmup_s']:g} s "
        f"warm-up), sign random. Sizes: torque as a share of the nominal drive torque "
        f"({plan['nominal_torque_nm']:.1f} N m), steering of {plan['nominal_steer_rad']:g} rad (so 10 % is "
        f"{0.1 * plan['nominal_steer_rad']:g} rad); a loss of effectiveness steps alpha to 1 - size at "
        f"{plan['loss_rate_per_s']:g} /s. Delay: from the onset to the first sample at which the faulty channel's "
        "level is WARN (or FAULT) or higher; p50 and p95 by nearest rank with the runs not detected within the run "
        "ranked last ('never' when the rank falls on one); worst: the largest detected delay. Before onset: runs "
        "whose faulty channel was at WARN between the warm-up and the onset. Other channel: WARN / FAULT raised on "
        "the healthy channel over the run (runs with one).\n",
        "| fault | estimator | WARN p50 / p95 / worst [s] | never WARN | FAULT p50 / p95 / worst [s] | never FAULT "
        "| WARN before onset | other channel WARN / FAULT (runs) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for key, case in cases.items():
        del key
        for name in ESTIMATOR_LABELS:
            for rule in _main_rules(document):
                lines.append(_delay_row(case["label"], _rule_label(name, rule), case[name][rule]))
    lines.append("")
    return lines


def _curve_section(document: dict[str, Any]) -> list[str]:
    curve = document["operating_curve"]
    lines = [
        "## Operating curve\n",
        "Both channels' WARN and FAULT thresholds multiplied by a factor (1: the calibrated profile's), the same "
        "estimates through the service's levels again: false WARN per 1,000 h on the healthy fleet against the p95 "
        "delay to WARN of a 10 % bias on that channel (the fault runs above).\n",
        "![False WARN per 1,000 vehicle-hours against the p95 WARN delay of a 10 % bias](detection.png)\n",
        "| estimator | channel | factor | WARN threshold | false WARN per 1,000 h (95 % bound) | false FAULT per "
        "1,000 h "
        "| 10 % bias: p95 to WARN [s], never |",
        "|---|---|---|---|---|---|---|",
    ]
    for name in ESTIMATOR_LABELS:
        for channel in CHANNELS:
            for p in curve[name][channel]:
                lines.append(
                    f"| {ESTIMATOR_LABELS[name]} | {SYMBOLS[channel]} | "
                    f"{p['factor']:g}{' (profile)' if p['factor'] == 1.0 else ''} | "
                    f"{_fmt(p['warn_threshold'])} | {p['warn_per_1000_h']:.3g} ({p['warn_upper95_per_1000_h']:.3g}) | "
                    f"{p['fault_per_1000_h']:.3g} | {_delay(p['bias_p95_warn_s'])}, "
                    f"{100 * p['bias_never_share']:.0f} % |"
                )
    lines.append("")
    return lines


def _how_measured(document: dict[str, Any]) -> list[str]:
    plan = document["plan"]
    h, f = plan["healthy"], plan["faults"]
    cusum = (
        "The CUSUM rows run the same estimates through the service's CUSUM rule (AlarmThresholds.rule 'cusum', "
        "service.fleet.cusum: Page's two-sided CUSUM on 0.1 s block means normalised by the calibration drive's "
        "block sigma, each level tuned for a shift of its threshold, h from the in-control run length of one "
        "false alarm per 1,000 h on Gaussian block means)."
        if plan["cusum_rule"]
        else "The profile had no block sigmas, so there are no CUSUM rows."
    )
    return [
        "## How it was measured\n",
        "Command: `agv-fe bench --only detection` (`make bench` runs it with the others; `run(out_dir, quick=True)` "
        "for a few vehicle-minutes). Plant: edge_client.plant.PlantSimulator (the 2-DOF model, RK4, steering lag), "
        "vectorised over the vehicles, open-loop steering and a speed-tracking driver, sensor noise sigma v_x "
        f"{plan['noise']['vx_sigma_mps']:g} m/s, r {plan['noise']['r_sigma_radps']:g} rad/s. Healthy fleet: "
        f"{h['vehicles']:,} vehicles x {h['duration_s'] / 60:g} min in {plan['workers']} processes, each "
        f"vehicle's drive in {h['segment_s']:g} s segments (a new random scenario per segment, the plant's state, "
        "the estimators and the alarm levels carried on, so every vehicle drives and is observed without a restart), "
        "every sample streamed through the calibrated observer (`FuzzyObserver`, the profile's gains), the augmented "
        "EKF (synth/ekf.py, same parameters, box and noise model) and `FaultLevels` once per threshold factor; no "
        "per-sample history is kept. Random driving: cruises, speed changes at 0.5-3 m/s^2 (braking 0.5-4) between "
        f"{h['speed_range_mps'][0]:g} and {h['speed_range_mps'][1]:g} m/s, turns (2-8 s held), lane changes and "
        "slaloms at constant speed with steering amplitudes uniform in 0.3-1 of a limit: the steady state within "
        f"{h['max_lateral_accel_mps2']:g} m/s^2 and within {100 * h['box_share']:g} % of the calibrated box's |r|, "
        "|v_y| "
        "and |delta| bounds; lateral wind gusts of 300-800 N, 0.5-2 s, every 15-40 s (edge_client.fleet_mix."
        f"random_gusts). Fault runs: {f['vehicles_per_case']} vehicles per (channel, kind, size), "
        f"{f['duration_s']:g} s, "
        "no gusts; biases and sines on random drives (steering faults at "
        f"{f['steer_fault_speed_range_mps'][0]:g}-{f['steer_fault_speed_range_mps'][1]:g} m/s with the manoeuvres' "
        "steering reduced by the fault: the open-loop steering does not correct a steering fault, so at high speed "
        "it alone would turn the car out of the box); a loss of effectiveness, f = (alpha - 1) u_d, shows only under "
        "a demand: the torque loss runs on straights accelerating and braking at "
        f"{f['loss_accel_mps2']:g} m/s^2 between {f['loss_speeds_mps'][0]:g} and {f['loss_speeds_mps'][1]:g} m/s "
        "(|T_d| about 0.75-1.15 of the nominal torque outside 0.5 s holds), the steering loss in a steady turn at "
        f"{f['loss_turn_speed_mps'][0]:g}-{f['loss_turn_speed_mps'][1]:g} m/s at the box's steering limit. "
        "The EKF's thresholds come from its own estimates on the calibration drive "
        "(real_vehicle.ekf_thresholds: the same false-alarm rate, persistence and required fault). Multi-body: "
        "real_vehicle's calibration, estimate_runs and healthy_figures. " + cusum + " The alpha rule: the "
        "observer's estimates of every healthy and faulty vehicle also go through synth.effectiveness."
        "EffectivenessEstimator (the profile's stage options, enabled) and its alpha_hat through service.fleet.alarms."
        "EffectivenessLevels, as the service runs them (no warm-up: the stage holds alpha_hat at 1 for its start "
        "delay; its false-alarm rate is over the same vehicle-hours as the observer's). Every figure is in "
        "detection.json beside this file.",
    ]


#: Earlier runs, kept below the current figures (their figures as measured then; the rules and code have changed).
EARLIER_RUNS = """## Earlier runs

* 2026-11-25 01:44 UTC, commit 8444a0b, 20.1 min with 2 processes (no effectiveness stage in the benchmark then):
  1,032 vehicle-hours of healthy driving; the calibrated observer 0 false WARN / 0 FAULT on both channels (95 %
  bound 2.9 per 1,000 h), the EKF the same; the CUSUM rule 793 false torque WARN and 8.35e+04 false steering
  WARN per 1,000 h (observer), 947 and 8.17e+04 (EKF). A 10 % bias to WARN, p50 / p95: observer torque 0.93 /
  1.04 s, steering 0.61 / 0.61 s; EKF 1.08 / 1.15 s and 0.61 / 0.62 s; CUSUM (observer) 0.45 / 0.55 s and
  0.16 / 0.21 s."""
