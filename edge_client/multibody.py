"""An independent plant: the CommonRoad multi-body vehicle model (MB), driven in closed loop.

The estimator is derived from the 2-DOF model of ``synth/model.py``. To check
that it works on a vehicle it was not derived from, this module simulates the
29-state multi-body model of Althoff and Würsching, *CommonRoad: Vehicle
Models* (2020): ``vehiclemodels.vehicle_dynamics_mb.vehicle_dynamics_mb`` of
the ``commonroad-vehicle-models`` package, unchanged, with its published
parameter sets (1 Ford Escort, 2 BMW 320i, 3 VW Vanagon; 4 is a kinematic
truck without multi-body data). Around it we add only what a real vehicle has
around its body: actuators, a driver (the autonomy stack's controllers) and
sensors, in the project's signal conventions:

* measured y = [v_x, r]: longitudinal speed of the body at the CG [m/s] (MB
  state x4) and yaw rate [rad/s] (x6), each with seeded Gaussian noise;
* demanded u_d = [T_d, delta_d]: total drive torque at the driven wheels
  [N m] (braking negative) and front road-wheel angle [rad], + = left;
* actuator faults f = [T_f, delta_f] of :mod:`edge_client.faults`, f = add(t)
  + gain(t) u_d: applied torque T = T_d + T_f, road-wheel target delta_d + delta_f.

Torque actuator. The MB's input u2 is a longitudinal acceleration, converted
inside to wheel torques T_E = m R_w u2 (drive, a share T_se at the front) or
T_B = m R_w u2 (brake, a share T_sb at the front); the four wheel torques sum
to m R_w u2. A total wheel torque T is therefore u2 = T / (m R_w). The MB
clips u2 (``acceleration_constraints``: |u2| <= a_max, and u2 <= a_max
v_switch / v_x above v_switch, a power limit); the truth records the torque
after that clip, evaluated at the start of each sample.

Steering actuator. The MB's input u1 is the road-wheel steering velocity,
clipped to [v_min, v_max] of ``p.steering`` by the model itself. A position
servo closes the loop inside the ODE: u1 = k_steer (delta_target - x3), so
the road wheels follow their target with a lag of 1 / k_steer and the
model's rate limit.

Integration. The inputs are held over each 10 ms sample and the MB ODE is
integrated with fixed-step RK4 in substeps. The stiffest mode is the wheel
spin: I_y_w dω/dt = -R_w F_x(slip), slip = 1 - R_w ω / v_x, an eigenvalue
of about -WHEEL_MODE_RATE_MPS2 / v_x (larger when braking). The substep count
per sample keeps |λ| h <= RK4_STEP_BUDGET, inside RK4's stability interval
(2.78) with margin: 2 to 10 substeps at 22 to 6 m/s (:func:`simulate_many`
runs drives in parallel processes).

What the MB does that the 2-DOF model does not (measured on sets 1 and 3):

* no aerodynamic drag or rolling resistance: cruising needs no torque;
* the lateral magic formula shifts by sign(camber) (S_hy, S_vy): about ±80 N
  per tyre at zero slip, switching at zero camber. On a straight at zero
  torque the car hunts laterally at 1.75 Hz (v_y ±0.015 m/s, a_y ±0.16
  m/s^2), whatever the step size; in a turn the roll cambers the tyres and
  the shift adds force, so the secant cornering stiffness at 1 m/s^2 is 40
  to 55 % above the tyre's slope, falling to it near 7 m/s^2;
* the longitudinal slip bends the lateral force (S_Vyκ): under drive torque a
  front-driven car (set 1) yaws right, a rear-driven one (set 3) left, about
  0.003 rad/s at 800 N m and 15 m/s, which the path follower's integral removes.
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import math
import multiprocessing
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from edge_client.faults import Fault, fault_tables
from synth.model import FloatArray

#: Sample period of the measurements and of the held inputs [s].
SAMPLE_PERIOD_S = 0.01
#: Parameter sets of commonroad-vehicle-models (4 has no multi-body data and is refused with a message).
PARAMETER_SETS = (1, 2, 3, 4)
#: Gravity of the MB model [m/s^2].
GRAVITY_MPS2 = 9.81
#: Position-servo gain of the steering actuator k_steer [1/s]: a lag of 1/k_steer = 33 ms.
STEER_SERVO_GAIN_PER_S = 30.0
#: |λ| of the wheel-spin mode times v_x that the RK4 substeps are sized for [m/s^2].
WHEEL_MODE_RATE_MPS2 = 12_000.0
#: Largest |λ| h per RK4 substep (RK4 is stable on the negative real axis up to 2.78).
RK4_STEP_BUDGET = 2.0
#: Bounds on the RK4 substeps per sample.
MIN_SUBSTEPS, MAX_SUBSTEPS = 2, 100
#: Below this speed the drive generators refuse to go [m/s].
MIN_DRIVE_SPEED_MPS = 6.0
#: Below this speed a simulation stops with an error: the MB's slip divides by the wheels' ground speeds [m/s].
MIN_SIMULATED_SPEED_MPS = 1.0
#: Default sensor noise: standard deviations of v_x [m/s] and r [rad/s].
DEFAULT_SPEED_SIGMA_MPS = 0.05
DEFAULT_YAW_RATE_SIGMA_RADPS = 0.005
#: Default noise on the reported road grade [rad]: 0.11 degrees, an INS's pitch less the suspension's.
DEFAULT_GRADE_SIGMA_RAD = 0.002

# Indices into the 29-state MB vector (the model's x1..x29 are 0-based here).
_STEER, _VX, _YAW_RATE, _PITCH, _VY, _Z = 2, 3, 5, 8, 10, 11
_Z_FRONT, _Z_REAR, _WHEELS = 16, 21, slice(23, 27)


class MultibodyError(ValueError):
    """A parameter set, drive or option the multi-body plant cannot use."""


# --------------------------------------------------------------------------- library access


class _Library(NamedTuple):
    """The functions of ``vehiclemodels`` this module uses."""

    dynamics: Callable[..., list[float]]
    init_mb: Callable[..., list[float]]
    setup_vehicle_parameters: Callable[..., Any]
    acceleration_constraints: Callable[..., float]


@functools.cache
def _library() -> _Library:
    """Import ``vehiclemodels`` lazily, so that the project runs without it until a plant is needed."""
    try:
        from vehiclemodels.init_mb import init_mb  # type: ignore[import-untyped]
        from vehiclemodels.utils.acceleration_constraints import (  # type: ignore[import-untyped]
            acceleration_constraints,
        )
        from vehiclemodels.vehicle_dynamics_mb import vehicle_dynamics_mb  # type: ignore[import-untyped]
        from vehiclemodels.vehicle_parameters import setup_vehicle_parameters  # type: ignore[import-untyped]
    except ImportError as exc:
        raise ImportError(
            "the multi-body plant needs the CommonRoad vehicle models: install commonroad-vehicle-models "
            "(pip install 'commonroad-vehicle-models>=3.0,<4', part of the project's dev extra)"
        ) from exc
    return _Library(vehicle_dynamics_mb, init_mb, setup_vehicle_parameters, acceleration_constraints)


@dataclass(frozen=True)
class Variant:
    """A physically different vehicle made from a parameter set, to check that calibration and alarms hold beyond
    the vehicles the project is measured on: the sprung mass's centre of gravity moved back along the wheelbase by
    ``cg_back_m`` [m] (forward if negative), the heights of it and of the whole vehicle's scaled by
    ``cg_height_factor``, the tyres' cornering stiffness (the magic formula's p_ky1) scaled by
    ``tyre_stiffness_factor``, the brakes' front share (T_sb) set to ``brake_front_share`` and the drive torque's
    (T_se) to ``drive_front_share`` (1 front-wheel drive, 0 rear-wheel, between: all-wheel), and the road's peak
    friction scaled by ``road_friction`` (the magic formula's p_dx1 and p_dy1, the tyres' peak force per load,
    with its combined-slip weighting rescaled to match, :func:`_tyre_on_road`; their slope at zero slip stays: 0.6
    is about a wet asphalt road). The identity changes nothing."""

    name: str
    cg_back_m: float = 0.0
    cg_height_factor: float = 1.0
    tyre_stiffness_factor: float = 1.0
    brake_front_share: float | None = None
    drive_front_share: float | None = None
    road_friction: float = 1.0

    def apply(self, p: Any) -> Any:
        """The MB parameters ``p`` changed as this variant says; raises :class:`MultibodyError` for a change that
        leaves no vehicle (an axle behind the CG, a height or stiffness not positive, a share outside [0, 1])."""
        values = (self.cg_back_m, self.cg_height_factor, self.tyre_stiffness_factor, self.road_friction)
        if not all(math.isfinite(v) for v in values):
            raise MultibodyError(f"variant {self.name!r}: every change must be finite, got {values}")
        a, b = p.a + self.cg_back_m, p.b - self.cg_back_m
        if not (a > 0.0 and b > 0.0):
            raise MultibodyError(f"variant {self.name!r}: cg_back_m {self.cg_back_m} leaves the CG off the wheelbase")
        if not (self.cg_height_factor > 0.0 and self.tyre_stiffness_factor > 0.0 and self.road_friction > 0.0):
            raise MultibodyError(f"variant {self.name!r}: the height, stiffness and friction factors must be positive")
        brake = p.T_sb if self.brake_front_share is None else self.brake_front_share
        drive = p.T_se if self.drive_front_share is None else self.drive_front_share
        for name, share in (("brake_front_share", brake), ("drive_front_share", drive)):
            if not 0.0 <= share <= 1.0:
                raise MultibodyError(f"variant {self.name!r}: {name} must lie in [0, 1], got {share}")
        return dataclasses.replace(
            p,
            a=a,
            b=b,
            h_s=p.h_s * self.cg_height_factor,
            h_cg=p.h_cg * self.cg_height_factor,
            T_sb=brake,
            T_se=drive,
            tire=_tyre_on_road(
                dataclasses.replace(p.tire, p_ky1=p.tire.p_ky1 * self.tyre_stiffness_factor), self.road_friction
            ),
        )


def _tyre_on_road(tire: Any, friction: float) -> Any:
    """The magic-formula tyre on a road of ``friction`` times the data's: the peak force per load (p_dx1, p_dy1)
    scaled, the slope at zero slip kept, and the combined-slip weighting made friction-similar. That weighting
    reads the slips themselves (B_x_alpha = r_bx1 cos(atan(r_bx2 kappa)) on alpha, B_y_kappa = r_by1
    cos(atan(r_by2 (alpha - r_by3))) on kappa), and with the slope kept a tyre reaches a given share of its
    grip at ``friction`` times the slip: each slip's coefficient is divided by ``friction`` and each slip offset
    multiplied, so that braking takes the same share of the lateral grip at the same share of the longitudinal
    one (as a brush tyre does), not less."""
    if friction == 1.0:
        return tire
    return dataclasses.replace(
        tire,
        p_dx1=tire.p_dx1 * friction,
        p_dy1=tire.p_dy1 * friction,
        r_bx1=tire.r_bx1 / friction,
        r_bx2=tire.r_bx2 / friction,
        r_hx1=tire.r_hx1 * friction,
        r_by1=tire.r_by1 / friction,
        r_by2=tire.r_by2 / friction,
        r_by3=tire.r_by3 * friction,
        r_hy1=tire.r_hy1 * friction,
        r_vy4=tire.r_vy4 / friction,
        r_vy6=tire.r_vy6 / friction,
    )


@functools.cache
def vehicle_parameters(parameter_set: int, variant: Variant | None = None) -> Any:
    """The MB parameters of CommonRoad vehicle ``parameter_set`` (1..4), a ``VehicleParameters`` dataclass,
    changed by ``variant`` if given.

    Raises :class:`MultibodyError` for an unknown id or a set without the
    multi-body parameters (set 4, the kinematic truck).
    """
    if isinstance(parameter_set, bool) or parameter_set not in PARAMETER_SETS:
        raise MultibodyError(f"parameter_set must be one of {PARAMETER_SETS}, got {parameter_set!r}")
    p = _library().setup_vehicle_parameters(vehicle_id=parameter_set)
    missing = [f.name for f in dataclasses.fields(p) if getattr(p, f.name) is None]
    if missing:
        raise MultibodyError(
            f"parameter set {parameter_set} lacks multi-body parameters ({', '.join(missing)}); "
            "the multi-body plant needs a passenger-car set"
        )
    return p if variant is None else variant.apply(p)


def loaded_parameters(parameter_set: int, payload_kg: float, variant: Variant | None = None) -> Any:
    """The MB parameters of ``parameter_set`` carrying ``payload_kg`` [kg] spread like its body: the sprung mass
    grows by the payload at the same centre of gravity, and its inertias (and the vehicle's yaw inertia) with
    it in proportion (the same radii of gyration). The set's own parameters (of ``variant`` if given) for no
    payload.

    Raises :class:`MultibodyError` for a payload that is negative or not finite.
    """
    if not (math.isfinite(payload_kg) and payload_kg >= 0.0):
        raise MultibodyError(f"payload_kg must be finite and >= 0, got {payload_kg!r}")
    p = vehicle_parameters(parameter_set, variant)
    if payload_kg == 0.0:
        return p
    body = (p.m_s + payload_kg) / p.m_s
    return dataclasses.replace(
        p,
        m=p.m + payload_kg,
        m_s=p.m_s + payload_kg,
        I_z=p.I_z * (p.m + payload_kg) / p.m,
        I_Phi_s=p.I_Phi_s * body,
        I_y_s=p.I_y_s * body,
        I_xz_s=p.I_xz_s * body,
    )


# --------------------------------------------------------------------------- reference values


def static_tyre_loads_n(parameter_set: int, variant: Variant | None = None) -> tuple[float, float]:
    """Static vertical load of one front and one rear tyre, (F_z,f, F_z,r) [N].

    These are the loads of ``init_mb``'s initial state: F_z = K_zt z_u with
    z_u = F0_z / (2 K_zt), F0_z,f = m_s g b / (a + b) + m_uf g (front axle) and
    F0_z,r = m_s g a / (a + b) + m_ur g (rear axle), i.e. the static axle
    loads halved. They are also the loads of the MB's static equilibrium
    (sprung mass settled), which :func:`initial_state` starts from.
    """
    p = vehicle_parameters(parameter_set, variant)
    wheelbase = p.a + p.b
    front_axle = p.m_s * GRAVITY_MPS2 * p.b / wheelbase + p.m_uf * GRAVITY_MPS2
    rear_axle = p.m_s * GRAVITY_MPS2 * p.a / wheelbase + p.m_ur * GRAVITY_MPS2
    return front_axle / 2.0, rear_axle / 2.0


def reference_values(parameter_set: int, variant: Variant | None = None) -> dict[str, float]:
    """What a calibration on this vehicle should find, from the MB's own parameters.

    * ``mass_kg`` m, ``yaw_inertia_kgm2`` I_z, ``front_axle_distance_m`` a,
      ``rear_axle_distance_m`` b, ``wheel_radius_m`` R_w: the MB's p.m, p.I_z,
      p.a, p.b, p.R_w (a, b and I_z refer to the sprung mass's CG, the MB's
      reference point for the planar motion); ``cg_height_m`` h, the MB's p.h_cg
      (the whole vehicle's centre of gravity, which the load transfer moves).
    * ``effective_mass_kg`` = m + 4 I_y_w / R_w^2: each wheel obeys
      I_y_w dω_i/dt = -R_w F_x,i + T_i and the T_i sum to T. Rolling at a
      settled slip, dω_i/dt = a_x / R_w, so sum F_x,i = T / R_w - 4 I_y_w a_x / R_w^2;
      with m a_x = sum F_x,i on a straight (the MB has no drag or rolling
      resistance), a_x = T / (R_w (m + 4 I_y_w / R_w^2)).
    * ``front_cornering_stiffness_npr``, ``rear_cornering_stiffness_npr``:
      PER TYRE (the project's F_yf = 2 C_f (...)), the slope |dF_y/dα| at α = 0
      and zero camber of the MB's lateral magic formula
      (``tire_model.formula_lateral``) at the static tyre load of
      :func:`static_tyre_loads_n`. There S_hy = S_vy = 0 and the slope is
      B_y C_y D_y = K_y = p_ky1 F_z, so C = |p_ky1| F_z.

    Units [kg], [kg m^2], [m], [N/rad].
    """
    p = vehicle_parameters(parameter_set, variant)
    front_load, rear_load = static_tyre_loads_n(parameter_set, variant)
    return {
        "mass_kg": float(p.m),
        "effective_mass_kg": float(p.m + 4.0 * p.I_y_w / p.R_w**2),
        "wheel_radius_m": float(p.R_w),
        "yaw_inertia_kgm2": float(p.I_z),
        "front_axle_distance_m": float(p.a),
        "rear_axle_distance_m": float(p.b),
        "cg_height_m": float(p.h_cg),
        # K_y = p_ky1 F_z: the slope of the lateral magic formula at α = 0, γ = 0
        "front_cornering_stiffness_npr": float(abs(p.tire.p_ky1) * front_load),
        "rear_cornering_stiffness_npr": float(abs(p.tire.p_ky1) * rear_load),
    }


def base_profile(parameter_set: int, variant: Variant | None = None) -> dict[str, dict[str, float]]:
    """A ``--params`` profile with only what a vehicle engineer reads off the data sheet.

    ``{"params": {mass_kg, yaw_inertia_kgm2, front_axle_distance_m,
    rear_axle_distance_m, wheel_radius_m, cg_height_m}}``; cornering stiffnesses
    and the longitudinal inertia are left for a calibration to find.
    """
    ref = reference_values(parameter_set, variant)
    names = (
        "mass_kg", "yaw_inertia_kgm2", "front_axle_distance_m", "rear_axle_distance_m", "wheel_radius_m", "cg_height_m"
    )  # fmt: skip
    return {"params": {name: ref[name] for name in names}}


# --------------------------------------------------------------------------- drives


@dataclass(frozen=True, eq=False)  # arrays: compare fields with numpy
class Drive:
    """What the vehicle's planner asks for, sampled every SAMPLE_PERIOD_S, K samples.

    speed_mps (K,) reference speed [m/s]; accel_mps2 (K,) its derivative
    [m/s^2]; curvature_1pm (K,) path curvature kappa [1/m], + = left. The
    reference yaw rate is speed * curvature. grade_rad (K,) the road's grade
    under the vehicle [rad], + uphill (None: level ground; :func:`on_hills`).
    """

    name: str
    speed_mps: FloatArray
    accel_mps2: FloatArray
    curvature_1pm: FloatArray
    grade_rad: FloatArray | None = None

    def __post_init__(self) -> None:
        n = self.speed_mps.shape
        for label in ("speed_mps", "accel_mps2", "curvature_1pm", "grade_rad"):
            value = getattr(self, label)
            if value is None:
                continue
            if value.ndim != 1 or value.shape != n:
                raise MultibodyError(f"Drive.{label}: expected shape {n}, found {value.shape}")
        if n[0] < 2:
            raise MultibodyError(f"Drive {self.name!r}: needs at least 2 samples, found {n[0]}")
        if not np.all(self.speed_mps > 0):
            raise MultibodyError(f"Drive {self.name!r}: speeds must be positive, min {self.speed_mps.min():.3g} m/s")

    @property
    def n_samples(self) -> int:
        return int(self.speed_mps.size)

    @property
    def initial_speed_mps(self) -> float:
        return float(self.speed_mps[0])

    @property
    def t(self) -> FloatArray:
        """Sample times (K,) [s]."""
        return _sample_times(self.n_samples)

    @property
    def yaw_rate_radps(self) -> FloatArray:
        """Reference yaw rate r = v kappa (K,) [rad/s]."""
        return self.speed_mps * self.curvature_1pm

    @property
    def lateral_accel_mps2(self) -> FloatArray:
        """Reference lateral acceleration v^2 kappa (K,) [m/s^2]."""
        return self.speed_mps**2 * self.curvature_1pm


@dataclass(frozen=True, eq=False)  # arrays: compare fields with numpy
class OpenLoopDemand:
    """Demanded inputs applied as they are, without a driver: u (K, 2) = [T_d [N m], delta_d [rad]]."""

    name: str
    initial_speed_mps: float
    u: FloatArray

    def __post_init__(self) -> None:
        if self.u.ndim != 2 or self.u.shape[1] != 2 or self.u.shape[0] < 2:
            raise MultibodyError(f"OpenLoopDemand.u: expected shape (K >= 2, 2), found {self.u.shape}")
        if not self.initial_speed_mps > 0:
            raise MultibodyError(f"OpenLoopDemand.initial_speed_mps must be positive, got {self.initial_speed_mps}")

    @property
    def n_samples(self) -> int:
        return int(self.u.shape[0])


def _sample_times(n_samples: int) -> FloatArray:
    return np.round(np.arange(n_samples) * SAMPLE_PERIOD_S, 9)


def _smoothstep(s: FloatArray) -> FloatArray:
    """3 s^2 - 2 s^3 on [0, 1], clipped: a jerk-limited ramp whose slope peaks at 1.5."""
    s = np.clip(s, 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s)


def _sine_shape(s: FloatArray, periods: int) -> FloatArray:
    """The unit-peak yaw-rate shapes of :meth:`_DriveBuilder.sine` over s = tau / P in [0, periods]."""
    if periods == 1:
        # 2 sin^3(x) cos(x) peaks at 3 sqrt(3) / 8, at x = pi / 3
        return np.sin(2.0 * np.pi * s) * np.sin(np.pi * s) ** 2 / (3.0 * math.sqrt(3.0) / 8.0)
    fade = np.minimum(_smoothstep(2.0 * s), _smoothstep(2.0 * (periods - s)))
    return np.sin(2.0 * np.pi * s) * fade


@dataclass
class _DriveBuilder:
    """Appends manoeuvres to a speed and yaw-rate reference; :meth:`build` cuts it at ``limit_s``.

    Lateral manoeuvres run at constant speed and straight stretches carry the
    speed changes, except :meth:`turn_changing_speed`, which brakes or
    accelerates in a turn. The planner bounds the yaw acceleration by
    min(MAX_YAW_ACCEL, MAX_LATERAL_JERK / v).
    """

    limit_s: float
    speed: list[FloatArray] = field(default_factory=list)
    yaw_rate: list[FloatArray] = field(default_factory=list)
    current_speed_mps: float = 0.0
    elapsed_s: float = 0.0

    MAX_YAW_ACCEL_RADPS2 = 0.6
    MAX_LATERAL_JERK_MPS3 = 6.0

    @property
    def full(self) -> bool:
        return self.elapsed_s >= self.limit_s - 0.5 * SAMPLE_PERIOD_S

    def yaw_accel_limit(self, speed_mps: float) -> float:
        return min(self.MAX_YAW_ACCEL_RADPS2, self.MAX_LATERAL_JERK_MPS3 / speed_mps)

    def _append(self, speed: FloatArray, yaw_rate: FloatArray) -> None:
        self.speed.append(speed)
        self.yaw_rate.append(yaw_rate)
        self.elapsed_s += speed.size * SAMPLE_PERIOD_S
        self.current_speed_mps = float(speed[-1])

    def _tau(self, duration_s: float) -> FloatArray:
        return np.arange(max(round(duration_s / SAMPLE_PERIOD_S), 1)) * SAMPLE_PERIOD_S

    def cruise(self, duration_s: float) -> None:
        tau = self._tau(duration_s)
        self._append(np.full(tau.size, self.current_speed_mps), np.zeros(tau.size))

    def change_speed(self, target_mps: float, peak_accel_mps2: float) -> None:
        """A jerk-limited speed change on a straight, peak |acceleration| ``peak_accel_mps2``."""
        start = self.current_speed_mps
        duration = max(1.5 * abs(target_mps - start) / peak_accel_mps2, SAMPLE_PERIOD_S)
        tau = self._tau(duration + SAMPLE_PERIOD_S)
        self._append(start + (target_mps - start) * _smoothstep(tau / duration), np.zeros(tau.size))

    def turn(self, yaw_rate_radps: float, hold_s: float) -> None:
        """A constant-radius turn: yaw rate ramped in, held for ``hold_s``, ramped out."""
        speed = self.current_speed_mps
        ramp = max(1.5 * abs(yaw_rate_radps) / self.yaw_accel_limit(speed), 0.3)
        tau = self._tau(2.0 * ramp + hold_s)
        shape = np.minimum(_smoothstep(tau / ramp), _smoothstep((tau[-1] - tau) / ramp))
        self._append(np.full(tau.size, speed), yaw_rate_radps * shape)

    def turn_changing_speed(self, lateral_accel_mps2: float, target_mps: float, peak_accel_mps2: float) -> None:
        """Brake (or accelerate) in a turn: the turn ramped in at the current speed to ``lateral_accel_mps2``
        (signed), the speed changed to ``target_mps`` at peak |a_x| ``peak_accel_mps2`` with a_y held (the
        radius tightening when braking, opening when accelerating), the turn ramped out at the new speed."""
        start = self.current_speed_mps
        self.turn_in(lateral_accel_mps2 / start)
        duration = max(1.5 * abs(target_mps - start) / peak_accel_mps2, SAMPLE_PERIOD_S)
        tau = self._tau(duration + SAMPLE_PERIOD_S)
        speed = start + (target_mps - start) * _smoothstep(tau / duration)
        self._append(speed, lateral_accel_mps2 / speed)
        self.turn_in(0.0, lateral_accel_mps2 / target_mps)

    def turn_in(self, yaw_rate_radps: float, from_radps: float = 0.0) -> None:
        """The yaw rate ramped from ``from_radps`` to ``yaw_rate_radps`` at the current speed."""
        speed = self.current_speed_mps
        ramp = max(1.5 * abs(yaw_rate_radps - from_radps) / self.yaw_accel_limit(speed), 0.3)
        tau = self._tau(ramp)
        self._append(np.full(tau.size, speed), from_radps + (yaw_rate_radps - from_radps) * _smoothstep(tau / ramp))

    def sine(self, yaw_rate_radps: float, period_s: float, periods: int) -> None:
        """A lane change (``periods`` = 1) or a slalom of whole periods P, peak yaw rate ``yaw_rate_radps``.

        Lane change: r = A sin(2 pi s) sin^2(pi s) / (3 sqrt(3) / 8), s = tau / P,
        whose heading returns to zero. Slalom: r = A sin(2 pi s), faded in
        and out over half a period. Both start and end with zero yaw
        acceleration; P is lengthened if needed to respect the yaw-acceleration limit.
        """
        speed = self.current_speed_mps
        fine = np.linspace(0.0, periods, 2000 * periods + 1)
        steepest = float(np.abs(np.gradient(_sine_shape(fine, periods), fine)).max())
        period = max(period_s, steepest * abs(yaw_rate_radps) / self.yaw_accel_limit(speed))
        tau = self._tau(period * periods)
        self._append(np.full(tau.size, speed), yaw_rate_radps * _sine_shape(tau / period, periods))

    def build(self, name: str) -> Drive:
        n = round(self.limit_s / SAMPLE_PERIOD_S)
        speed = np.concatenate(self.speed)[:n]
        yaw_rate = np.concatenate(self.yaw_rate)[:n]
        if speed.size < n:
            speed = np.concatenate([speed, np.full(n - speed.size, speed[-1])])
            yaw_rate = np.concatenate([yaw_rate, np.zeros(n - yaw_rate.size)])
        accel = np.gradient(speed, SAMPLE_PERIOD_S)
        return Drive(name=name, speed_mps=speed, accel_mps2=accel, curvature_1pm=yaw_rate / speed)


def combined_drive(
    seed: int,
    duration_s: float,
    *,
    speed_range_mps: tuple[float, float] = (10.0, 22.0),
    lateral_accel_mps2: tuple[float, float] = (2.0, 4.5),
    max_accel_mps2: float = 3.5,
    specific_power_w_per_kg: float = 45.0,
) -> Drive:
    """A seeded drive of braking and accelerating in turns (:meth:`_DriveBuilder.turn_changing_speed`), both ways,
    the speed kept in ``speed_range_mps``, |a_y| drawn in ``lateral_accel_mps2``, the peak |a_x| in [0.4, 1] of
    ``max_accel_mps2`` (accelerating also under ``specific_power_w_per_kg`` / v), straight cruises between. The
    first 2 s are a straight cruise. Deterministic for a seed."""
    low, high = speed_range_mps
    if not MIN_DRIVE_SPEED_MPS <= low < high - 3.0:
        raise MultibodyError(
            f"speed_range_mps must satisfy {MIN_DRIVE_SPEED_MPS} <= low < high - 3, got {speed_range_mps}"
        )
    rng = np.random.default_rng(seed)
    builder = _DriveBuilder(limit_s=duration_s, current_speed_mps=float(rng.uniform(low, high)))
    builder.cruise(2.0)
    while not builder.full:
        speed = builder.current_speed_mps
        braking = speed - low > high - speed
        if braking:
            target = float(rng.uniform(low, speed - 0.5 * (speed - low)))
        else:
            target = float(rng.uniform(speed + 0.5 * (high - speed), high))
        peak = float(rng.uniform(0.4, 1.0) * max_accel_mps2)
        if not braking:
            peak = min(peak, specific_power_w_per_kg / target)
        lateral = float(rng.uniform(*lateral_accel_mps2) * rng.choice([-1.0, 1.0]))
        builder.turn_changing_speed(lateral, target, peak)
        builder.cruise(float(rng.uniform(1.0, 3.0)))
    return builder.build(f"combined_{seed}")


def random_drive(
    seed: int,
    duration_s: float,
    *,
    speed_range_mps: tuple[float, float] = (8.0, 22.0),
    max_lateral_accel_mps2: float = 7.0,
    max_yaw_rate_radps: float = 0.5,
    max_accel_mps2: float = 3.0,
    specific_power_w_per_kg: float = 45.0,
) -> Drive:
    """A seeded random drive: cruise, acceleration and braking on straights; turns, lane changes, slaloms.

    Speeds stay in ``speed_range_mps`` (the lower end at least
    MIN_DRIVE_SPEED_MPS); speed changes peak at |a_x| <= ``max_accel_mps2``
    and accelerations also at a_x v <= ``specific_power_w_per_kg`` (a power
    limit below the MB's a_max v_switch of sets 1 and 3: 55 and 90 W/kg).
    Lateral manoeuvres run at constant speed with |r| <= ``max_yaw_rate_radps``
    and |a_y| = v |r| <= ``max_lateral_accel_mps2``; amplitudes are drawn in
    [0.3, 1] of that limit. The first 2 s are a straight cruise. Deterministic
    for a seed.
    """
    low, high = speed_range_mps
    if not MIN_DRIVE_SPEED_MPS <= low < high:
        raise MultibodyError(f"speed_range_mps must satisfy {MIN_DRIVE_SPEED_MPS} <= low < high, got {speed_range_mps}")
    for label, value in (
        ("duration_s", duration_s),
        ("max_lateral_accel_mps2", max_lateral_accel_mps2),
        ("max_yaw_rate_radps", max_yaw_rate_radps),
        ("max_accel_mps2", max_accel_mps2),
        ("specific_power_w_per_kg", specific_power_w_per_kg),
    ):
        if not value > 0:
            raise MultibodyError(f"{label} must be positive, got {value}")
    rng = np.random.default_rng(seed)
    builder = _DriveBuilder(limit_s=duration_s, current_speed_mps=float(rng.uniform(low, high)))
    builder.cruise(2.0)
    kinds = ("cruise", "accelerate", "brake", "turn", "lane_change", "slalom")
    weights = np.array([0.12, 0.14, 0.14, 0.2, 0.2, 0.2])
    while not builder.full:
        kind = str(rng.choice(kinds, p=weights))
        speed = builder.current_speed_mps
        if kind in ("accelerate", "brake"):
            room_up, room_down = high - speed, speed - low
            going_up = room_up > room_down if min(room_up, room_down) < 2.0 else kind == "accelerate"
            target = float(
                rng.uniform(speed + 0.5 * room_up, high) if going_up else rng.uniform(low, speed - 0.5 * room_down)
            )
            peak = float(rng.uniform(0.3, 1.0) * max_accel_mps2)
            if going_up:
                peak = min(peak, specific_power_w_per_kg / target)
            builder.change_speed(target, peak)
            continue
        if kind == "cruise":
            builder.cruise(float(rng.uniform(1.0, 5.0)))
            continue
        limit = min(max_yaw_rate_radps, max_lateral_accel_mps2 / speed)
        amplitude = float(rng.uniform(0.3, 1.0) * limit * rng.choice([-1.0, 1.0]))
        if kind == "turn":
            builder.turn(amplitude, hold_s=float(rng.uniform(2.0, 8.0)))
        elif kind == "lane_change":
            builder.sine(amplitude, period_s=float(rng.uniform(3.0, 6.0)), periods=1)
        else:
            builder.sine(amplitude, period_s=float(rng.uniform(2.5, 6.0)), periods=int(rng.integers(2, 5)))
        builder.cruise(float(rng.uniform(0.5, 2.0)))
    return builder.build(f"random_{seed}")


def straight_drive(speed_mps: float, duration_s: float) -> Drive:
    """Cruise straight at ``speed_mps`` for ``duration_s``."""
    builder = _DriveBuilder(limit_s=duration_s, current_speed_mps=speed_mps)
    builder.cruise(duration_s)
    return builder.build(f"straight_{speed_mps:g}mps")


def steady_turn_drive(speed_mps: float, lateral_accel_mps2: float, duration_s: float) -> Drive:
    """A straight second, then a constant-radius turn at ``lateral_accel_mps2`` (+ = left) to the end."""
    builder = _DriveBuilder(limit_s=duration_s, current_speed_mps=speed_mps)
    builder.cruise(1.0)
    builder.turn(lateral_accel_mps2 / speed_mps, hold_s=duration_s)
    return builder.build(f"turn_{speed_mps:g}mps_{lateral_accel_mps2:g}mps2")


def calibration_drive() -> Drive:
    """About two minutes of ordinary driving that excites every parameter, the same every time.

    Speed changes between 10 and 20 m/s (up to 2.5 m/s^2 accelerating, 3 m/s^2
    braking), steady turns both ways at 3 to 5 m/s^2 entered as quickly as the
    planner's yaw-acceleration limit allows (step steers of a road vehicle),
    lane changes and slaloms, at 10, 12, 15, 16 and 20 m/s; a final cruise
    fills the two minutes.
    """
    b = _DriveBuilder(limit_s=120.0, current_speed_mps=10.0)
    b.cruise(2.0)
    # 10 m/s: steady turns both ways, a lane change, a slalom
    b.turn(0.3, hold_s=3.0)
    b.cruise(1.0)
    b.turn(-0.45, hold_s=3.0)
    b.cruise(1.0)
    b.sine(0.3, period_s=5.0, periods=1)
    b.sine(0.3, period_s=3.0, periods=2)
    b.cruise(1.0)
    b.change_speed(15.0, 2.5)
    b.cruise(1.0)
    # 15 m/s
    b.turn(-0.2, hold_s=3.0)
    b.cruise(1.0)
    b.turn(0.33, hold_s=3.0)
    b.cruise(1.0)
    b.sine(0.2, period_s=5.0, periods=1)
    b.sine(-0.25, period_s=3.0, periods=2)
    b.cruise(1.0)
    b.change_speed(10.0, 3.0)
    b.cruise(1.0)
    b.change_speed(20.0, 2.0)
    b.cruise(1.0)
    # 20 m/s
    b.turn(0.15, hold_s=3.0)
    b.cruise(1.0)
    b.turn(-0.25, hold_s=3.0)
    b.cruise(1.0)
    b.sine(0.12, period_s=5.0, periods=1)
    b.sine(0.15, period_s=3.0, periods=2)
    b.cruise(1.0)
    # 12 m/s: a slalom after braking, then accelerating into a turn
    b.change_speed(12.0, 3.0)
    b.cruise(1.0)
    b.sine(-0.3, period_s=3.0, periods=2)
    b.cruise(1.0)
    b.change_speed(16.0, 2.0)
    b.turn(0.3, hold_s=2.0)
    b.cruise(120.0)
    return b.build("calibration")


#: Steepest grade of :func:`on_hills` by default [rad]: 6 %, a steep main road or a warehouse ramp.
HILL_GRADE_RAD = 0.06
#: How long :func:`on_hills` holds a grade [s] (uniform in this range) and takes to change it [s].
HILL_HOLD_S, HILL_CHANGE_S = (8.0, 25.0), 5.0


def on_hills(drive: Drive, rng: np.random.Generator, max_grade_rad: float = HILL_GRADE_RAD) -> Drive:
    """``drive`` on a road that climbs and descends: grades uniform in +-``max_grade_rad``, each held for
    HILL_HOLD_S and reached over HILL_CHANGE_S with a smooth ramp, level for the first HILL_HOLD_S[0]."""
    if not 0.0 < max_grade_rad < 0.5:
        raise MultibodyError(f"max_grade_rad must be in (0, 0.5) rad, got {max_grade_rad}")
    t = drive.t
    grade = np.zeros_like(t)
    start, level = HILL_HOLD_S[0], 0.0
    while start < t[-1]:
        target = float(rng.uniform(-max_grade_rad, max_grade_rad))
        ramp = _smoothstep((t - start) / HILL_CHANGE_S)
        hold_end = start + HILL_CHANGE_S + float(rng.uniform(*HILL_HOLD_S))
        inside = t >= start
        grade[inside] = level + (target - level) * ramp[inside]
        start, level = hold_end, target
    return dataclasses.replace(drive, name=f"{drive.name}_hills", grade_rad=grade)


#: Deterministic drives by name (each a function of no arguments).
NAMED_DRIVES: dict[str, Callable[[], Drive]] = {
    "calibration": calibration_drive,
    "straight_15": lambda: straight_drive(15.0, 20.0),
    "turn_15_left": lambda: steady_turn_drive(15.0, 4.0, 20.0),
}


def named_drive(name: str) -> Drive:
    """One of :data:`NAMED_DRIVES`; an unknown name raises :class:`MultibodyError` listing the known ones."""
    try:
        make = NAMED_DRIVES[name]
    except KeyError:
        raise MultibodyError(f"unknown drive {name!r}; known: {', '.join(sorted(NAMED_DRIVES))}") from None
    return make()


# --------------------------------------------------------------------------- driver and sensors


@dataclass(frozen=True)
class SensorNoise:
    """Seeded Gaussian noise on the measured v_x [m/s] and r [rad/s] and, on a drive with a grade, on the grade
    the vehicle reports [rad] (standard deviations)."""

    speed_sigma_mps: float = DEFAULT_SPEED_SIGMA_MPS
    yaw_rate_sigma_radps: float = DEFAULT_YAW_RATE_SIGMA_RADPS
    grade_sigma_rad: float = DEFAULT_GRADE_SIGMA_RAD


@dataclass(frozen=True)
class DriverTuning:
    """The autonomy stack's speed and path-following controllers (100 Hz, on measured signals).

    Speed: T_d = m_nom R_w (a_ref + kp e + ki ∫e), e = v_ref - v_meas, with
    m_nom = ``nominal_mass_factor`` m (the data-sheet mass plus a textbook
    share for the rotating parts), clipped to ``torque_margin`` times the
    powertrain's limit so that healthy driving never reaches the MB's clip.
    Path: delta_d = L kappa + (L / v_meas) (kp e_r + ki ∫e_r), e_r = kappa v_meas
    - r_meas: the kinematic angle plus feedback on the yaw rate, converted to
    a curvature error so that the loop gain does not change with speed; the
    integral removes understeer and a constant steering bias, as a path
    follower does. The measured yaw rate passes a first-order filter of
    ``yaw_rate_filter_s``; the speed, one of ``speed_filter_s`` around a
    prediction with the last commanded acceleration (so that it does not lag
    while accelerating).
    """

    speed_kp_per_s: float = 1.5
    speed_ki_per_s2: float = 0.6
    yaw_kp: float = 2.5
    yaw_ki_per_s: float = 1.0
    speed_filter_s: float = 0.1
    yaw_rate_filter_s: float = 0.03
    nominal_mass_factor: float = 1.04
    torque_margin: float = 0.95
    steer_margin: float = 0.9


class _Driver:
    """Speed PI with feed-forward and a yaw-rate path follower; see :class:`DriverTuning`."""

    def __init__(self, p: Any, tuning: DriverTuning, drive: Drive) -> None:
        self.tuning = tuning
        self.drive = drive
        self.wheelbase_m = float(p.a + p.b)
        self.torque_per_accel = tuning.nominal_mass_factor * p.m * p.R_w
        self.limit_torque_per_accel = p.m * p.R_w
        self.a_max = float(p.longitudinal.a_max)
        self.v_switch = float(p.longitudinal.v_switch)
        self.steer_limit_rad = tuning.steer_margin * float(p.steering.max)
        self.speed_alpha = SAMPLE_PERIOD_S / (tuning.speed_filter_s + SAMPLE_PERIOD_S)
        self.yaw_rate_alpha = SAMPLE_PERIOD_S / (tuning.yaw_rate_filter_s + SAMPLE_PERIOD_S)
        self.speed_mps = math.nan  # set by the first measurement
        self.yaw_rate_radps = 0.0
        self.speed_integral = 0.0
        self.commanded_accel_mps2 = 0.0
        self.steer_integral = 0.0

    def torque_limits(self, speed_mps: float) -> tuple[float, float]:
        """The powertrain's torque range at ``speed_mps`` times the margin [N m]."""
        accel_limit = self.a_max if speed_mps <= self.v_switch else self.a_max * self.v_switch / speed_mps
        margin = self.tuning.torque_margin * self.limit_torque_per_accel
        return -margin * self.a_max, margin * accel_limit

    def command(self, k: int, y_speed: float, y_yaw_rate: float) -> tuple[float, float]:
        g, dt = self.tuning, SAMPLE_PERIOD_S
        if math.isnan(self.speed_mps):
            self.speed_mps, self.yaw_rate_radps = y_speed, y_yaw_rate
        # speed estimate: predicted with the last commanded acceleration, corrected by the measurement
        self.speed_mps += self.commanded_accel_mps2 * dt
        self.speed_mps += self.speed_alpha * (y_speed - self.speed_mps)
        self.yaw_rate_radps += self.yaw_rate_alpha * (y_yaw_rate - self.yaw_rate_radps)
        speed = max(self.speed_mps, 1.0)
        # speed: feed-forward of the reference acceleration plus PI
        error = float(self.drive.speed_mps[k]) - speed
        accel = float(self.drive.accel_mps2[k]) + g.speed_kp_per_s * error + self.speed_integral
        if self.drive.grade_rad is not None:  # the grade's feed-forward (the stack knows its road)
            accel += GRAVITY_MPS2 * math.sin(float(self.drive.grade_rad[k]))
        low, high = self.torque_limits(speed)
        torque = self.torque_per_accel * accel
        if low < torque < high or (torque >= high and error < 0) or (torque <= low and error > 0):
            self.speed_integral += g.speed_ki_per_s2 * error * dt
        torque = min(max(torque, low), high)
        self.commanded_accel_mps2 = torque / self.torque_per_accel
        # path: kinematic angle L kappa plus PI on the yaw rate, as a curvature error
        curvature = float(self.drive.curvature_1pm[k])
        scale = self.wheelbase_m / speed
        yaw_error = curvature * speed - self.yaw_rate_radps
        steer = self.wheelbase_m * curvature + scale * g.yaw_kp * yaw_error + self.steer_integral
        if abs(steer) < self.steer_limit_rad or steer * yaw_error < 0:
            self.steer_integral += scale * g.yaw_ki_per_s * yaw_error * dt
        steer = min(max(steer, -self.steer_limit_rad), self.steer_limit_rad)
        return torque, steer


# --------------------------------------------------------------------------- simulation


@dataclass(frozen=True, eq=False)  # arrays: compare fields with numpy
class MultibodyRun:
    """One simulated drive of the MB plant, K samples every SAMPLE_PERIOD_S.

    Signals: t (K,) [s]; y (K, 2) measured [v_x m/s, r rad/s]; u (K, 2)
    demanded [T_d N m, delta_d rad]. Truth: x_true (K, 3) = [v_x, v_y, r] at
    the CG in the body frame [m/s, m/s, rad/s] (MB states x4, x11, x6);
    torque_nm (K,) applied wheel torque after the MB's acceleration clip;
    steer_rad (K,) applied road-wheel angle (MB state x3); f (K, 2) true faults
    = applied minus demanded [T - T_d, delta_target - delta_d]; a_x, a_y (K,)
    body accelerations [m/s^2] (a_x = dv_x/dt - r v_y, a_y = dv_y/dt + r v_x);
    grade_rad (K,) the road grade the vehicle reports [rad] (the drive's, with
    the sensor's noise; None on level ground).
    Row k is the state at t_k and the inputs held over [t_k, t_k+1).
    """

    name: str
    parameter_set: int
    seed: int
    t: FloatArray
    y: FloatArray
    u: FloatArray
    x_true: FloatArray
    torque_nm: FloatArray
    steer_rad: FloatArray
    f: FloatArray
    a_x: FloatArray
    a_y: FloatArray
    grade_rad: FloatArray | None = None

    def __len__(self) -> int:
        return int(self.t.size)

    def to_csv(self, path: str | Path) -> None:
        """Write the replay format (edge_client.recording) plus truth columns, floats at full precision.

        Columns: t, vx, r, torque, steer, vx_true, vy_true, r_true, torque_fault, steer_fault, ay, and grade (the
        reported road grade) on a drive with one.
        """
        header: tuple[str, ...] = (
            "t",
            "vx",
            "r",
            "torque",
            "steer",
            "vx_true",
            "vy_true",
            "r_true",
            "torque_fault",
            "steer_fault",
            "ay",
        )
        columns = [self.t, self.y, self.u, self.x_true, self.f, self.a_y]
        if self.grade_rad is not None:
            header += ("grade",)
            columns.append(self.grade_rad)
        table = np.column_stack(columns).tolist()
        with Path(path).open("w", newline="") as handle:
            writer = csv.writer(handle)
            writer.writerow(header)
            writer.writerows([repr(float(v)) for v in row] for row in table)


def initial_state(
    parameter_set: int, speed_mps: float, payload_kg: float = 0.0, variant: Variant | None = None
) -> FloatArray:
    """The MB state (29,) of ``init_mb`` at ``speed_mps``, straight, with the sprung mass at rest on its springs.

    ``init_mb`` leaves the sprung mass at z = 0 and zero pitch while the
    unsprung masses sit at their static tyre deflection, so the body would
    bounce at the start. We place it where every suspension deflection
    z_S = z_u - z_s + (a or -b) theta is zero: theta = (z_r - z_f) / (a + b),
    z_s = z_f + a theta (then camber and suspension forces are static).
    """
    p = loaded_parameters(parameter_set, payload_kg, variant)
    x = np.array(_library().init_mb([0.0, 0.0, 0.0, speed_mps, 0.0, 0.0, 0.0], p), dtype=float)
    x[_PITCH] = (x[_Z_REAR] - x[_Z_FRONT]) / (p.a + p.b)
    x[_Z] = x[_Z_FRONT] + p.a * x[_PITCH]
    return x


def substeps_for(speed_mps: float) -> int:
    """RK4 substeps per sample at ``speed_mps`` so that |λ_wheel| h <= RK4_STEP_BUDGET."""
    rate = WHEEL_MODE_RATE_MPS2 / max(abs(speed_mps), 0.5)
    n = math.ceil(SAMPLE_PERIOD_S * rate / RK4_STEP_BUDGET)
    return min(max(n, MIN_SUBSTEPS), MAX_SUBSTEPS)


def _hold_sample(
    dynamics: Callable[..., list[float]],
    p: Any,
    x: FloatArray,
    steer_target: float,
    accel: float,
    steer_gain: float,
    grade_accel: float = 0.0,
) -> tuple[FloatArray, FloatArray]:
    """Integrate the MB over one sample with the inputs held; return (x at t_k+1, dx/dt at t_k). ``grade_accel``
    = g sin(grade) [m/s^2] pulls the whole mass back along the body's x axis (the MB's equation for v_x)."""

    def rhs(state: FloatArray) -> FloatArray:
        values = state.tolist()
        # steering servo: u1 = k_steer (delta_target - x3); the MB clips the rate
        d = np.array(dynamics(values, [steer_gain * (steer_target - values[_STEER]), accel], p))
        if grade_accel:
            d[_VX] -= grade_accel
        return d

    n = substeps_for(float(x[_VX]))
    h = SAMPLE_PERIOD_S / n
    first = rhs(x)
    k1 = first
    for i in range(n):
        if i:
            k1 = rhs(x)
        k2 = rhs(x + (0.5 * h) * k1)
        k3 = rhs(x + (0.5 * h) * k2)
        k4 = rhs(x + h * k3)
        x = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        # the MB forbids negative wheel spin (it clamps its own copy of the state)
        np.maximum(x[_WHEELS], 0.0, out=x[_WHEELS])
    return x, first


def _check_drivable(x: FloatArray, t_s: float, drive: Drive | OpenLoopDemand) -> None:
    """Raise :class:`MultibodyError` if the state left the model's range (too slow, or not finite)."""
    if not np.isfinite(x).all():
        raise MultibodyError(f"{drive.name}: the multi-body state is not finite at t = {t_s:.2f} s")
    if x[_VX] < MIN_SIMULATED_SPEED_MPS:
        raise MultibodyError(
            f"{drive.name}: v_x fell to {x[_VX]:.3g} m/s at t = {t_s:.2f} s, below {MIN_SIMULATED_SPEED_MPS} m/s "
            "where the multi-body plant stops (its longitudinal slip divides by the wheels' ground speed)"
        )


def _table_demand(table: FloatArray) -> Callable[[int, float, float], tuple[float, float]]:
    """An open-loop 'driver' that reads row k of ``table`` (K, 2) whatever it measures."""

    def command(k: int, y_speed: float, y_yaw_rate: float) -> tuple[float, float]:
        return float(table[k, 0]), float(table[k, 1])

    return command


def simulate(
    drive: Drive | OpenLoopDemand,
    parameter_set: int = 1,
    *,
    faults: Sequence[Fault] = (),
    seed: int = 0,
    noise: SensorNoise = SensorNoise(),
    driver: DriverTuning = DriverTuning(),
    steer_gain_per_s: float = STEER_SERVO_GAIN_PER_S,
    payload_kg: float = 0.0,
    variant: Variant | None = None,
) -> MultibodyRun:
    """Simulate the MB of ``parameter_set`` (changed by ``variant`` if given) along ``drive`` with ``faults``;
    ``seed`` drives the sensor noise; the vehicle carries ``payload_kg`` (:func:`loaded_parameters`).

    A :class:`Drive` is followed by the closed-loop driver; an
    :class:`OpenLoopDemand` is applied as it is. At each sample t_k the
    sensors measure, the driver demands u_d, the faults act, and the MB is
    integrated to t_k+1 with the inputs held (see the module docstring).
    """
    lib = _library()
    p = loaded_parameters(parameter_set, payload_kg, variant)
    if not steer_gain_per_s > 0:
        raise MultibodyError(f"steer_gain_per_s must be positive, got {steer_gain_per_s}")
    n = drive.n_samples
    t = _sample_times(n)
    fault_add, fault_gain = fault_tables(tuple(faults), t)
    rng = np.random.default_rng(seed)
    sensor = rng.standard_normal((n, 2)) * np.array([noise.speed_sigma_mps, noise.yaw_rate_sigma_radps])
    demand = _Driver(p, driver, drive).command if isinstance(drive, Drive) else _table_demand(drive.u)
    accel_per_torque = 1.0 / (p.m * p.R_w)
    grade = drive.grade_rad if isinstance(drive, Drive) else None
    grade_accel = np.zeros(n) if grade is None else GRAVITY_MPS2 * np.sin(grade)
    reported_grade = None if grade is None else grade + rng.standard_normal(n) * noise.grade_sigma_rad

    x = initial_state(parameter_set, drive.initial_speed_mps, payload_kg, variant)
    states = np.zeros((n, 29))
    derivatives = np.zeros((n, 29))
    y = np.zeros((n, 2))
    u = np.zeros((n, 2))
    torque_applied = np.zeros(n)
    steer_target = np.zeros(n)
    for k in range(n):
        _check_drivable(x, float(t[k]), drive)
        y[k] = (x[_VX] + sensor[k, 0], x[_YAW_RATE] + sensor[k, 1])
        u[k] = demand(k, float(y[k, 0]), float(y[k, 1]))
        # f = add + gain u_d: T = T_d + T_f, delta_target = delta_d + delta_f
        applied = u[k] + fault_add[k] + fault_gain[k] * u[k]
        torque, steer_target[k] = float(applied[0]), applied[1]
        # u2 = T / (m R_w); the MB clips it, the truth keeps the clipped torque
        demanded_accel = torque * accel_per_torque
        accel = float(lib.acceleration_constraints(float(x[_VX]), demanded_accel, p.longitudinal))
        torque_applied[k] = torque if accel == demanded_accel else accel / accel_per_torque
        states[k] = x
        try:
            x, derivatives[k] = _hold_sample(
                lib.dynamics, p, x, float(steer_target[k]), accel, steer_gain_per_s, float(grade_accel[k])
            )
        except ZeroDivisionError as exc:  # the MB's slips divide by each wheel's ground speed
            raise MultibodyError(
                f"{getattr(drive, 'name', 'drive')}: a wheel's ground speed reached 0 at t = {t[k]:.2f} s (the "
                "vehicle slid or spun beyond its tyres' grip, where the multi-body plant stops)"
            ) from exc

    v_x, v_y, r = states[:, _VX], states[:, _VY], states[:, _YAW_RATE]
    return MultibodyRun(
        name=getattr(drive, "name", "drive"),
        parameter_set=parameter_set,
        seed=seed,
        t=t,
        y=y,
        u=u,
        x_true=np.column_stack([v_x, v_y, r]),
        torque_nm=torque_applied,
        steer_rad=states[:, _STEER],
        f=np.column_stack([torque_applied - u[:, 0], steer_target - u[:, 1]]),
        a_x=derivatives[:, _VX] - r * v_y,
        a_y=derivatives[:, _VY] + r * v_x,
        grade_rad=reported_grade,
    )


@dataclass(frozen=True)
class MultibodyJob:
    """The arguments of one :func:`simulate` call, for :func:`simulate_many`."""

    drive: Drive | OpenLoopDemand
    parameter_set: int = 1
    faults: tuple[Fault, ...] = ()
    seed: int = 0
    noise: SensorNoise = SensorNoise()
    driver: DriverTuning = DriverTuning()
    steer_gain_per_s: float = STEER_SERVO_GAIN_PER_S
    payload_kg: float = 0.0
    variant: Variant | None = None


def run_job(job: MultibodyJob) -> MultibodyRun:
    """:func:`simulate` with the arguments of ``job``."""
    return simulate(
        job.drive,
        job.parameter_set,
        faults=job.faults,
        seed=job.seed,
        noise=job.noise,
        driver=job.driver,
        steer_gain_per_s=job.steer_gain_per_s,
        payload_kg=job.payload_kg,
        variant=job.variant,
    )


def simulate_many(jobs: Sequence[MultibodyJob], workers: int = 2) -> list[MultibodyRun]:
    """Run the jobs in up to ``workers`` processes (spawned, so safe beside threads); results in job order.

    ``workers=1`` runs them here, one after another. Each run is deterministic,
    so the results do not depend on the number of workers.
    """
    if workers < 1:
        raise MultibodyError(f"workers must be at least 1, got {workers}")
    if workers == 1 or len(jobs) <= 1:
        return [run_job(job) for job in jobs]
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=min(workers, len(jobs)), mp_context=context) as pool:
        return list(pool.map(run_job, jobs))
