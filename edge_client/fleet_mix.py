"""Scenarios for a simulated fleet: a validated mix of healthy and faulty vehicles.

``--scenario-mix`` takes either weights per kind, ``"healthy=0.5,torque_bias=0.2,steer_bias=0.3"``
(normalised; a kind left out gets no vehicles), or the path of a scenario file
(.json/.yaml holding one scenario or a list of them; vehicles cycle through the list).

Kinds (:data:`MIX_KINDS`): every vehicle drives a seeded random drive inside the
operating bounds (:mod:`edge_client.random_drive`); the faulty ones carry one
fault from their onset on:

==================  ===========================================================
healthy             no actuator fault: a correct service never alarms on it
torque_bias         T_f step of 80-150 N m, either sign (eqs. 7-8)
torque_loe          torque loss of effectiveness to alpha_min 0.3-0.5 at
                    5-10 %/s (eqs. 9-11), driven at 15-25 m/s so that
                    |T_f| = (1 - alpha) T_d exceeds 80 N m at cruise
steer_bias          delta_f step of 0.02-0.03 rad, either sign
steer_sinusoidal    delta_f = A sin(omega t), A 0.02-0.03 rad, omega 0.3-1 rad/s
intermittent        a torque (100-150 N m) or steering (0.02-0.03 rad) bias on
                    for 2-4 s out of every 5-8 s
==================  ===========================================================

With ``gusts`` every vehicle, healthy or not, also meets random lateral wind
gusts of 300-800 N (:func:`random_gusts`): a disturbance, not a fault. With
``loads`` every vehicle carries a random payload of 0-25 % of its mass
(:func:`random_load`), which the fleet reports to the service at the start;
with ``hills`` every vehicle drives a road that climbs and descends (grades
within 2-6 %, :func:`random_hills`) and reports the grade with each sample.
Each is drawn from a stream of its own, so the drive and the fault are the
same with or without them.

Fault sizes follow the service's default alarm thresholds (:data:`ASSUMED_ALARM`, the
defaults of ``service.profiles.AlarmThresholds``, which a test keeps equal): the WARN levels, |T_f estimate|
above 40 N m or |delta_f estimate| above 0.01 rad held for 0.5 s, about five
times the fault-estimate RMSE of the default robust design under realistic
noise. Every injected fault is at least twice its threshold once established. Fault onsets come after
15-35 % of the run, or of its first 60 s for longer runs (at least 2 s), so the observer has converged
first.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, get_args

import numpy as np

from edge_client.faults import BiasFault, Fault, IntermittentFault, LossOfEffectivenessFault, SinusoidalFault
from edge_client.random_drive import random_drive
from edge_client.scenario import (
    Gust,
    RoadGrade,
    Scenario,
    ScenarioError,
    SensorNoise,
    read_scenario_file,
    scenario_from_data,
)
from synth.params import VehicleParams

MixKind = Literal["healthy", "torque_bias", "torque_loe", "steer_bias", "steer_sinusoidal", "intermittent"]
MIX_KINDS: tuple[MixKind, ...] = get_args(MixKind)
DEFAULT_MIX = "healthy=0.5,torque_bias=0.1,torque_loe=0.1,steer_bias=0.1,steer_sinusoidal=0.1,intermittent=0.1"

#: Earliest fault onset [s]: the observer must have converged before a fault appears.
MIN_ONSET_S = 2.0
#: Onsets fall at 15-35 % of the run, or of this horizon for longer runs [s]: an operator watching a long
#: (or open-ended) fleet sees the faults appear within the first minute.
ONSET_HORIZON_S = 60.0
#: Largest steering fault any kind injects [rad]; reserved from the manoeuvres' steering budget.
MAX_STEER_FAULT_RAD = 0.03
#: Range of |F_w| of the optional random gusts [N]; a test checks that they keep healthy vehicles'
#: estimates below the alarm thresholds.
GUST_FORCE_N = (300.0, 800.0)
#: Range of the optional random payloads, as a share of the vehicle's mass.
LOAD_SHARE = (0.0, 0.25)
#: Range of the optional hills' largest grade [rad] and of their period [s].
HILL_GRADE_RAD = (0.02, 0.06)
HILL_PERIOD_S = (20.0, 60.0)


@dataclass(frozen=True)
class AlarmAssumption:
    """What the fleet's fault sizes assume of the service's alarms: its default WARN thresholds."""

    torque_threshold_nm: float
    steer_threshold_rad: float
    persistence_s: float


#: The service's default WARN thresholds and persistence (service.profiles.AlarmThresholds; the vehicle side
#: imports nothing of the service, and tests/edge_client/test_fleet_mix.py keeps them equal).
ASSUMED_ALARM = AlarmAssumption(torque_threshold_nm=40.0, steer_threshold_rad=0.01, persistence_s=0.5)


class MixError(ValueError):
    """A --scenario-mix that cannot be used; the message says which part and why."""


@dataclass(frozen=True)
class FleetMember:
    """One simulated vehicle: its id, the mix kind it was drawn from ('file' for scenario files) and scenario."""

    vehicle_id: str
    kind: str
    scenario: Scenario

    @property
    def faulty(self) -> bool:
        return self.scenario.faulty

    @property
    def fault_onset_s(self) -> float | None:
        """Earliest onset of the vehicle's faults [s], None if healthy."""
        return min((f.onset_s for f in self.scenario.faults), default=None)


def parse_mix(text: str) -> dict[MixKind, float]:
    """Parse ``kind=weight,...`` into normalised fractions; raise MixError naming the bad part."""
    weights: dict[MixKind, float] = {}
    if not text.strip():
        raise MixError("empty scenario mix; expected e.g. 'healthy=0.5,torque_bias=0.5'")
    for part in text.split(","):
        name, sep, value = part.partition("=")
        name = name.strip()
        if not sep:
            raise MixError(f"{part.strip()!r}: expected KIND=WEIGHT, e.g. 'healthy=0.5'")
        if name not in MIX_KINDS:
            raise MixError(f"unknown kind {name!r}; known kinds: {', '.join(MIX_KINDS)}")
        if name in weights:
            raise MixError(f"kind {name!r} is given twice")
        try:
            weight = float(value)
        except ValueError:
            raise MixError(f"{name}: weight {value.strip()!r} is not a number") from None
        if not math.isfinite(weight) or weight < 0:
            raise MixError(f"{name}: weight must be finite and >= 0, got {value.strip()!r}")
        weights[name] = weight
    total = sum(weights.values())
    if total <= 0:
        raise MixError("all weights are zero; at least one kind needs a positive weight")
    return {kind: weight / total for kind, weight in weights.items()}


def allocate(fractions: dict[MixKind, float], n_vehicles: int) -> list[MixKind]:
    """Kinds for ``n_vehicles`` by largest remainder, interleaved so that any prefix is mixed too."""
    quotas = {kind: fraction * n_vehicles for kind, fraction in fractions.items()}
    counts = {kind: math.floor(q) for kind, q in quotas.items()}
    by_remainder = sorted(quotas, key=lambda kind: (quotas[kind] - counts[kind], -MIX_KINDS.index(kind)), reverse=True)
    for kind in by_remainder[: n_vehicles - sum(counts.values())]:
        counts[kind] += 1
    # interleave: vehicle j gets the kind whose (placed + 0.5) / count is smallest
    placed = dict.fromkeys(counts, 0)
    kinds: list[MixKind] = []
    for _ in range(n_vehicles):
        kind = min(
            (k for k in counts if placed[k] < counts[k]),
            key=lambda k: ((placed[k] + 0.5) / counts[k], MIX_KINDS.index(k)),
        )
        placed[kind] += 1
        kinds.append(kind)
    return kinds


def _onset(rng: np.random.Generator, duration_s: float) -> float:
    horizon = min(duration_s, ONSET_HORIZON_S)
    return round(max(MIN_ONSET_S, float(rng.uniform(0.15, 0.35)) * horizon), 2)


def _sign(rng: np.random.Generator) -> float:
    return float(rng.choice([-1.0, 1.0]))


def _faults_for(kind: MixKind, rng: np.random.Generator, duration_s: float) -> tuple[Fault, ...]:
    onset = _onset(rng, duration_s)
    if kind == "healthy":
        return ()
    if kind == "torque_bias":
        return (BiasFault(channel="torque", onset_s=onset, magnitude=_sign(rng) * round(rng.uniform(80, 150), 1)),)
    if kind == "torque_loe":
        return (
            LossOfEffectivenessFault(
                channel="torque",
                onset_s=onset,
                rate_per_s=round(float(rng.uniform(0.05, 0.10)), 3),
                alpha_min=round(float(rng.uniform(0.3, 0.5)), 2),
            ),
        )
    if kind == "steer_bias":
        magnitude = _sign(rng) * round(float(rng.uniform(0.02, MAX_STEER_FAULT_RAD)), 4)
        return (BiasFault(channel="steer", onset_s=onset, magnitude=magnitude),)
    if kind == "steer_sinusoidal":
        return (
            SinusoidalFault(
                channel="steer",
                onset_s=onset,
                amplitude=round(float(rng.uniform(0.02, MAX_STEER_FAULT_RAD)), 4),
                omega_radps=round(float(rng.uniform(0.3, 1.0)), 3),
            ),
        )
    # intermittent
    period = round(float(rng.uniform(5.0, 8.0)), 2)
    on = round(float(rng.uniform(2.0, 4.0)), 2)
    if rng.random() < 0.5:
        magnitude = _sign(rng) * round(float(rng.uniform(100, 150)), 1)
        return (IntermittentFault(channel="torque", onset_s=onset, magnitude=magnitude, period_s=period, on_s=on),)
    magnitude = _sign(rng) * round(float(rng.uniform(0.02, MAX_STEER_FAULT_RAD)), 4)
    return (IntermittentFault(channel="steer", onset_s=onset, magnitude=magnitude, period_s=period, on_s=on),)


def random_gusts(rng: np.random.Generator, duration_s: float) -> tuple[Gust, ...]:
    """Lateral gusts of 300-800 N either way, 0.5-2 s long, one every 15-40 s."""
    gusts = []
    t = float(rng.uniform(5.0, 20.0))
    while t < duration_s:
        force = _sign(rng) * round(float(rng.uniform(*GUST_FORCE_N)), 1)
        length = round(float(rng.uniform(0.5, 2.0)), 2)
        gusts.append(Gust(start_s=round(t, 2), duration_s=length, force_n=force))
        t += length + float(rng.uniform(15.0, 40.0))
    return tuple(gusts)


def random_load(rng: np.random.Generator, vehicle: VehicleParams) -> float:
    """A payload of LOAD_SHARE of the vehicle's mass [kg], to 10 kg."""
    return round(float(rng.uniform(*LOAD_SHARE)) * vehicle.mass_kg, -1)


def random_hills(rng: np.random.Generator) -> RoadGrade:
    """A road whose grade swings within HILL_GRADE_RAD over HILL_PERIOD_S, from a random phase."""
    return RoadGrade(
        amplitude_rad=round(float(rng.uniform(*HILL_GRADE_RAD)), 3),
        period_s=round(float(rng.uniform(*HILL_PERIOD_S)), 1),
        phase_rad=round(float(rng.uniform(0.0, 2.0 * math.pi)), 2),
    )


def mix_scenario(
    kind: MixKind,
    vehicle_id: str,
    duration_s: float,
    seed: int,
    noise: SensorNoise | None = None,
    gusts: bool = False,
    loads: bool = False,
    hills: bool = False,
) -> Scenario:
    """The scenario of one fleet vehicle of ``kind``: a random drive plus that kind's fault, seeded.

    ``gusts`` adds :func:`random_gusts`, ``loads`` a :func:`random_load`, ``hills`` :func:`random_hills` (each
    drawn from a stream of its own, so the drive and the fault are the same with or without them).
    """
    rng = np.random.default_rng(seed)
    faults = _faults_for(kind, rng, duration_s)
    steer_fault = any(f.channel == "steer" for f in faults)
    speed_range = (15.0, 25.0) if kind == "torque_loe" else (8.0, 25.0)
    drive = random_drive(
        rng,
        duration_s,
        speed_range_mps=speed_range,
        reserved_steer_rad=MAX_STEER_FAULT_RAD if steer_fault else 0.0,
    )
    return Scenario(
        name=f"{vehicle_id}-{kind}".replace("_", "-")[:64],
        description=f"fleet vehicle {vehicle_id}: random drive, {kind.replace('_', ' ')}",
        duration_s=duration_s,
        initial_speed_mps=drive.initial_speed_mps,
        speed_profile=drive.speed_profile,
        manoeuvres=drive.manoeuvres,
        faults=faults,
        gusts=random_gusts(np.random.default_rng([seed, 1]), duration_s) if gusts else (),
        noise=noise or SensorNoise(),
        payload_kg=random_load(np.random.default_rng([seed, 2]), VehicleParams()) if loads else 0.0,
        road_grade=random_hills(np.random.default_rng([seed, 3])) if hills else None,
        seed=seed,
    )


def vehicle_ids(n_vehicles: int, prefix: str = "veh") -> list[str]:
    width = max(3, len(str(n_vehicles - 1)))
    return [f"{prefix}-{i:0{width}d}" for i in range(n_vehicles)]


def build_fleet(
    mix: str,
    n_vehicles: int,
    duration_s: float,
    *,
    seed: int = 0,
    noise: SensorNoise | None = None,
    id_prefix: str = "veh",
    gusts: bool = False,
    loads: bool = False,
    hills: bool = False,
) -> list[FleetMember]:
    """The fleet for ``--scenario-mix``: weights per kind, or a scenario file to cycle through (its scenarios
    keep their own gusts, payloads and roads; ``gusts``, ``loads`` and ``hills`` are for the kinds).

    Raises MixError (bad weights) or ScenarioError (bad file), both naming what is wrong.
    """
    if n_vehicles < 1:
        raise MixError(f"the fleet needs at least one vehicle, got {n_vehicles}")
    ids = vehicle_ids(n_vehicles, id_prefix)
    if Path(mix).suffix.lower() in (".json", ".yaml", ".yml"):
        scenarios = load_scenario_list(mix)
        members = []
        for i, vehicle_id in enumerate(ids):
            scenario = scenarios[i % len(scenarios)]
            updates: dict[str, object] = {"duration_s": duration_s}
            if noise is not None:
                updates["noise"] = noise
            if i >= len(scenarios):  # repeated scenarios get their own noise stream
                updates["seed"] = scenario.seed + i
            members.append(FleetMember(vehicle_id, "file", scenario.model_copy(update=updates)))
        return members
    kinds = allocate(parse_mix(mix), n_vehicles)
    seeds = np.random.SeedSequence(seed).generate_state(n_vehicles)
    return [
        FleetMember(vehicle_id, kind, mix_scenario(kind, vehicle_id, duration_s, int(s), noise, gusts, loads, hills))
        for vehicle_id, kind, s in zip(ids, kinds, seeds, strict=True)
    ]


def load_scenario_list(path: str | Path) -> list[Scenario]:
    """One scenario or a list of scenarios from a .json/.yaml file; errors name the entry and field."""
    path = Path(path)
    data = read_scenario_file(path)
    entries: Sequence[object] = data if isinstance(data, list) else [data]
    if not entries:
        raise ScenarioError(f"{path}: the list of scenarios is empty")
    return [
        scenario_from_data(entry, source=f"{path}[{i}]" if isinstance(data, list) else str(path))
        for i, entry in enumerate(entries)
    ]
