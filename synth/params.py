"""Vehicle parameters (Table 1) and operating bounds (eq. 13).

Field names say what a quantity is and carry its unit; the paper's symbol is
given in each description and by :meth:`VehicleParams.symbols`. Both models
are frozen and validated: an error names the field and the value.
"""

from __future__ import annotations

import math
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, model_validator

PositiveFloat = Annotated[float, Field(gt=0, allow_inf_nan=False)]
NonNegativeFloat = Annotated[float, Field(ge=0, allow_inf_nan=False)]
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]

#: The default bound of the applied road-wheel angle |delta| [rad].
STEER_MAX_DEFAULT_RAD = 0.3
#: g [m/s^2], for the load transfer (VehicleParams.load_transfer_gain).
STANDARD_GRAVITY_MPS2 = 9.80665
#: The former name of ``effective_mass_kg``, still accepted on input.
LEGACY_INERTIA_FIELD = "longitudinal_inertia_kgm2"


class VehicleParams(BaseModel):
    """Physical parameters of the 2-DOF vehicle model (Table 1, eq. 5, eq. 12) and its longitudinal terms.

    The defaults are the paper's Table 1, read physically (the ``paper`` profile): its I_e = 443 is the
    effective mass the drive force accelerates, and its "torque" is a force, i.e. a torque at a wheel
    of radius 1 m. A real vehicle states its wheel radius, its effective mass (mass plus the rotating
    parts' inertia over the wheel radius squared), its rolling resistance and the cornering drag
    (``agv-fe calibrate`` identifies what a data sheet does not give).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    mass_kg: PositiveFloat = Field(1481.0, description="M_v, vehicle mass [kg]")
    effective_mass_kg: PositiveFloat = Field(
        443.0,
        description="m_eff (the paper's I_e), the inertia of the longitudinal motion: vehicle mass plus the "
        "rotating parts' inertia over the wheel radius squared [kg]",
    )
    wheel_radius_m: Annotated[float, Field(gt=0, le=5, allow_inf_nan=False)] = Field(
        1.0,
        description="R_w, effective rolling radius of the driven wheels: the drive force is T_d / R_w [m] "
        "(1 m in the paper's profile, where its torque and force coincide)",
    )
    yaw_inertia_kgm2: PositiveFloat = Field(1807.0, description="I_z, yaw moment of inertia [kg m^2]")
    front_axle_distance_m: PositiveFloat = Field(1.12, description="l_f, centre of gravity to front axle [m]")
    rear_axle_distance_m: PositiveFloat = Field(1.5, description="l_r, centre of gravity to rear axle [m]")
    front_cornering_stiffness_npr: PositiveFloat = Field(
        57110.0, description="C_f, cornering stiffness of one front tyre (the axle has 2 C_f) [N/rad]"
    )
    rear_cornering_stiffness_npr: PositiveFloat = Field(
        58100.0, description="C_r, cornering stiffness of one rear tyre (the axle has 2 C_r) [N/rad]"
    )
    longitudinal_drag_coeff: NonNegativeFloat = Field(
        0.37, description="C_x, longitudinal aerodynamic drag coefficient: drag force C_x v_x^2 [N s^2/m^2]"
    )
    rolling_resistance_n: NonNegativeFloat = Field(
        0.0, description="F_r, rolling resistance: a constant force against the motion (v_x > 0) [N]"
    )
    cornering_drag: bool = Field(
        False,
        description="dv_x/dt includes -F_yf sin(delta) / m_eff, the front lateral force projected on the "
        "vehicle's x axis (off in the paper's model; hundreds of N in hard cornering)",
    )
    lateral_drag_coeff: PositiveFloat = Field(0.42, description="C_y, lateral aerodynamic drag coefficient [N s^2/m^2]")
    steer_time_constant_s: Annotated[float, Field(ge=0, le=1.0, allow_inf_nan=False)] = Field(
        0.0,
        description="tau_delta, time constant of the steering actuator: the road-wheel angle follows the demand "
        "(and a steering fault) through a first-order lag; 0 = the paper's ideal actuator [s]",
    )
    cg_height_m: Annotated[float, Field(ge=0, le=5.0, allow_inf_nan=False)] = Field(
        0.0,
        description="h, height of the centre of gravity above the road: braking moves load to the front axle "
        "and stiffens it against the rear, accelerating the reverse, which the model takes as an equivalent "
        "steering angle (docs/math.md 12.4); 0 = not modelled, as in the paper [m]",
    )
    torque_fault_gain: PositiveFloat = Field(1.0, description="b_T, actuator gain of the torque fault (eq. 5) [-]")
    steer_fault_gain: PositiveFloat = Field(1.0, description="b_delta, actuator gain of the steering fault (eq. 5) [-]")
    sample_period_s: Annotated[float, Field(gt=0, le=1.0, allow_inf_nan=False)] = Field(
        0.01, description="s, sampling period of the Euler discretisation (eq. 12) [s]"
    )

    @model_validator(mode="before")
    @classmethod
    def _renamed_fields(cls, data: Any) -> Any:
        """Profiles and gains stored before the longitudinal inertia was named for what it is keep loading."""
        if isinstance(data, dict) and LEGACY_INERTIA_FIELD in data:
            if "effective_mass_kg" in data:
                raise ValueError(f"give effective_mass_kg or its former name {LEGACY_INERTIA_FIELD}, not both")
            data = {k: v for k, v in data.items() if k != LEGACY_INERTIA_FIELD} | {
                "effective_mass_kg": data[LEGACY_INERTIA_FIELD]
            }
        return data

    @property
    def has_paper_longitudinal_model(self) -> bool:
        """True when the longitudinal equation is the paper's: no rolling resistance, no cornering drag, R_w = 1."""
        return self.wheel_radius_m == 1.0 and self.rolling_resistance_n == 0.0 and not self.cornering_drag

    def symbols(self) -> dict[str, float]:
        """The parameters under the paper's symbols (M_v, m_eff = its I_e, ...) and R_w, F_r."""
        return {
            "M_v": self.mass_kg,
            "m_eff": self.effective_mass_kg,
            "R_w": self.wheel_radius_m,
            "I_z": self.yaw_inertia_kgm2,
            "l_f": self.front_axle_distance_m,
            "l_r": self.rear_axle_distance_m,
            "C_f": self.front_cornering_stiffness_npr,
            "C_r": self.rear_cornering_stiffness_npr,
            "C_x": self.longitudinal_drag_coeff,
            "F_r": self.rolling_resistance_n,
            "C_y": self.lateral_drag_coeff,
            "b_T": self.torque_fault_gain,
            "b_delta": self.steer_fault_gain,
            "s": self.sample_period_s,
        }

    def hashed(self) -> dict[str, Any]:
        """The parameters as the gains' content hash sees them (synth.gains).

        With the paper's longitudinal model the new fields are left out and the effective mass keeps its
        former name, so that gains designed before these fields existed keep their hash and version.
        """
        data = self.model_dump()
        if self.has_paper_longitudinal_model:
            for name in ("wheel_radius_m", "rolling_resistance_n", "cornering_drag"):
                del data[name]
            data[LEGACY_INERTIA_FIELD] = data.pop("effective_mass_kg")
        for name in ("steer_time_constant_s", "cg_height_m"):
            if data[name] == 0.0:
                del data[name]
        return data

    @property
    def load_transfer_gain(self) -> float:
        """G = M_v h / (g (l_f + l_r)) (1 / (2 C_f) + 1 / (2 C_r)) [rad s^4/m^2]: the change of the understeer
        gradient per m/s^2 of longitudinal acceleration when each axle's cornering stiffness follows its load
        (docs/math.md 12.4); 0 without a centre-of-gravity height."""
        if self.cg_height_m == 0.0:
            return 0.0
        wheelbase = self.front_axle_distance_m + self.rear_axle_distance_m
        compliance = 0.5 / self.front_cornering_stiffness_npr + 0.5 / self.rear_cornering_stiffness_npr
        return self.mass_kg * self.cg_height_m / (STANDARD_GRAVITY_MPS2 * wheelbase) * compliance

    @property
    def steer_lag_mean_factor(self) -> float:
        """c = 1 - (tau_delta / s)(1 - a): the road-wheel angle's mean over a sample is delta_k + c (target - delta_k)
        when the target is held over it (1 for the ideal actuator)."""
        a = self.steer_lag_factor
        if a == 0.0:
            return 1.0
        return 1.0 - self.steer_time_constant_s / self.sample_period_s * (1.0 - a)

    @property
    def steer_lag_factor(self) -> float:
        """a = exp(-s / tau_delta): the road-wheel angle's exact discrete lag, delta_{k+1} = a delta_k + (1 - a)
        (delta_d,k + b_delta delta_f,k); 0 for the ideal actuator (the angle is the demand)."""
        if self.steer_time_constant_s == 0.0:
            return 0.0
        return math.exp(-self.sample_period_s / self.steer_time_constant_s)


class OperatingBounds(BaseModel):
    """The operating set S_x of eq. (13): the box the design is certified on."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    vx_min_mps: PositiveFloat = Field(5.0, description="lower bound of v_x [m/s]")
    vx_max_mps: PositiveFloat = Field(30.0, description="upper bound of v_x [m/s]")
    vy_min_mps: FiniteFloat = Field(-1.5, description="lower bound of v_y [m/s]")
    vy_max_mps: FiniteFloat = Field(1.5, description="upper bound of v_y [m/s]")
    r_min_radps: FiniteFloat = Field(-0.55, description="lower bound of the yaw rate r [rad/s]")
    r_max_radps: FiniteFloat = Field(0.55, description="upper bound of the yaw rate r [rad/s]")
    steer_max_rad: Annotated[float, Field(gt=0, le=1.0, allow_inf_nan=False)] = Field(
        STEER_MAX_DEFAULT_RAD,
        description="bound of |delta|, the applied road-wheel angle; used only by the cornering-drag term, "
        "whose DMVT bounds grow with it [rad]",
    )

    front_lateral_force_max_n: Annotated[float, Field(gt=0, allow_inf_nan=False)] | None = Field(
        None,
        description="bound of |F_yf|, the front axle's lateral force, in the operating domain (at most the "
        "grip, about mu m g l_r / L); tightens the cornering drag's DMVT bounds. None: what the box of v_y, r, "
        "v_x and delta allows [N]",
    )

    @model_validator(mode="after")
    def _lower_below_upper(self) -> OperatingBounds:
        for name in ("vx", "vy", "r"):
            unit = "radps" if name == "r" else "mps"
            low = getattr(self, f"{name}_min_{unit}")
            high = getattr(self, f"{name}_max_{unit}")
            if not low < high:
                raise ValueError(f"{name}_min_{unit} must be below {name}_max_{unit}, got {low} >= {high}")
        return self

    def hashed(self) -> dict[str, Any]:
        """The bounds as the gains' content hash sees them: the steering and front-force bounds only when they are
        not their defaults, so gains designed before they existed keep their hash."""
        data = self.model_dump()
        if data["steer_max_rad"] == STEER_MAX_DEFAULT_RAD:
            del data["steer_max_rad"]
        if data["front_lateral_force_max_n"] is None:
            del data["front_lateral_force_max_n"]
        return data

    @property
    def inverse_speed_bounds(self) -> tuple[float, float]:
        """Bounds of the premise V_x = 1/v_x [s/m], lower first."""
        return 1.0 / self.vx_max_mps, 1.0 / self.vx_min_mps

    @property
    def yaw_rate_bounds(self) -> tuple[float, float]:
        """Bounds of the premise r [rad/s], lower first."""
        return self.r_min_radps, self.r_max_radps

    @property
    def lateral_speed_bounds(self) -> tuple[float, float]:
        """Bounds of v_y [m/s], lower first."""
        return self.vy_min_mps, self.vy_max_mps
