"""Vehicle parameters (Table 1) and operating bounds (eq. 13).

Field names say what a quantity is and carry its unit; the paper's symbol is
given in each description and by :meth:`VehicleParams.symbols`. Both models
are frozen and validated: an error names the field and the value.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, model_validator

PositiveFloat = Annotated[float, Field(gt=0, allow_inf_nan=False)]
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]


class VehicleParams(BaseModel):
    """Physical parameters of the 2-DOF vehicle model (Table 1, eq. 5, eq. 12)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    mass_kg: PositiveFloat = Field(1481.0, description="M_v, vehicle mass [kg]")
    longitudinal_inertia_kgm2: PositiveFloat = Field(
        443.0, description="I_e, effective longitudinal inertia seen by the engine torque [kg m^2]"
    )
    yaw_inertia_kgm2: PositiveFloat = Field(1807.0, description="I_z, yaw moment of inertia [kg m^2]")
    front_axle_distance_m: PositiveFloat = Field(1.12, description="l_f, centre of gravity to front axle [m]")
    rear_axle_distance_m: PositiveFloat = Field(1.5, description="l_r, centre of gravity to rear axle [m]")
    front_cornering_stiffness_npr: PositiveFloat = Field(
        57110.0, description="C_f, front axle cornering stiffness [N/rad]"
    )
    rear_cornering_stiffness_npr: PositiveFloat = Field(
        58100.0, description="C_r, rear axle cornering stiffness [N/rad]"
    )
    longitudinal_drag_coeff: PositiveFloat = Field(
        0.37, description="C_x, longitudinal aerodynamic drag coefficient [N s^2/m^2]"
    )
    lateral_drag_coeff: PositiveFloat = Field(0.42, description="C_y, lateral aerodynamic drag coefficient [N s^2/m^2]")
    torque_fault_gain: PositiveFloat = Field(1.0, description="b_T, actuator gain of the torque fault (eq. 5) [-]")
    steer_fault_gain: PositiveFloat = Field(1.0, description="b_delta, actuator gain of the steering fault (eq. 5) [-]")
    sample_period_s: Annotated[float, Field(gt=0, le=1.0, allow_inf_nan=False)] = Field(
        0.01, description="s, sampling period of the Euler discretisation (eq. 12) [s]"
    )

    def symbols(self) -> dict[str, float]:
        """The parameters under the paper's symbols (M_v, I_e, ...)."""
        return {
            "M_v": self.mass_kg,
            "I_e": self.longitudinal_inertia_kgm2,
            "I_z": self.yaw_inertia_kgm2,
            "l_f": self.front_axle_distance_m,
            "l_r": self.rear_axle_distance_m,
            "C_f": self.front_cornering_stiffness_npr,
            "C_r": self.rear_cornering_stiffness_npr,
            "C_x": self.longitudinal_drag_coeff,
            "C_y": self.lateral_drag_coeff,
            "b_T": self.torque_fault_gain,
            "b_delta": self.steer_fault_gain,
            "s": self.sample_period_s,
        }


class OperatingBounds(BaseModel):
    """The operating set S_x of eq. (13): the box the design is certified on."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    vx_min_mps: PositiveFloat = Field(5.0, description="lower bound of v_x [m/s]")
    vx_max_mps: PositiveFloat = Field(30.0, description="upper bound of v_x [m/s]")
    vy_min_mps: FiniteFloat = Field(-1.5, description="lower bound of v_y [m/s]")
    vy_max_mps: FiniteFloat = Field(1.5, description="upper bound of v_y [m/s]")
    r_min_radps: FiniteFloat = Field(-0.55, description="lower bound of the yaw rate r [rad/s]")
    r_max_radps: FiniteFloat = Field(0.55, description="upper bound of the yaw rate r [rad/s]")

    @model_validator(mode="after")
    def _lower_below_upper(self) -> OperatingBounds:
        for name in ("vx", "vy", "r"):
            unit = "radps" if name == "r" else "mps"
            low = getattr(self, f"{name}_min_{unit}")
            high = getattr(self, f"{name}_max_{unit}")
            if not low < high:
                raise ValueError(f"{name}_min_{unit} must be below {name}_max_{unit}, got {low} >= {high}")
        return self

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

    @property
    def speed_bounds(self) -> tuple[float, float]:
        """Bounds of v_x [m/s], lower first."""
        return self.vx_min_mps, self.vx_max_mps
