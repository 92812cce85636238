"""Vehicle profiles: what one vehicle type needs to be observed and alarmed on.

A profile bundles the vehicle parameters (Table 1), the operating bounds
(eq. 13), the observer design options, the alarm thresholds and the
plausibility limits of the inputs. Design options are kept as the user gave
them (``exclude_unset``), so a change of the default design reaches profiles
that did not choose one.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Annotated, Any, Literal, Self

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from synth.options import DesignOptions, EffectivenessOptions
from synth.params import OperatingBounds, VehicleParams

#: The characters of a profile name, 1 to 64 of ``A-Z a-z 0-9 _ . -``. Check a name with
#: :func:`valid_profile_name`: Python's ``re.match`` would let a trailing newline through ``$``, and the
#: names ``.`` and ``..`` are refused as well.
PROFILE_NAME_PATTERN = r"^[A-Za-z0-9_.-]{1,64}$"
PROFILE_NAME_RULE = "1-64 of A-Z a-z 0-9 _ . -, not '.' or '..'"
DEFAULT_PROFILE_NAME = "default"

#: The longest duration an alarm rule may name [s]: one day, 8.64e13 ns, far inside int64 sample time
#: (the detectors count in integer nanoseconds, :func:`service.fleet.alarms.seconds_to_ns`).
MAX_RULE_DURATION_S = 86_400.0
#: The largest threshold or limit a profile may set, in its unit: finite, and far beyond any vehicle.
MAX_MAGNITUDE = 1e12

NonNegative = Annotated[float, Field(ge=0, le=MAX_MAGNITUDE, allow_inf_nan=False)]
Positive = Annotated[float, Field(gt=0, le=MAX_MAGNITUDE, allow_inf_nan=False)]
Duration = Annotated[float, Field(ge=0, le=MAX_RULE_DURATION_S, allow_inf_nan=False)]
PositiveDuration = Annotated[float, Field(gt=0, le=MAX_RULE_DURATION_S, allow_inf_nan=False)]


class AlarmThresholds(BaseModel):
    """Alarm rules of a profile: fault thresholds with persistence and hysteresis, and the other conditions.

    A fault level is raised when |estimate| >= its threshold for ``raise_after_s``
    of vehicle time, and drops when |estimate| < ``hysteresis`` x threshold for
    ``clear_after_s``. Fault alarms are not evaluated during ``warmup_s`` after
    an observer (re)starts, while its estimate converges. With ``rule`` 'cusum'
    the fault levels come from a two-sided CUSUM instead (service.fleet.cusum).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    # Defaults: about 5x the fault-estimate RMSE of the default 'robust' design under realistic
    # sensor noise (6-9 N m, 0.0005-0.005 rad; docs/benchmarks/accuracy.md) for WARN, twice that for FAULT.
    torque_warn_nm: Positive = Field(40.0, description="|T_f| raising WARN [N m]")
    torque_fault_nm: Positive = Field(80.0, description="|T_f| raising FAULT [N m]")
    steer_warn_rad: Positive = Field(0.01, description="|delta_f| raising WARN [rad]")
    steer_fault_rad: Positive = Field(0.02, description="|delta_f| raising FAULT [rad]")
    hysteresis: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] = Field(
        0.8, description="a level holds until the value falls below hysteresis x its threshold [-]"
    )
    raise_after_s: Duration = Field(0.5, description="how long a condition must hold before it raises [s]")
    clear_after_s: Duration = Field(1.0, description="how long a condition must be gone before it clears [s]")
    warmup_s: Duration = Field(3.0, description="no fault alarms this long after an observer (re)starts [s]")
    grip_limit_g: Annotated[float, Field(gt=0, le=3, allow_inf_nan=False)] | None = Field(
        0.55,
        description="the combined acceleration |(dv_x/dt, v_x r)| / g above which, while the vehicle brakes or "
        "accelerates at grip_longitudinal_g or more, the tyres leave the model's linear range: the fault levels "
        "are held unjudged there and for grip_hold_s after (docs/math.md 12.4: measured on dry roads, and it holds "
        "on a wet one driven within its grip; lower it and grip_longitudinal_g for a vehicle high for its track); "
        "null: no grip gate [g]",
    )
    grip_longitudinal_g: Annotated[float, Field(ge=0, le=3, allow_inf_nan=False)] = Field(
        0.2, description="|dv_x/dt| / g from which grip_limit_g applies (below it, grip_cornering_g does) [g]"
    )
    grip_cornering_g: Annotated[float, Field(gt=0, le=3, allow_inf_nan=False)] = Field(
        0.8,
        description="the combined acceleration / g beyond which the fault levels are held whatever the "
        "longitudinal part (steady cornering: measured to hold to 0.8 g on a dry road) [g]",
    )
    grip_hold_s: Duration = Field(
        2.0,
        description="the fault levels stay unjudged this long after the last sample beyond the grip limits: the "
        "observer's estimate settling after the model's miss there (docs/math.md 12.4: 1 s was short after "
        "braking at 0.4 g in a 0.6 g turn, 2 s measured to cover it) [s]",
    )
    out_of_domain_after_s: Duration = Field(
        0.5, description="premise or estimated v_y outside the design bounds this long raises WARN [s]"
    )
    stale_after_s: PositiveDuration = Field(1.0, description="no measurement this long makes the vehicle STALE [s]")
    reject_burst_count: Annotated[int, Field(ge=1, le=1_000_000)] = Field(
        10, description="this many rejected measurements within the window raise WARN"
    )
    reject_burst_window_s: PositiveDuration = Field(1.0, description="window of the rejected-input count [s]")
    sequence_reject_count: Annotated[int, Field(ge=1, le=1_000_000)] = Field(
        100,
        description="this many samples in a row refused as late (out_of_order) or with an implausible sequence "
        "jump (implausible_seq) raise WARN sequence_rejected",
    )
    effectiveness_warn: Annotated[float, Field(gt=0, lt=1, allow_inf_nan=False)] = Field(
        0.9,
        description="an actuator's effectiveness alpha identified below this (the upper confidence bound "
        "alpha_hat + effectiveness_confidence_k sigma_alpha below it) raises WARN (effectiveness stage) [-]",
    )
    effectiveness_fault: Annotated[float, Field(ge=0, lt=1, allow_inf_nan=False)] = Field(
        0.75, description="an actuator's effectiveness alpha identified below this raises FAULT [-]"
    )
    effectiveness_after_s: Duration = Field(
        1.0, description="how long alpha's upper confidence bound must stay below a threshold before it raises [s]"
    )
    effectiveness_confidence_k: Annotated[float, Field(ge=0, le=10, allow_inf_nan=False)] = Field(
        3.0,
        description="the effectiveness alarms compare alpha's upper confidence bound alpha_hat + k sigma_alpha "
        "(sigma_alpha: the stage's posterior standard deviation) with the thresholds: alpha is alarmed only when "
        "the data identify it below a threshold; 0 compares alpha_hat itself [-]",
    )
    rule: Literal["threshold", "cusum"] = Field(
        "threshold",
        description="how the fault channels raise levels: 'threshold' (|estimate| above a threshold for "
        "raise_after_s) or 'cusum' (a two-sided CUSUM on block means of the estimate, tuned for shifts of the "
        "WARN and FAULT thresholds; needs the healthy sigmas)",
    )
    cusum_block_s: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] = Field(
        0.1, description="the CUSUM's block length: it runs on the estimate's means over blocks this long [s]"
    )
    cusum_false_alarms_per_1000_h: Annotated[float, Field(gt=0, le=1e6, allow_inf_nan=False)] = Field(
        1.0, description="the CUSUM's design false-alarm rate per level on Gaussian block means [per 1,000 h]"
    )
    torque_block_sigma_nm: Positive | None = Field(
        None, description="standard deviation of the healthy T_f estimate's block means [N m] (calibration)"
    )
    steer_block_sigma_rad: Positive | None = Field(
        None, description="standard deviation of the healthy delta_f estimate's block means [rad] (calibration)"
    )

    @model_validator(mode="after")
    def _warn_below_fault(self) -> AlarmThresholds:
        for channel, unit in (("torque", "nm"), ("steer", "rad")):
            warn, fault = getattr(self, f"{channel}_warn_{unit}"), getattr(self, f"{channel}_fault_{unit}")
            if not warn < fault:
                raise ValueError(f"{channel}_warn_{unit} must be below {channel}_fault_{unit}, got {warn} >= {fault}")
        if not self.effectiveness_fault < self.effectiveness_warn:
            raise ValueError(
                f"effectiveness_fault must be below effectiveness_warn, got {self.effectiveness_fault} >= "
                f"{self.effectiveness_warn}"
            )
        if self.rule == "cusum" and (self.torque_block_sigma_nm is None or self.steer_block_sigma_rad is None):
            raise ValueError(
                "rule 'cusum' needs torque_block_sigma_nm and steer_block_sigma_rad (agv-fe calibrate sets them)"
            )
        return self


class InputLimits(BaseModel):
    """Plausibility limits of a measurement; values outside are rejected as ``out_of_range``.

    They are wider than the design bounds: a plausible sample outside the
    design box is observed and flagged out of domain, an implausible one
    (a broken sensor, a unit error) never reaches the observer.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    vx_min_mps: NonNegative = Field(0.0, description="lowest v_x [m/s]")
    vx_max_mps: Positive = Field(100.0, description="highest v_x [m/s]")
    r_abs_max_radps: Positive = Field(5.0, description="highest |r| [rad/s]")
    torque_abs_max_nm: Positive = Field(20_000.0, description="highest |T_d| [N m]")
    steer_abs_max_rad: Positive = Field(1.0, description="highest |delta_d| [rad]")
    grade_abs_max_rad: Positive = Field(0.35, description="highest |road grade| a sample may carry [rad]")

    @model_validator(mode="after")
    def _ordered(self) -> InputLimits:
        if not self.vx_min_mps < self.vx_max_mps:
            raise ValueError(f"vx_min_mps must be below vx_max_mps, got {self.vx_min_mps} >= {self.vx_max_mps}")
        return self


class ProfileSpec(BaseModel):
    """Everything that defines a vehicle type: the body of ``PUT /profiles/{name}``."""

    model_config = ConfigDict(
        frozen=True,
        extra="forbid",
        json_schema_extra={
            "examples": [
                {
                    "description": "delivery van, heavier than the paper's car",
                    "params": {"mass_kg": 2100.0, "yaw_inertia_kgm2": 2600.0},
                    "bounds": {"vx_min_mps": 5.0, "vx_max_mps": 25.0},
                    "design": {"fault_order": 1},
                    "alarms": {"torque_warn_nm": 80.0, "torque_fault_nm": 160.0},
                }
            ]
        },
    )

    description: str = Field("", max_length=500)
    params: VehicleParams = Field(default_factory=VehicleParams, description="vehicle parameters (Table 1)")
    bounds: OperatingBounds = Field(default_factory=OperatingBounds, description="operating box (eq. 13)")
    design: DesignOptions = Field(
        default_factory=DesignOptions, description="observer design options; unset fields follow the defaults"
    )
    alarms: AlarmThresholds = Field(default_factory=AlarmThresholds)
    limits: InputLimits = Field(default_factory=InputLimits)
    effectiveness: EffectivenessOptions = Field(
        default_factory=EffectivenessOptions,
        description="the loss-of-effectiveness stage (alpha beside the bias, docs/math.md section 14): when "
        "enabled, estimates carry torque/steer bias and alpha, torque_fault/steer_fault are the total faults, and "
        "alarms fire on alpha too; needs the 'robust' design with fault_order 1",
    )

    @model_validator(mode="after")
    def _stage_fits_the_design(self) -> Self:
        d = self.design
        if self.effectiveness.enabled and (d.design != "robust" or d.fault_order != 1):
            raise ValueError(
                f"effectiveness.enabled needs design 'robust' with fault_order 1 (the stage reads the observer's "
                f"random-walk fault estimate), got design {d.design!r} with fault_order {d.fault_order}"
            )
        return self

    def stored(self) -> dict[str, Any]:
        """The JSON kept in the database: only what was set, so defaults keep propagating."""
        return self.model_dump(mode="json", exclude_unset=True)

    def design_inputs(self) -> dict[str, Any]:
        """What the gains depend on, fully resolved: params, bounds and options."""
        return {
            "params": self.params.model_dump(mode="json"),
            "bounds": self.bounds.model_dump(mode="json"),
            "options": self.design.model_dump(mode="json"),
        }


def valid_profile_name(name: str) -> bool:
    """Whether ``name`` is a usable profile name: all of it matches :data:`PROFILE_NAME_PATTERN`, and it is
    neither ``.`` nor ``..`` (path segments, not names)."""
    return re.fullmatch(PROFILE_NAME_PATTERN, name) is not None and name not in (".", "..")


def check_profile_name(name: str) -> str:
    """Return ``name`` if it is a usable profile name, else raise ValueError saying what a name is."""
    if not valid_profile_name(name):
        raise ValueError(f"invalid profile name {name!r}: use {PROFILE_NAME_RULE}")
    return name


class ProfileFileError(ValueError):
    """An initial-profiles file that cannot be used; the text names the file and the field."""


def load_profiles_file(path: Path) -> dict[str, ProfileSpec]:
    """Read ``{"profiles": {NAME: ProfileSpec, ...}}`` from a JSON or YAML file."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise ProfileFileError(f"{path}: cannot read: {exc.strerror}") from exc
    try:
        data = yaml.safe_load(text) if path.suffix in (".yaml", ".yml") else json.loads(text)
    except (yaml.YAMLError, json.JSONDecodeError) as exc:
        kind = "YAML" if path.suffix in (".yaml", ".yml") else "JSON"
        raise ProfileFileError(f"{path}: not valid {kind}: {exc}") from exc
    if not isinstance(data, dict) or not isinstance(data.get("profiles"), dict) or not data["profiles"]:
        raise ProfileFileError(f'{path}: expected an object {{"profiles": {{NAME: PROFILE, ...}}}} with one or more')
    profiles: dict[str, ProfileSpec] = {}
    for name, body in data["profiles"].items():
        if not valid_profile_name(str(name)):
            raise ProfileFileError(f"{path}: invalid profile name {name!r}: use {PROFILE_NAME_RULE}")
        try:
            profiles[str(name)] = ProfileSpec.model_validate(body)
        except ValidationError as exc:
            problems = "; ".join(
                f"profiles.{name}.{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in exc.errors()
            )
            raise ProfileFileError(f"{path}: {problems}") from exc
    return profiles
