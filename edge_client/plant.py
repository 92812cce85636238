"""The vehicle plant: the nonlinear 2-DOF model integrated with RK4, finer than the sample period.

:class:`PlantSimulator` steps a batch of vehicles (one scenario each, one
set of vehicle parameters for the batch) at the sample period s: at sample k
it measures y_k (with noise), runs the driver (speed tracking -> T_d, open-loop
steering -> delta_d), evaluates the faults f_k, then integrates eqs. (1)-(2)
and the planar pose over [t_k, t_{k+1}) with the inputs held, in
``substeps`` RK4 steps (10 = 1 ms at s = 10 ms).

Scenario signals are compiled in chunks, so a fleet can run for hours with
bounded memory. The next chunk is compiled a few vehicles at a time during
the second half of the current one (``prefetch``), so a paced loop never
stalls for a whole fleet's compilation at a chunk boundary.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from edge_client.scenario import Scenario, ScenarioSignals
from synth.model import FloatArray, continuous_dynamics, model_demand, model_inputs
from synth.params import STANDARD_GRAVITY_MPS2, VehicleParams

#: The tyre model of eq. (2) divides by v_x; below this speed the plant holds v_x here.
MIN_SPEED_MPS = 0.5
CHUNK_SAMPLES = 1000


@dataclass(frozen=True)
class PlantSample:
    """One sample of a batch of nv vehicles, everything at t_k.

    x : (nv, 3) true [v_x, v_y, r]; y : (nv, 2) measured [v_x, r]
    u : (nv, 2) demanded [T_d, delta_d]; f : (nv, 2) true faults [T_f, delta_f]
    wind : (nv,) F_w [N]; pose : (nv, 3) [X [m], Y [m], heading psi [rad]]
    active : (nv,) the vehicle's scenario has not ended
    grade : (nv,) the road grade each vehicle reports [rad, + uphill], NaN for a vehicle whose scenario has no
    road grade; None when none has
    """

    k: int
    t: float
    x: FloatArray
    y: FloatArray
    u: FloatArray
    f: FloatArray
    wind: FloatArray
    pose: FloatArray
    active: np.ndarray
    grade: FloatArray | None = None


def dynamics_with_pose(
    state: FloatArray, u_d: FloatArray, w: FloatArray, f: FloatArray, p: VehicleParams
) -> FloatArray:
    """d/dt of [v_x, v_y, r, X, Y, psi], shape (nv, 6): eqs. (1)-(2) plus planar kinematics."""
    x = state[:, :3].copy()
    x[:, 0] = np.maximum(x[:, 0], MIN_SPEED_MPS)
    dx = continuous_dynamics(x, u_d, w, f, p)
    psi = state[:, 5]
    v_x, v_y, r = x[:, 0], x[:, 1], x[:, 2]
    dX = v_x * np.cos(psi) - v_y * np.sin(psi)
    dY = v_x * np.sin(psi) + v_y * np.cos(psi)
    return np.column_stack([dx, dX, dY, r])


class PlantSimulator:
    """A batch of simulated vehicles following their scenarios."""

    def __init__(
        self,
        scenarios: Sequence[Scenario],
        params: VehicleParams | None = None,
        substeps: int = 10,
        seed: int | None = None,
        prefetch: bool = True,
    ) -> None:
        if not scenarios:
            raise ValueError("PlantSimulator needs at least one scenario")
        if substeps < 1:
            raise ValueError(f"substeps must be >= 1, got {substeps}")
        self.scenarios = list(scenarios)
        self.params = params or self.scenarios[0].vehicle
        self.sample_period_s = self.params.sample_period_s
        self.substeps = substeps
        nv = len(self.scenarios)
        self.state = np.zeros((nv, 6))
        self.state[:, 0] = [s.initial_speed_mps for s in self.scenarios]
        self.state[:, 1] = [s.initial_lateral_speed_mps for s in self.scenarios]
        self.state[:, 2] = [s.initial_yaw_rate_radps for s in self.scenarios]
        self.n_samples = np.array([round(s.duration_s / self.sample_period_s) for s in self.scenarios])
        entropy = [s.seed for s in self.scenarios] if seed is None else [seed]
        self.rng = np.random.default_rng(np.random.SeedSequence(entropy))
        noise = [s.noise for s in self.scenarios]
        self.noise_sigma = np.array([[n.vx_sigma_mps, n.r_sigma_radps] for n in noise])
        self.noise_bias = np.array([[n.vx_bias_mps, n.r_bias_radps] for n in noise])
        self.speed_kp = np.array([s.driver.speed_kp_per_s for s in self.scenarios])
        payload = np.array([s.payload_kg for s in self.scenarios], dtype=float)
        #: each vehicle's payload [kg], None when none carries one
        self.payload: FloatArray | None = payload if payload.any() else None
        #: which vehicles drive a road with a grade (and report it)
        self.graded = np.array([s.road_grade is not None for s in self.scenarios])
        self.k = 0
        #: the road-wheel angle of each vehicle's steering actuator, with a lag (None until the first sample)
        self.steer_angle: FloatArray | None = None
        self.prefetch = prefetch
        self._chunk_start = -1
        self._chunk: dict[str, FloatArray] = {}
        self._next_start = -1
        self._next_parts: list[ScenarioSignals] = []

    def _integrate_with_steering_lag(
        self, state: FloatArray, u: FloatArray, wind: FloatArray, f: FloatArray, dt: float
    ) -> FloatArray:
        """RK4 over one sample with the road-wheel angle of a first-order actuator: it moves from its value
        towards the target delta_d + b_delta delta_f as delta(t) = target + (delta_0 - target) exp(-t / tau),
        evaluated at every RK4 stage."""
        p = self.params
        target = u[:, 1] + p.steer_fault_gain * f[:, 1]
        if self.steer_angle is None:
            self.steer_angle = target.copy()  # an actuator at rest on its first target
        start = self.steer_angle
        tau = p.steer_time_constant_s
        no_steer_fault = f.copy()
        no_steer_fault[:, 1] = 0.0

        def inputs(t: float) -> FloatArray:
            return np.column_stack([u[:, 0], target + (start - target) * math.exp(-t / tau)])

        for i in range(self.substeps):
            t0 = i * dt
            u0, u_half, u1 = inputs(t0), inputs(t0 + 0.5 * dt), inputs(t0 + dt)
            k1 = dynamics_with_pose(state, u0, wind, no_steer_fault, p)
            k2 = dynamics_with_pose(state + 0.5 * dt * k1, u_half, wind, no_steer_fault, p)
            k3 = dynamics_with_pose(state + 0.5 * dt * k2, u_half, wind, no_steer_fault, p)
            k4 = dynamics_with_pose(state + dt * k3, u1, wind, no_steer_fault, p)
            state = state + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        self.steer_angle = inputs(self.sample_period_s)[:, 1]
        return state

    @property
    def n_vehicles(self) -> int:
        return len(self.scenarios)

    def _drive_force(self, accel: FloatArray, speed: FloatArray, grade: FloatArray | None) -> FloatArray:
        """The driver's drive force [N] for ``accel``: the inertia, drag and rolling resistance of the vehicle with
        its payload (the rolling resistance in proportion to the weight), and the weight's pull on the grade."""
        p = self.params
        if self.payload is None and grade is None:
            return p.effective_mass_kg * accel + p.longitudinal_drag_coeff * speed**2 + p.rolling_resistance_n
        payload = 0.0 if self.payload is None else self.payload
        weight = p.mass_kg + payload
        force = (p.effective_mass_kg + payload) * accel + p.longitudinal_drag_coeff * speed**2
        force += p.rolling_resistance_n * weight / p.mass_kg
        if grade is not None:
            force += weight * STANDARD_GRAVITY_MPS2 * np.sin(grade)
        return np.asarray(force, dtype=float)

    def _loaded_on_grade(
        self, x: FloatArray, u: FloatArray, f: FloatArray, grade: FloatArray | None
    ) -> tuple[FloatArray, FloatArray]:
        """The demand and faults that drive the batch's model as the vehicles with their payloads move on their
        grades: the torque of synth.model.model_inputs (exact for this model: docs/math.md 12.5, 12.6), a torque
        fault T_f acting as rho T_f. The service's observer, told the payload and the grade, makes the same
        approximations (the cornering drag's share of a payload, cos(theta)), so these vehicles check what it is
        told, not the approximations; the multi-body benchmark (docs/benchmarks/real_vehicle.md) checks those."""
        model_u, _, rho = model_inputs(x[:, [0, 2]], u, self.payload, grade, self.params)
        if rho is not None:
            f = f.copy()
            f[:, 0] *= rho
        return model_u, f

    @property
    def finished(self) -> bool:
        return bool(self.k >= self.n_samples.max())

    def _signals_at(self, k: int) -> tuple[int, dict[str, FloatArray]]:
        """The compiled signals of the chunk holding sample k, each stacked to (CHUNK_SAMPLES, nv[, 2])."""
        start = (k // CHUNK_SAMPLES) * CHUNK_SAMPLES
        if start != self._chunk_start:
            parts = self._next_parts if self._next_start == start else []
            compiled = parts + [
                s.compile(self.sample_period_s, start, CHUNK_SAMPLES) for s in self.scenarios[len(parts) :]
            ]
            self._chunk = {
                name: np.stack([getattr(c, name) for c in compiled], axis=1)
                for name in ScenarioSignals.__dataclass_fields__
            }
            self._chunk_start = start
            self._next_start, self._next_parts = -1, []
        return k - start, self._chunk

    def prepare(self) -> None:
        """Compile the signals of the next sample's chunk now, so the first :meth:`step` does not."""
        self._signals_at(self.k)

    def _prefetch_next_chunk(self) -> None:
        """In the second half of a chunk, compile a share of the next chunk's vehicles (done a tick early)."""
        offset = self.k - self._chunk_start
        if offset < CHUNK_SAMPLES // 2 or offset >= CHUNK_SAMPLES:
            return
        next_start = self._chunk_start + CHUNK_SAMPLES
        if self._next_start != next_start:
            self._next_start, self._next_parts = next_start, []
        todo = self.n_vehicles - len(self._next_parts)
        if todo <= 0:
            return
        ticks_left = max(CHUNK_SAMPLES - offset - 1, 1)
        for scenario in self.scenarios[len(self._next_parts) :][: math.ceil(todo / ticks_left)]:
            self._next_parts.append(scenario.compile(self.sample_period_s, next_start, CHUNK_SAMPLES))

    def step(self) -> PlantSample:
        """Measure, drive, inject faults at t_k; integrate to t_{k+1}; return the sample at t_k."""
        k = self.k
        offset, chunk = self._signals_at(k)
        p = self.params
        steer_demand = chunk["steer_demand"][offset]
        speed_ref = chunk["speed_ref"][offset]
        speed_ref_rate = chunk["speed_ref_rate"][offset]
        wind = chunk["wind"][offset]
        fault_add = chunk["fault_add"][offset]
        fault_gain = chunk["fault_gain"][offset]

        grade = chunk["grade"][offset] if self.graded.any() else None
        x = self.state[:, :3].copy()
        y = x[:, [0, 2]] + self.noise_bias + self.noise_sigma * self.rng.standard_normal((self.n_vehicles, 2))
        # driver: speed tracking on the measured speed, drag, rolling-resistance (and a load's, a grade's)
        # feed-forward; the drive force becomes a torque at the wheels
        speed_meas = np.maximum(y[:, 0], MIN_SPEED_MPS)
        accel = speed_ref_rate + self.speed_kp * (speed_ref - speed_meas)
        force = self._drive_force(accel, speed_meas, grade)
        torque = p.wheel_radius_m * force
        u = np.column_stack([torque, steer_demand])
        f = fault_add + fault_gain * u
        sample = PlantSample(
            k=k,
            t=k * self.sample_period_s,
            x=x,
            y=y,
            u=u,
            f=f,
            wind=wind,
            pose=self.state[:, 3:].copy(),
            active=k < self.n_samples,
            grade=None if grade is None else np.where(self.graded, grade, np.nan),
        )
        dt = self.sample_period_s / self.substeps
        state = self.state
        if self.payload is not None or grade is not None:
            u, f = self._loaded_on_grade(x, u, f, grade)
        # the model's input: the demand with the load transfer's steering angle (none without a CG height)
        u_model = model_demand(x[:, [0, 2]], u, p)
        if p.steer_time_constant_s == 0.0:
            for _ in range(self.substeps):
                k1 = dynamics_with_pose(state, u_model, wind, f, p)
                k2 = dynamics_with_pose(state + 0.5 * dt * k1, u_model, wind, f, p)
                k3 = dynamics_with_pose(state + 0.5 * dt * k2, u_model, wind, f, p)
                k4 = dynamics_with_pose(state + dt * k3, u_model, wind, f, p)
                state = state + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        else:
            state = np.asarray(self._integrate_with_steering_lag(state, u_model, wind, f, dt), dtype=float)
        state[:, 0] = np.maximum(state[:, 0], MIN_SPEED_MPS)
        self.state = state
        self.k += 1
        if self.prefetch:
            self._prefetch_next_chunk()
        return sample
