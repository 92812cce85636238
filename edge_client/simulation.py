"""Closed runs of plant + estimators: the engine behind `agv-fe simulate`, `compare` and the accuracy bench.

:func:`simulate_plant` records what the vehicles did and measured;
:func:`estimate` runs any batch estimator over such a record, so that several
estimators see exactly the same noisy data; :func:`run` does both.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from edge_client.plant import PlantSimulator
from edge_client.scenario import Scenario
from synth.gains import ObserverGains
from synth.model import FloatArray, model_inputs, payload_torque
from synth.observer import FuzzyObserver
from synth.options import EffectivenessOptions
from synth.params import VehicleParams


class EstimatorOutput(Protocol):
    """What a batch estimator reports per step."""

    @property
    def state(self) -> FloatArray: ...  # (nv, 3)

    @property
    def faults(self) -> FloatArray: ...  # (nv, 2)

    @property
    def in_domain(self) -> NDArray[np.bool_]: ...  # (nv,)

    @property
    def certified(self) -> NDArray[np.bool_]: ...  # (nv,) the estimate lies where the design's bound holds


class BatchEstimator(Protocol):
    """A state and fault estimator for a batch of vehicles."""

    def step(self, y: FloatArray, u: FloatArray) -> EstimatorOutput: ...


class EstimatorFactory(Protocol):
    """Makes a batch estimator for nv vehicles from their first measurement.

    y0 : (nv, 2) first [v_x, r]; x_hat0 : (nv, 3) initial [v_x, v_y, r] or None (measured v_x, r, v_y = 0);
    u0 : (nv, 2) first demand [T_d, delta_d], where a steering actuator model starts at rest (None: at 0).
    """

    def __call__(self, y0: FloatArray, x_hat0: FloatArray | None, u0: FloatArray | None = None) -> BatchEstimator: ...


def observer_factory(gains: ObserverGains) -> EstimatorFactory:
    """An :class:`EstimatorFactory` for the fuzzy observer with these gains."""

    def make(y0: FloatArray, x_hat0: FloatArray | None, u0: FloatArray | None = None) -> BatchEstimator:
        return FuzzyObserver(gains, y0, x_hat0, u0)

    return make


def effectiveness_factory(gains: ObserverGains, options: EffectivenessOptions | None = None) -> EstimatorFactory:
    """An :class:`EstimatorFactory` for the fuzzy observer with its loss-of-effectiveness stage
    (synth.effectiveness): the faults it reports are the totals, bias plus (alpha - 1) demand."""
    from synth.effectiveness import EffectivenessObserver

    chosen = options or EffectivenessOptions(enabled=True)

    def make(y0: FloatArray, x_hat0: FloatArray | None, u0: FloatArray | None = None) -> BatchEstimator:
        return EffectivenessObserver(gains, chosen, y0, x_hat0, u0)

    return make


def ekf_factory(gains_or_options: ObserverGains) -> EstimatorFactory:
    """An :class:`EstimatorFactory` for the EKF tuned like these gains (params, bounds, noise model, fault order).

    The EKF's steering actuator model (with a lag) starts at rest on the first demand it steps with, which is
    ``u0`` when the caller steps from the sample it started on; so it needs no ``u0`` of its own.
    """
    from synth.ekf import AugmentedEKF

    g = gains_or_options

    def make(y0: FloatArray, x_hat0: FloatArray | None, u0: FloatArray | None = None) -> BatchEstimator:
        return AugmentedEKF(g.params, g.bounds, g.options.noise, g.options.fault_order, y0, x_hat0)

    return make


@dataclass(frozen=True)
class _PayloadOutput:
    state: FloatArray
    faults: FloatArray
    in_domain: NDArray[np.bool_]
    certified: NDArray[np.bool_]


class _PayloadEstimator:
    """An estimator fed the payload torque (synth.model.payload_torque), its torque fault scaled back by rho."""

    def __init__(
        self,
        inner_factory: EstimatorFactory,
        params: VehicleParams,
        payload_kg: float,
        y0: FloatArray,
        x_hat0: FloatArray | None,
        u0: FloatArray | None,
    ) -> None:
        self._params, self._payload = params, payload_kg
        model_u0 = None if u0 is None else self._model_demand(np.asarray(y0, float), np.asarray(u0, float))[0]
        self._inner = inner_factory(y0, x_hat0, model_u0)

    def _model_demand(self, y: FloatArray, u: FloatArray) -> tuple[FloatArray, FloatArray]:
        torque, rho = payload_torque(y[:, 0], u[:, 0], self._payload, self._params)
        return np.column_stack([torque, u[:, 1]]), rho

    def step(self, y: FloatArray, u: FloatArray) -> EstimatorOutput:
        y = np.asarray(y, dtype=float)
        model_u, rho = self._model_demand(y, np.asarray(u, dtype=float))
        out = self._inner.step(y, model_u)
        faults = np.array(out.faults, dtype=float)
        faults[:, 0] /= rho
        return _PayloadOutput(out.state, faults, out.in_domain, out.certified)


def payload_factory(factory: EstimatorFactory, params: VehicleParams, payload_kg: float) -> EstimatorFactory:
    """``factory``'s estimator for vehicles carrying ``payload_kg`` more than ``params`` (the profile) states, as
    the service runs it once the payload is reported (PUT /vehicles/{id}/payload, docs/math.md 12.5)."""

    def make(y0: FloatArray, x_hat0: FloatArray | None, u0: FloatArray | None = None) -> BatchEstimator:
        return _PayloadEstimator(factory, params, payload_kg, y0, x_hat0, u0)

    return make


@dataclass
class PlantRecord:
    """What a batch of vehicles did and measured, K samples, nv vehicles.

    x : (K, nv, 3) true state; f : (K, nv, 2) true faults; y : (K, nv, 2) measured;
    u : (K, nv, 2) demanded inputs; pose : (K, nv, 3); wind : (K, nv); t : (K,);
    grade : (K, nv) the road grade each vehicle reported [rad] (NaN: none), None when none did
    """

    scenarios: list[Scenario]
    t: FloatArray
    x: FloatArray
    f: FloatArray
    y: FloatArray
    u: FloatArray
    wind: FloatArray
    pose: FloatArray
    grade: FloatArray | None = None

    def observer_initial_state(self) -> FloatArray | None:
        init = [s.observer_initial_state for s in self.scenarios]
        return None if any(i is None for i in init) else np.array(init, dtype=float)


@dataclass
class SimulationResult(PlantRecord):
    """A :class:`PlantRecord` with one estimator's output: x_hat (K, nv, 3), f_hat (K, nv, 2), in_domain (K, nv)."""

    x_hat: FloatArray = field(default_factory=lambda: np.zeros(0))
    f_hat: FloatArray = field(default_factory=lambda: np.zeros(0))
    in_domain: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, dtype=bool))
    step_times_s: FloatArray = field(default_factory=lambda: np.zeros(0))

    def rmse(self, after_s: float = 0.0) -> dict[str, FloatArray]:
        """Root-mean-square errors per vehicle from ``after_s`` on: keys v_x, v_y, r, T_f, delta_f."""
        window = self.t >= after_s
        errors = {
            "v_x": self.x_hat[window, :, 0] - self.x[window, :, 0],
            "v_y": self.x_hat[window, :, 1] - self.x[window, :, 1],
            "r": self.x_hat[window, :, 2] - self.x[window, :, 2],
            "T_f": self.f_hat[window, :, 0] - self.f[window, :, 0],
            "delta_f": self.f_hat[window, :, 1] - self.f[window, :, 1],
        }
        return {name: np.sqrt(np.mean(err**2, axis=0)) for name, err in errors.items()}

    def fault_amplitude(self) -> FloatArray:
        """Peak absolute true fault per vehicle and channel, (nv, 2)."""
        return np.asarray(np.abs(self.f).max(axis=0))


def simulate_plant(scenarios: Sequence[Scenario], *, substeps: int = 10) -> PlantRecord:
    """Simulate the scenarios as one batch and record everything."""
    plant = PlantSimulator(scenarios, substeps=substeps)
    n_samples = int(plant.n_samples.max())
    nv = plant.n_vehicles
    rec = PlantRecord(
        scenarios=list(scenarios),
        t=np.arange(n_samples) * plant.sample_period_s,
        x=np.zeros((n_samples, nv, 3)),
        f=np.zeros((n_samples, nv, 2)),
        y=np.zeros((n_samples, nv, 2)),
        u=np.zeros((n_samples, nv, 2)),
        wind=np.zeros((n_samples, nv)),
        pose=np.zeros((n_samples, nv, 3)),
    )
    if plant.graded.any():
        rec.grade = np.full((n_samples, nv), np.nan)
    for k in range(n_samples):
        sample = plant.step()
        rec.x[k], rec.f[k], rec.y[k], rec.u[k] = sample.x, sample.f, sample.y, sample.u
        rec.wind[k], rec.pose[k] = sample.wind, sample.pose
        if rec.grade is not None and sample.grade is not None:
            rec.grade[k] = sample.grade
    return rec


def told_demands(record: PlantRecord) -> Callable[[int], tuple[FloatArray, FloatArray | None]]:
    """For sample k, the demand as the service gives it to an estimator of vehicles that reported their payloads
    and road grades (synth.model.model_inputs, with the scenarios' vehicle as the profile), and rho to scale the
    torque fault back by (None without a payload): ``record.u[k]`` and None for empty vehicles on level ground."""
    carried = np.array([s.payload_kg for s in record.scenarios], dtype=float)
    payload = carried if carried.any() else None
    grades = record.grade
    if grades is None and payload is None:
        return lambda k: (record.u[k], None)
    params = record.scenarios[0].vehicle

    def demand(k: int) -> tuple[FloatArray, FloatArray | None]:
        grade = None if grades is None else np.nan_to_num(grades[k], nan=0.0)
        model_u, _, rho = model_inputs(record.y[k], record.u[k], payload, grade, params)
        return model_u, None if rho is None else np.asarray(rho, dtype=float)

    return demand


def estimate(record: PlantRecord, estimator: EstimatorFactory) -> SimulationResult:
    """Run an estimator over a record, told what its vehicles reported (their payloads and road grades:
    :func:`told_demands`); every step is timed."""
    n_samples, nv = record.y.shape[:2]
    x_hat = np.zeros((n_samples, nv, 3))
    f_hat = np.zeros((n_samples, nv, 2))
    in_domain = np.zeros((n_samples, nv), dtype=bool)
    step_times = np.zeros(n_samples)
    told = told_demands(record)
    est = estimator(record.y[0], record.observer_initial_state(), told(0)[0])
    for k in range(n_samples):
        u, rho = told(k)
        started = time.perf_counter()
        out = est.step(record.y[k], u)
        step_times[k] = time.perf_counter() - started
        x_hat[k], f_hat[k], in_domain[k] = out.state, out.faults, out.in_domain
        if rho is not None:  # the torque fault at the vehicle's scale, as the service reports it
            f_hat[k, :, 0] /= rho
    return SimulationResult(**record.__dict__, x_hat=x_hat, f_hat=f_hat, in_domain=in_domain, step_times_s=step_times)


def run(scenarios: Sequence[Scenario], estimator: EstimatorFactory, *, substeps: int = 10) -> SimulationResult:
    """Simulate the scenarios and run the estimator on their measurements."""
    return estimate(simulate_plant(scenarios, substeps=substeps), estimator)
