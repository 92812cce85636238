"""Estimator comparison on identical noisy data: accuracy, detection delay, compute cost, memory.

Used by `agv-fe compare` and the accuracy benchmark. Every estimator runs on
the same :class:`~edge_client.simulation.PlantRecord` (same noise samples), so
differences come from the estimators alone.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from edge_client.library import builtin_scenario
from edge_client.scenario import REALISTIC_NOISE, Scenario
from edge_client.simulation import EstimatorFactory, SimulationResult, estimate, simulate_plant
from synth.model import FloatArray

#: RMSE and detections are counted from this time on: the first seconds are the
#: initial-condition transient (the paper's scenarios start the observer at [5, -1, 0]).
RMSE_AFTER_S = 3.0
#: A diagnostic window that leaves out the paper scenarios' initial-state transient as well [s].
RMSE_LATE_S = 8.0
CHANNELS = ("T_f", "delta_f")


@dataclass(frozen=True)
class DetectionRule:
    """A fault is detected when |estimate| stays above the threshold for ``hold_s``."""

    torque_nm: float = 15.0
    steer_rad: float = 0.005
    hold_s: float = 0.3

    def thresholds(self) -> tuple[float, float]:
        return self.torque_nm, self.steer_rad


@dataclass
class EstimatorScore:
    """One estimator on one run."""

    rmse: dict[str, float]
    rmse_late: dict[str, float]
    detection_delay_s: dict[str, float | None]
    false_detections: dict[str, int]


@dataclass
class Comparison:
    """Scores of several estimators over seeds of one scenario, plus compute cost."""

    scenario: str
    seeds: list[int]
    scores: dict[str, list[EstimatorScore]] = field(default_factory=dict)
    step_us_1: dict[str, float] = field(default_factory=dict)
    step_us_batch: dict[str, float] = field(default_factory=dict)
    batch_size: int = 0
    state_bytes: dict[str, int] = field(default_factory=dict)
    example: dict[str, SimulationResult] = field(default_factory=dict)

    def median(self, estimator: str, metric: str, channel: str) -> float | None:
        values = [getattr(s, metric)[channel] for s in self.scores[estimator]]
        present = [float(v) for v in values if v is not None]
        return statistics.median(present) if present else None


def fault_onsets(scenario: Scenario) -> dict[str, float | None]:
    """Earliest onset per channel of the scenario's faults (None: no fault on that channel)."""
    onsets: dict[str, float | None] = {"T_f": None, "delta_f": None}
    for fault in scenario.faults:
        name = "T_f" if fault.channel == "torque" else "delta_f"
        current = onsets[name]
        onsets[name] = fault.onset_s if current is None else min(current, fault.onset_s)
    return onsets


def detection(
    t: FloatArray,
    estimate_c: FloatArray,
    threshold: float,
    hold_s: float,
    onset: float | None,
    warm_up_s: float = 0.0,
) -> tuple[float | None, int]:
    """(delay after onset of the first persistent crossing, number of persistent crossings before onset).

    Samples before ``warm_up_s`` are ignored (the observer's initial transient); a fault present
    before then counts its delay from the end of the warm-up.
    """
    above = (np.abs(estimate_c) > threshold) & (t >= warm_up_s)
    if onset is not None:
        onset = max(onset, warm_up_s)
    dt = float(t[1] - t[0]) if t.size > 1 else 1.0
    need = max(1, round(hold_s / dt))
    run = 0
    false_count = 0
    armed = True
    for k in range(t.size):
        run = run + 1 if above[k] else 0
        if run == 0:
            armed = True
        if run >= need and armed:
            armed = False
            if onset is None or t[k] - hold_s < onset:
                false_count += 1
            else:
                return float(t[k] - onset), false_count
    return None, false_count


def score(result: SimulationResult, rule: DetectionRule, vehicle: int = 0) -> EstimatorScore:
    rmse = {k: float(v[vehicle]) for k, v in result.rmse(after_s=RMSE_AFTER_S).items()}
    onsets = fault_onsets(result.scenarios[vehicle])
    delays: dict[str, float | None] = {}
    false: dict[str, int] = {}
    for c, (name, threshold) in enumerate(zip(CHANNELS, rule.thresholds(), strict=True)):
        delays[name], false[name] = detection(
            result.t, result.f_hat[:, vehicle, c], threshold, rule.hold_s, onsets[name]
        )
    late = {k: float(v[vehicle]) for k, v in result.rmse(after_s=RMSE_LATE_S).items()}
    return EstimatorScore(rmse=rmse, rmse_late=late, detection_delay_s=delays, false_detections=false)


def step_cost_us(
    factories: dict[str, EstimatorFactory], batch: int, steps: int = 200, seed: int = 0
) -> dict[str, float]:
    """Median wall time of one step for a batch of ``batch`` vehicles, estimators interleaved."""
    rng = np.random.default_rng(seed)
    y = np.column_stack([rng.uniform(6.0, 28.0, batch), rng.uniform(-0.4, 0.4, batch)])
    u = np.column_stack([rng.uniform(0.0, 300.0, batch), rng.uniform(-0.05, 0.05, batch)])
    estimators = {name: make(y, None) for name, make in factories.items()}
    times: dict[str, list[float]] = {name: [] for name in factories}
    for _ in range(steps):
        for name, est in estimators.items():
            started = time.perf_counter()
            est.step(y, u)
            times[name].append(time.perf_counter() - started)
    return {name: 1e6 * statistics.median(v) for name, v in times.items()}


def state_bytes_per_vehicle(factories: dict[str, EstimatorFactory], batch: int = 100) -> dict[str, int]:
    """Bytes of per-vehicle state each estimator keeps (arrays that grow with the fleet)."""
    y = np.tile([12.0, 0.0], (batch, 1))
    out = {}
    for name, make in factories.items():
        est = make(y, None)
        total = sum(v.nbytes for v in vars(est).values() if isinstance(v, np.ndarray) and v.shape[:1] == (batch,))
        out[name] = total // batch
    return out


def compare(
    scenario_name: str,
    factories: dict[str, EstimatorFactory],
    seeds: int,
    rule: DetectionRule | None = None,
    batch: int = 1000,
    scenario_factory: Callable[[str, int], Scenario] | None = None,
) -> Comparison:
    """Run every estimator on ``seeds`` noisy runs of the scenario and measure cost at ``batch`` vehicles.

    By default every scenario runs with realistic sensor noise (REALISTIC_NOISE), whatever its own setting.
    """
    rule = rule or DetectionRule()
    make_scenario = scenario_factory or (lambda name, seed: builtin_scenario(name, noise=REALISTIC_NOISE, seed=seed))
    comparison = Comparison(scenario=scenario_name, seeds=list(range(seeds)), batch_size=batch)
    comparison.scores = {name: [] for name in factories}
    for seed in comparison.seeds:
        record = simulate_plant([make_scenario(scenario_name, seed)])
        for name, make in factories.items():
            result = estimate(record, make)
            comparison.scores[name].append(score(result, rule))
            if seed == 0:
                comparison.example[name] = result
    comparison.step_us_1 = step_cost_us(factories, 1)
    comparison.step_us_batch = step_cost_us(factories, batch)
    comparison.state_bytes = state_bytes_per_vehicle(factories)
    return comparison
