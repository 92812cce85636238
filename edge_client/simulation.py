"""Closed runs of plant + estimator: the engine behind `agv-fe simulate`, `compare` and the accuracy bench."""

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
from synth.model import FloatArray
from synth.observer import FuzzyObserver


class EstimatorOutput(Protocol):
    """What a batch estimator reports per step."""

    @property
    def state(self) -> FloatArray: ...  # (nv, 3)

    @property
    def faults(self) -> FloatArray: ...  # (nv, 2)

    @property
    def in_domain(self) -> NDArray[np.bool_]: ...  # (nv,)


class BatchEstimator(Protocol):
    """A state and fault estimator for a batch of vehicles."""

    def step(self, y: FloatArray, u: FloatArray) -> EstimatorOutput: ...


EstimatorFactory = Callable[[FloatArray, FloatArray | None], BatchEstimator]


def observer_factory(gains: ObserverGains) -> EstimatorFactory:
    """An :data:`EstimatorFactory` for the fuzzy observer with these gains."""

    def make(y0: FloatArray, x_hat0: FloatArray | None) -> BatchEstimator:
        return FuzzyObserver(gains, y0, x_hat0)

    return make


@dataclass
class SimulationResult:
    """Time histories of a batch run, K samples, nv vehicles.

    x, x_hat : (K, nv, 3); f, f_hat : (K, nv, 2); y, u : (K, nv, 2);
    pose : (K, nv, 3); wind : (K, nv); in_domain : (K, nv); t : (K,)
    """

    scenarios: list[Scenario]
    t: FloatArray
    x: FloatArray
    f: FloatArray
    y: FloatArray
    u: FloatArray
    wind: FloatArray
    pose: FloatArray
    x_hat: FloatArray
    f_hat: FloatArray
    in_domain: NDArray[np.bool_]
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


def run(
    scenarios: Sequence[Scenario],
    estimator: EstimatorFactory,
    *,
    substeps: int = 10,
) -> SimulationResult:
    """Simulate the scenarios as one batch and run the estimator on the measurements."""
    plant = PlantSimulator(scenarios, substeps=substeps)
    n_samples = int(plant.n_samples.max())
    nv = plant.n_vehicles
    out = {
        "x": np.zeros((n_samples, nv, 3)),
        "f": np.zeros((n_samples, nv, 2)),
        "y": np.zeros((n_samples, nv, 2)),
        "u": np.zeros((n_samples, nv, 2)),
        "wind": np.zeros((n_samples, nv)),
        "pose": np.zeros((n_samples, nv, 3)),
        "x_hat": np.zeros((n_samples, nv, 3)),
        "f_hat": np.zeros((n_samples, nv, 2)),
    }
    in_domain = np.zeros((n_samples, nv), dtype=bool)
    step_times = np.zeros(n_samples)
    t = np.zeros(n_samples)
    est: BatchEstimator | None = None
    for k in range(n_samples):
        sample = plant.step()
        if est is None:
            init = [s.observer_initial_state for s in scenarios]
            x_hat0 = None if any(i is None for i in init) else np.array(init, dtype=float)
            est = estimator(sample.y, x_hat0)
        started = time.perf_counter()
        result = est.step(sample.y, sample.u)
        step_times[k] = time.perf_counter() - started
        t[k] = sample.t
        out["x"][k], out["f"][k], out["y"][k], out["u"][k] = sample.x, sample.f, sample.y, sample.u
        out["wind"][k], out["pose"][k] = sample.wind, sample.pose
        out["x_hat"][k], out["f_hat"][k] = result.state, result.faults
        in_domain[k] = result.in_domain
    return SimulationResult(scenarios=list(scenarios), t=t, in_domain=in_domain, step_times_s=step_times, **out)
