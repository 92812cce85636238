"""Random driving within the operating bounds: a seeded speed profile and manoeuvre sequence.

The observer is certified on the box S_x of eq. (13) (default v_x in [5, 30] m/s,
|v_y| <= 1.5 m/s, |r| <= 0.55 rad/s). A random drive must stay inside it, or a
healthy vehicle leaves the design domain and its estimate loses the guarantee.
The steering amplitude of each manoeuvre is therefore bounded by the
steady-state lateral response of eqs. (1)-(2), linearised at the highest speed
of the manoeuvre's window, times a safety margin: at 30 m/s one radian of
steering gives about -23 m/s of v_y and 6.8 rad/s of r, so the budget there
is ~0.02 rad, against ~0.1 rad at 8 m/s. Steering faults use the same budget
(``reserved_steer_rad``), so manoeuvre plus fault stays inside.

Everything here is zenoh-free and deterministic for a given ``numpy`` Generator.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from edge_client.scenario import Manoeuvre, SpeedPoint
from synth.model import continuous_dynamics
from synth.params import OperatingBounds, VehicleParams

#: Fraction of the operating bounds a steady-state response may use (the rest covers transients).
DEFAULT_MARGIN = 0.6
#: Longitudinal acceleration limit of the random speed profile [m/s^2].
MAX_ACCEL_MPS2 = 1.0


def lateral_steady_state_gains(params: VehicleParams, speed_mps: float) -> tuple[float, float]:
    """Steady-state (v_y, r) per radian of steering at ``speed_mps``: ([m/s / rad], [rad/s / rad]).

    The lateral part of eqs. (1)-(2), linearised at x = [v_x, 0, 0] by finite
    differences of :func:`synth.model.continuous_dynamics` (the model is affine in
    v_y, r and delta there, so the differences are exact up to rounding):
    0 = J [v_y, r] + b delta  =>  [v_y, r] = -J^{-1} b delta.
    """
    x0 = np.array([speed_mps, 0.0, 0.0])
    u0 = np.array([params.longitudinal_drag_coeff * speed_mps**2, 0.0])
    no_fault = np.zeros(2)
    base = continuous_dynamics(x0, u0, 0.0, no_fault, params)[1:]
    eps = 1e-6
    J = np.zeros((2, 2))
    for column, index in enumerate((1, 2)):
        x = x0.copy()
        x[index] += eps
        J[:, column] = (continuous_dynamics(x, u0, 0.0, no_fault, params)[1:] - base) / eps
    u = u0.copy()
    u[1] += eps
    b = (continuous_dynamics(x0, u, 0.0, no_fault, params)[1:] - base) / eps
    vy_gain, r_gain = -np.linalg.solve(J, b)
    return float(vy_gain), float(r_gain)


def steer_budget_rad(
    params: VehicleParams, bounds: OperatingBounds, max_speed_mps: float, margin: float = DEFAULT_MARGIN
) -> float:
    """Largest |delta| [rad] whose steady state keeps |v_y| and |r| within ``margin`` of the bounds.

    Evaluated on a grid from the lowest bound speed to ``max_speed_mps`` because
    the v_y gain changes sign with speed.
    """
    vy_limit = margin * min(-bounds.vy_min_mps, bounds.vy_max_mps)
    r_limit = margin * min(-bounds.r_min_radps, bounds.r_max_radps)
    budget = np.inf
    for speed in np.linspace(bounds.vx_min_mps, max_speed_mps, 12):
        vy_gain, r_gain = lateral_steady_state_gains(params, float(speed))
        budget = min(budget, vy_limit / max(abs(vy_gain), 1e-9), r_limit / max(abs(r_gain), 1e-9))
    return float(budget)


@dataclass(frozen=True)
class RandomDrive:
    """A random drive: initial speed [m/s], piecewise-linear speed reference and a manoeuvre sequence."""

    initial_speed_mps: float
    speed_profile: tuple[SpeedPoint, ...]
    manoeuvres: tuple[Manoeuvre, ...]


def random_speed_profile(
    rng: np.random.Generator, duration_s: float, speed_range_mps: tuple[float, float]
) -> tuple[SpeedPoint, ...]:
    """Speed points every 8-20 s, speeds uniform in ``speed_range_mps``, slopes within MAX_ACCEL_MPS2."""
    low, high = speed_range_mps
    t = 0.0
    speed = float(rng.uniform(low, high))
    points = [SpeedPoint(t_s=0.0, speed_mps=round(speed, 3))]
    while t < duration_s:
        target = float(rng.uniform(low, high))
        hold = float(rng.uniform(8.0, 20.0))
        ramp = max(abs(target - speed) / MAX_ACCEL_MPS2, 1.0)
        t += hold
        points.append(SpeedPoint(t_s=round(t, 3), speed_mps=round(speed, 3)))
        t += ramp
        points.append(SpeedPoint(t_s=round(t, 3), speed_mps=round(target, 3)))
        speed = target
    return tuple(points)


def random_manoeuvres(
    rng: np.random.Generator,
    duration_s: float,
    max_steer_rad: float,
    first_start_s: float = 1.0,
) -> tuple[Manoeuvre, ...]:
    """A sequence of straight stretches (1-5 s) and turns, lane changes and slaloms.

    Each manoeuvre's amplitude is uniform in [0.3, 1] * ``max_steer_rad`` with a random sign.
    """
    manoeuvres = []
    t = first_start_s
    while t < duration_s:
        t += float(rng.uniform(1.0, 5.0))  # straight stretch
        if t >= duration_s:
            break
        kind = str(rng.choice(["turn", "lane_change", "slalom"]))
        amplitude = float(rng.uniform(0.3, 1.0) * max_steer_rad * rng.choice([-1.0, 1.0]))
        if kind == "turn":
            length = float(rng.uniform(3.0, 8.0))
            manoeuvre = Manoeuvre(kind="turn", start_s=round(t, 3), duration_s=length, amplitude_rad=amplitude)
        elif kind == "lane_change":
            length = float(rng.uniform(4.0, 8.0))
            manoeuvre = Manoeuvre(kind="lane_change", start_s=round(t, 3), duration_s=length, amplitude_rad=amplitude)
        else:
            period = float(rng.uniform(3.0, 6.0))
            length = period * int(rng.integers(1, 4))
            manoeuvre = Manoeuvre(
                kind="slalom", start_s=round(t, 3), duration_s=length, amplitude_rad=amplitude, period_s=period
            )
        manoeuvres.append(manoeuvre)
        t += length
    return tuple(manoeuvres)


def random_drive(
    rng: np.random.Generator,
    duration_s: float,
    *,
    speed_range_mps: tuple[float, float] = (8.0, 25.0),
    reserved_steer_rad: float = 0.0,
    params: VehicleParams | None = None,
    bounds: OperatingBounds | None = None,
    margin: float = DEFAULT_MARGIN,
) -> RandomDrive:
    """A random speed profile and manoeuvre sequence that keeps the vehicle inside ``bounds``.

    ``reserved_steer_rad`` is the largest steering fault the vehicle will carry;
    it is taken off the steering budget so that manoeuvre plus fault stays inside.
    Raises ValueError if the speed range leaves the bounds or nothing is left to steer with.
    """
    params = params or VehicleParams()
    bounds = bounds or OperatingBounds()
    low, high = speed_range_mps
    if not bounds.vx_min_mps <= low < high <= bounds.vx_max_mps:
        raise ValueError(
            f"speed_range_mps {speed_range_mps} must lie inside the bounds "
            f"[{bounds.vx_min_mps}, {bounds.vx_max_mps}] m/s with low < high"
        )
    budget = steer_budget_rad(params, bounds, high, margin) - reserved_steer_rad
    if budget <= 0:
        raise ValueError(
            f"no steering left for manoeuvres: the budget at {high} m/s is "
            f"{budget + reserved_steer_rad:.4f} rad and the fault reserves {reserved_steer_rad:.4f} rad"
        )
    profile = random_speed_profile(rng, duration_s, speed_range_mps)
    return RandomDrive(
        initial_speed_mps=profile[0].speed_mps,
        speed_profile=profile,
        manoeuvres=random_manoeuvres(rng, duration_s, budget),
    )
