"""Driving scenarios: manoeuvres, speed profile, wind, faults, sensor noise, seed.

A :class:`Scenario` is a validated pydantic model (so a JSON or YAML file with
a mistake is rejected with a message naming the field) that compiles into
per-sample signal tables (:class:`ScenarioSignals`). The plant simulator only
indexes those arrays, so hundreds of vehicles with different scenarios step
together in numpy.
"""

from __future__ import annotations

import itertools
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from edge_client.faults import Fault, fault_tables
from synth.model import FloatArray
from synth.params import VehicleParams

NonNegative = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]
Finite = Annotated[float, Field(allow_inf_nan=False)]


class _Strict(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class Manoeuvre(_Strict):
    """An open-loop steering manoeuvre, added to the steering demand delta_d.

    ``turn``: amplitude held, with smooth ramps of ``ramp_s`` in and out;
    ``lane_change``: one full sine period over the duration (a lateral offset);
    ``slalom``: a sine of period ``period_s`` for the duration;
    ``straight``: nothing (documents intent in scenario files).
    Positive amplitude steers left (positive yaw rate).
    """

    kind: Literal["straight", "turn", "lane_change", "slalom"]
    start_s: NonNegative
    duration_s: Positive
    amplitude_rad: Finite = 0.0
    ramp_s: NonNegative = 1.0
    period_s: Positive = 4.0

    @model_validator(mode="after")
    def _ramps_fit(self) -> Manoeuvre:
        if self.kind == "turn" and 2 * self.ramp_s > self.duration_s:
            raise ValueError(
                f"ramp_s={self.ramp_s} is too long for a turn of duration_s={self.duration_s} "
                "(needs 2*ramp_s <= duration_s)"
            )
        return self

    def steer(self, t: FloatArray) -> FloatArray:
        """Steering demand contribution [rad], shape of t."""
        tau = t - self.start_s
        inside = (tau >= 0) & (tau < self.duration_s)
        if self.kind == "straight":
            return np.zeros_like(t)
        if self.kind == "turn":
            if self.ramp_s == 0:
                shape = np.ones_like(t)
            else:
                up = _smoothstep(tau / self.ramp_s)
                down = _smoothstep((self.duration_s - tau) / self.ramp_s)
                shape = np.minimum(up, down)
            return np.where(inside, self.amplitude_rad * shape, 0.0)
        period = self.duration_s if self.kind == "lane_change" else self.period_s
        return np.where(inside, self.amplitude_rad * np.sin(2.0 * np.pi * tau / period), 0.0)


class SpeedPoint(_Strict):
    """A point of the piecewise-linear speed reference."""

    t_s: NonNegative
    speed_mps: Positive


class Gust(_Strict):
    """A lateral wind force F_w [N] between start_s and start_s + duration_s, with 0.2 s ramps."""

    start_s: NonNegative
    duration_s: Positive
    force_n: Finite

    def force(self, t: FloatArray) -> FloatArray:
        tau = t - self.start_s
        ramp = min(0.2, self.duration_s / 2)
        shape = np.minimum(_smoothstep(tau / ramp), _smoothstep((self.duration_s - tau) / ramp))
        return np.where((tau >= 0) & (tau < self.duration_s), self.force_n * shape, 0.0)


class RoadGrade(_Strict):
    """A road that climbs and descends: theta(t) = offset_rad + amplitude_rad sin(2 pi t / period_s + phase_rad)
    [rad, + uphill], the road's angle to the horizontal along the vehicle's x axis. The weight pulls the vehicle
    back with (M_v + payload) g sin(theta); the vehicle reports theta with each measurement (flag bit 1)."""

    amplitude_rad: Annotated[float, Field(ge=0, le=0.2, allow_inf_nan=False)] = 0.0
    period_s: Positive = 30.0
    phase_rad: Finite = 0.0
    offset_rad: Annotated[float, Field(ge=-0.2, le=0.2, allow_inf_nan=False)] = 0.0

    @model_validator(mode="after")
    def _within_a_road(self) -> RoadGrade:
        if abs(self.offset_rad) + self.amplitude_rad > 0.3:
            raise ValueError(
                f"|offset_rad| + amplitude_rad must be at most 0.3 rad (a 31 % grade), got "
                f"{abs(self.offset_rad) + self.amplitude_rad:g}"
            )
        return self

    def grade(self, t: FloatArray) -> FloatArray:
        return np.asarray(self.offset_rad + self.amplitude_rad * np.sin(2 * np.pi * t / self.period_s + self.phase_rad))


class SensorNoise(_Strict):
    """Gaussian white noise and constant bias on the measured v_x and r."""

    vx_sigma_mps: NonNegative = 0.0
    r_sigma_radps: NonNegative = 0.0
    vx_bias_mps: Finite = 0.0
    r_bias_radps: Finite = 0.0


#: The noise level of NOTES.md finding 5, typical of wheel-speed and gyro sensors.
REALISTIC_NOISE = SensorNoise(vx_sigma_mps=0.05, r_sigma_radps=0.005)


class DriverGains(_Strict):
    """Speed tracking: a = dv_ref/dt + k_p (v_ref - v_meas); T_d = R_w (m_eff a + C_x v_meas^2 + F_r)."""

    speed_kp_per_s: Positive = 1.0


class Scenario(_Strict):
    """Everything one simulated vehicle does."""

    name: str = Field(min_length=1, max_length=64)
    description: str = ""
    duration_s: Annotated[float, Field(gt=0, le=86_400, allow_inf_nan=False)]
    initial_speed_mps: Positive = 10.0
    initial_lateral_speed_mps: Finite = 0.0
    initial_yaw_rate_radps: Finite = 0.0
    speed_profile: tuple[SpeedPoint, ...] = Field(
        default=(), description="piecewise-linear v_ref; empty = hold initial speed"
    )
    manoeuvres: tuple[Manoeuvre, ...] = ()
    faults: tuple[Fault, ...] = ()
    gusts: tuple[Gust, ...] = ()
    noise: SensorNoise = SensorNoise()
    driver: DriverGains = DriverGains()
    vehicle: VehicleParams = VehicleParams()
    payload_kg: NonNegative = Field(
        0.0,
        description="a load at the centre of gravity beyond the vehicle's parameters [kg], at most its mass_kg; "
        "the fleet reports it to the service at the start",
    )
    road_grade: RoadGrade | None = Field(None, description="the road's grade; None = level ground, none reported")
    seed: Annotated[int, Field(ge=0)] = 0
    observer_initial_state: tuple[Finite, Finite, Finite] | None = Field(
        None, description="[v_x, v_y, r] the observer starts from; None = measured v_x, r and v_y = 0"
    )

    @model_validator(mode="after")
    def _speed_profile_sorted(self) -> Scenario:
        times = [p.t_s for p in self.speed_profile]
        if any(b <= a for a, b in itertools.pairwise(times)):
            raise ValueError(f"speed_profile times must increase strictly, got {times}")
        if self.payload_kg > self.vehicle.mass_kg:
            raise ValueError(
                f"payload_kg must be at most the vehicle's mass_kg ({self.vehicle.mass_kg:g}), got {self.payload_kg:g}"
            )
        return self

    @property
    def faulty(self) -> bool:
        return len(self.faults) > 0

    def n_samples(self, sample_period_s: float) -> int:
        """Number of samples of the scenario at this period."""
        return round(self.duration_s / sample_period_s)

    def compile(self, sample_period_s: float, start: int = 0, count: int | None = None) -> ScenarioSignals:
        """Sample every open-loop signal at t_k = k * sample_period_s for start <= k < start + count.

        ``count`` None means up to the end of the scenario; samples past the end
        are still produced (the plant marks them inactive).
        """
        if count is None:
            count = max(self.n_samples(sample_period_s) - start, 0)
        n = count
        t = (start + np.arange(n)) * sample_period_s
        steer = np.zeros(n)
        if n:
            t_first, t_last = float(t[0]), float(t[-1])
            for m in self.manoeuvres:
                # only manoeuvres overlapping the window: a long drive has hundreds
                if m.start_s <= t_last and m.start_s + m.duration_s > t_first:
                    steer += m.steer(t)
        if self.speed_profile:
            pts_t = np.array([p.t_s for p in self.speed_profile])
            pts_v = np.array([p.speed_mps for p in self.speed_profile])
            speed_ref = np.interp(t, pts_t, pts_v)
        else:
            speed_ref = np.full(n, self.initial_speed_mps)
        speed_ref_rate = np.zeros(n)
        if self.speed_profile:
            pts_t = np.array([p.t_s for p in self.speed_profile])
            pts_v = np.array([p.speed_mps for p in self.speed_profile])
            slopes = np.diff(pts_v) / np.diff(pts_t) if len(pts_t) > 1 else np.zeros(0)
            segment = np.searchsorted(pts_t, t, side="right") - 1
            inside = (segment >= 0) & (segment < len(slopes))
            speed_ref_rate[inside] = slopes[segment[inside]]
        wind = np.zeros(n)
        for g in self.gusts:
            wind += g.force(t)
        fault_add, fault_gain = fault_tables(self.faults, t)
        return ScenarioSignals(
            t=t,
            steer_demand=steer,
            speed_ref=speed_ref,
            speed_ref_rate=speed_ref_rate,
            wind=wind,
            fault_add=fault_add,
            fault_gain=fault_gain,
            grade=np.zeros(n) if self.road_grade is None else self.road_grade.grade(t),
        )


@dataclass(frozen=True)
class ScenarioSignals:
    """Open-loop signals of one scenario on the sample grid (K samples).

    t, steer_demand [rad], speed_ref [m/s], speed_ref_rate [m/s^2], wind [N], grade [rad, + uphill]: (K,);
    fault_add, fault_gain: (K, 2) with f = fault_add + fault_gain * u_d.
    """

    t: FloatArray
    steer_demand: FloatArray
    speed_ref: FloatArray
    speed_ref_rate: FloatArray
    wind: FloatArray
    fault_add: FloatArray
    fault_gain: FloatArray
    grade: FloatArray


def _smoothstep(z: FloatArray) -> FloatArray:
    z = np.clip(z, 0.0, 1.0)
    return z * z * (3.0 - 2.0 * z)


class ScenarioError(ValueError):
    """A scenario file that cannot be used; the message names the file and the field."""


def read_scenario_file(path: str | Path) -> object:
    """The parsed content of a .json, .yaml or .yml file; ScenarioError names the file if it cannot be read."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ScenarioError(f"{path}: cannot read: {exc.strerror}") from exc
    try:
        return yaml.safe_load(text) if path.suffix.lower() in (".yaml", ".yml") else json.loads(text)
    except (yaml.YAMLError, json.JSONDecodeError) as exc:
        raise ScenarioError(f"{path}: cannot parse: {exc}") from exc


def load_scenario(path: str | Path) -> Scenario:
    """Read a scenario from a .json, .yaml or .yml file, validated."""
    return scenario_from_data(read_scenario_file(path), source=str(path))


def scenario_from_data(data: object, source: str = "<scenario>") -> Scenario:
    """Validate already-parsed scenario data; errors name every offending field."""
    if not isinstance(data, dict):
        raise ScenarioError(f"{source}: a scenario must be a mapping of fields, got {type(data).__name__}")
    try:
        return Scenario.model_validate(data)
    except ValidationError as exc:
        problems = []
        for err in exc.errors():
            where = ".".join(str(p) for p in err["loc"]) or "(root)"
            value = err.get("input")
            shown = "" if isinstance(value, dict | list) else f" (got {value!r})"
            problems.append(f"  {where}: {err['msg']}{shown}")
        raise ScenarioError(f"{source}: invalid scenario:\n" + "\n".join(problems)) from exc
