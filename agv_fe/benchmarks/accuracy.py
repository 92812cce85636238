"""Accuracy and cost of the robust observer against the augmented-state EKF on identical noisy data."""

from __future__ import annotations

import dataclasses
import os
import statistics
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from agv_fe.benchmarks import report_header
from edge_client.evaluation import RMSE_AFTER_S, RMSE_LATE_S, Comparison, DetectionRule, compare, step_cost_us
from edge_client.library import EVALUATION_SCENARIOS, builtin_scenario
from edge_client.scenario import REALISTIC_NOISE, Scenario, SensorNoise
from edge_client.simulation import ekf_factory, observer_factory
from synth.analysis import FrozenResponse, frozen_comparison
from synth.design import synthesize
from synth.gains import ObserverGains
from synth.observer import FuzzyObserver, StepResult, _features, _gain_products, switched_step
from synth.options import ROBUST_DECAY_RATE, DesignOptions

SEEDS = 5
BATCH = 1000
COST_REPEATS = 5
#: Speeds of the frozen-premise table [m/s] (r = 0).
FROZEN_SPEEDS = (5.0, 10.0, 25.0, 30.0)


def _noise_free(name: str, seed: int) -> Scenario:
    return builtin_scenario(name, noise=SensorNoise(), seed=seed)


def _measured_start(name: str, seed: int) -> Scenario:
    """The scenario with both estimators started as the service starts an observer: from the first
    measurement (v_x and r measured, v_y = 0), not from the paper's [5, -1, 0]."""
    scenario = builtin_scenario(name, noise=REALISTIC_NOISE, seed=seed)
    return scenario.model_copy(update={"observer_initial_state": None})


class _CountingSwitched(FuzzyObserver):
    """A switched observer that counts the samples each vehicle spent on the fast set."""

    def __init__(self, gains: ObserverGains, y0: Any, x_hat0: Any = None, u0: Any = None) -> None:
        super().__init__(gains, y0, x_hat0, u0)
        self.fast_samples = self.samples = 0

    def step(self, y: Any, u: Any) -> StepResult:
        result = super().step(y, u)
        if result.fast is not None:
            self.fast_samples += int(result.fast[0])
            self.samples += 1
        return result


class _Pinned(FuzzyObserver):
    """A switched observer held on one set (``every``-th vehicle fast, 0: none) for the cost table: a settled
    fleet, whose statistic stays below the threshold (the cost probe's inputs are random, not a trajectory)."""

    def __init__(self, gains: ObserverGains, y0: Any, x_hat0: Any = None, every: int = 0, u0: Any = None) -> None:
        super().__init__(gains, y0, x_hat0, u0)
        # never raised by the statistic; the pinned vehicles' countdown outlasts any cost probe
        self.runtime = dataclasses.replace(self.runtime, switch_threshold=float("inf"))
        self.left.fill(0)
        if every:
            self.left[::every] = 1 << 40


def _counting(gains: ObserverGains, runs: list[_CountingSwitched]) -> Any:
    def make(y0: Any, x_hat0: Any, u0: Any = None) -> FuzzyObserver:
        obs = _CountingSwitched(gains, y0, x_hat0, u0)
        runs.append(obs)
        return obs

    return make


def _pinned(gains: ObserverGains, every: int) -> Any:
    def make(y0: Any, x_hat0: Any, u0: Any = None) -> FuzzyObserver:
        return _Pinned(gains, y0, x_hat0, every, u0)

    return make


def mixed_batch_split(gains: ObserverGains, every: int, batch: int = BATCH, steps: int = 200) -> dict[str, float]:
    """Where a switched observer's step goes for a batch with every ``every``-th vehicle on the fast set (0: none).

    Medians [us] over ``steps`` of the whole step (:func:`synth.observer.switched_step`), of its feature matrix
    Phi alone and of its gain products alone (one set's GEMMs, or both sets' and the per-vehicle pick), each
    timed right after an EKF step of the same batch, which leaves the caches as the cost table finds them.
    """
    rng = np.random.default_rng(0)
    y = np.column_stack([rng.uniform(6.0, 28.0, batch), rng.uniform(-0.4, 0.4, batch)])
    u = np.column_stack([rng.uniform(0.0, 300.0, batch), rng.uniform(-0.05, 0.05, batch)])
    observer = _Pinned(gains, y, every=every)
    ekf = ekf_factory(gains)(y, None)
    rt, z, stat, left = observer.runtime, observer.z, observer.stat, observer.left
    fast = left > 0
    mixed = bool(0 < np.count_nonzero(fast) < batch)
    Phi, x, _, _ = _features(rt, z, y, u)
    parts: dict[str, Any] = {
        "step": lambda: switched_step(rt, z, stat, left, y, u),
        "features": lambda: _features(rt, z, y, u),
        "gain products": lambda: _gain_products(rt, Phi, x, fast, mixed),
    }
    times: dict[str, list[float]] = {name: [] for name in parts}
    for _ in range(steps):
        for name, part in parts.items():
            ekf.step(y, u)
            started = time.perf_counter()
            part()
            times[name].append(time.perf_counter() - started)
    return {name: 1e6 * statistics.median(t) for name, t in times.items()}


def _noise_part(noisy: float, noise_free: float) -> float:
    """RMS of the part of the error that sensor noise adds (the two parts are nearly uncorrelated)."""
    return float(max(noisy**2 - noise_free**2, 0.0) ** 0.5)


@dataclass
class AccuracyResults:
    """What one accuracy run measured: the designs, the comparisons on every scenario, the step costs."""

    default: ObserverGains  # the switched robust design
    one_set: ObserverGains
    h2_form: ObserverGains
    seeds: int
    rule: DetectionRule
    #: realistic noise, one per scenario of EVALUATION_SCENARIOS; the same without noise (seed 0)
    rows: list[Comparison]
    clean: list[Comparison]
    #: fraction of the default observer's samples on the fast set, by scenario
    fast_share: dict[str, float]
    #: the paper's scenarios started from the first measurement, by scenario
    as_deployed: dict[str, Comparison]
    #: the names of the default design's cost variants (the other rows of ``costs`` are other designs)
    variants: tuple[str, ...]
    #: COST_REPEATS step costs [us] by variant, each {"observer": ..., "EKF": ...}
    costs: dict[str, list[dict[str, float]]]
    #: one settled vehicle's step cost [us]
    single: dict[str, float]
    #: the settled and the 1-in-100 batch's step split into its parts [us] (:func:`mixed_batch_split`)
    mixed_split: dict[str, dict[str, float]]
    #: the 1-minute load average before and after the cost measurements (the machine may be shared)
    load_average: tuple[float, float]
    #: (v_x, (fast set, quiet set, 'h2', Kalman)) at the frozen premises of FROZEN_SPEEDS
    frozen: list[tuple[float, tuple[FrozenResponse, ...]]]

    @property
    def cost_ratio(self) -> dict[str, float]:
        """Median over the runs of EKF / observer step cost, by variant."""
        return {name: statistics.median(c["EKF"] / c["observer"] for c in runs) for name, runs in self.costs.items()}


def measure(seeds: int = SEEDS) -> AccuracyResults:
    """Synthesise the designs, run every estimator on every scenario, and time their steps."""
    default = synthesize(options=DesignOptions())  # the switched robust design
    one_set = synthesize(options=DesignOptions(switching=None))
    h2_form = synthesize(options=DesignOptions(design="robust", robust_cost="h2"))
    paper = synthesize(options=DesignOptions(design="paper"))
    switched_runs: list[_CountingSwitched] = []
    rule = DetectionRule()
    factories = {
        "observer": _counting(default, switched_runs),
        "EKF": ekf_factory(default),
        "paper": observer_factory(paper),
        "h2": observer_factory(h2_form),
        "one set": observer_factory(one_set),
    }
    rows = []
    clean = []
    fast_share: dict[str, float] = {}
    for name in EVALUATION_SCENARIOS:
        print(f"  {name} ...", flush=True)
        switched_runs.clear()
        rows.append(compare(name, factories, seeds, rule, batch=10))
        runs = [r for r in switched_runs if r.samples > 100]  # the accuracy runs, not the cost probes
        fast_share[name] = sum(r.fast_samples for r in runs) / max(1, sum(r.samples for r in runs))
        clean.append(compare(name, factories, 1, rule, batch=10, scenario_factory=_noise_free))
    # the scenarios that start the observer away from the measurement (the paper's), started from it as well
    restarted = [
        n for n in EVALUATION_SCENARIOS if builtin_scenario(n, noise=REALISTIC_NOISE).observer_initial_state is not None
    ]
    as_deployed = {
        name: compare(name, {k: factories[k] for k in ("observer", "EKF", "one set")}, seeds, rule, batch=10,
                      scenario_factory=_measured_start)
        for name in restarted
    }  # fmt: skip
    # each variant interleaved with the EKF alone (the step after the EKF's pays for the cache the EKF's
    # covariances evicted, so the pairing must be the same for all): the default pinned to its sets, a settled
    # fleet first (the cost probe's inputs are random, not trajectories), and one gain set
    variants = {
        "settled fleet (all on the quiet set)": 0,
        "1 in 100 on the fast set": 100,
        "1 in 10 on the fast set": 10,
        "all on the fast set": 1,
    }
    load_before = os.getloadavg()[0]
    costs = {
        name: [step_cost_us({"observer": _pinned(default, every), "EKF": factories["EKF"]}, BATCH)
               for _ in range(COST_REPEATS)]
        for name, every in variants.items()
    }  # fmt: skip
    costs[ONE_SET_COST] = [
        step_cost_us({"observer": factories["one set"], "EKF": factories["EKF"]}, BATCH) for _ in range(COST_REPEATS)
    ]
    single = step_cost_us({"observer": _pinned(default, 0), "EKF": factories["EKF"]}, 1)
    mixed_split = {name: mixed_batch_split(default, variants[name]) for name in list(variants)[:2]}
    load_average = (load_before, os.getloadavg()[0])
    frozen: list[tuple[float, tuple[FrozenResponse, ...]]] = []
    for v_x in FROZEN_SPEEDS:
        fast, kal = frozen_comparison(default, v_x)
        quiet, _ = frozen_comparison(default.quiet_gains(), v_x)
        h2o, _ = frozen_comparison(h2_form, v_x)
        frozen.append((v_x, (fast, quiet, h2o, kal)))
    return AccuracyResults(
        default=default,
        one_set=one_set,
        h2_form=h2_form,
        seeds=seeds,
        rule=rule,
        rows=rows,
        clean=clean,
        fast_share=fast_share,
        as_deployed=as_deployed,
        variants=tuple(variants),
        costs=costs,
        single=single,
        mixed_split=mixed_split,
        load_average=load_average,
        frozen=frozen,
    )


#: The cost row of the one-set design.
ONE_SET_COST = "one gain set (`switching` null)"
CHANNELS = ("T_f", "delta_f")


def _ratio(c: Comparison, estimator: str, metric: str, channel: str) -> float:
    """The estimator's median ``metric`` over the EKF's (nan where either has none)."""
    return (c.median(estimator, metric, channel) or float("nan")) / (c.median("EKF", metric, channel) or float("nan"))


def _worst(ratios: Iterable[float]) -> float:
    """The largest ratio, 0 when there is none (a nan ratio never wins)."""
    worst = 0.0
    for ratio in ratios:
        worst = max(worst, ratio)
    return worst


def _started(r: AccuracyResults, c: Comparison) -> Comparison:
    """The scenario as the service starts an observer: the restarted run where there is one."""
    return r.as_deployed.get(c.scenario, c)


def run(out_dir: Path, seeds: int = SEEDS) -> Path:
    """Measure and write ``accuracy.md`` into ``out_dir``."""
    results = measure(seeds)
    path = out_dir / "accuracy.md"
    path.write_text("\n".join(render(results)) + "\n")
    return path


def render(r: AccuracyResults) -> list[str]:
    """The report's lines, section by section."""
    return [
        *_render_intro(r),
        *_render_accuracy(r),
        *_render_error_sources(r),
        *_render_frozen(r),
        *_render_one_set(r),
        *_render_as_deployed(r),
        *_render_detection(r),
        *_render_cost(r),
        *_render_reading(r),
    ]


def _render_intro(r: AccuracyResults) -> list[str]:
    default, cert = r.default, r.default.certificate
    sw_rule = default.options.switching
    assert sw_rule is not None
    return [
        report_header("Accuracy: robust observer vs augmented-state EKF", "accuracy"),
        "Observer: the default design, the switched robust design (docs/switched-gains.md): a fast gain set, the "
        f"one-set robust design at decay rate {default.options.robust_decay_rate:g}, and a quiet set designed with "
        "the 'h2' cost LMIs, both under one fuzzy Lyapunov function (fault order "
        f"{default.options.fault_order}; certified decay rate {cert.decay_rate:.4f} for any switching sequence; "
        f"guaranteed H2 cost {cert.performance['h2_cost_bound']:.3f} for the quiet set, "
        f"{cert.performance['fast_set_h2_cost_bound']:.3f} for the fast set), gains version {default.version}. "
        f"Rule (defaults of `SwitchingRule`): the fast set for the first {sw_rule.start_s:g} s and for "
        f"{sw_rule.hold_s:g} s after the innovation statistic exceeds {sw_rule.threshold:g}; the quiet set "
        "otherwise. EKF: augmented state with "
        "random-walk faults, Joseph-form update, tuned from the same noise model (design options `noise`). "
        "Both run on the same simulated measurements, realistic sensor noise (sigma v_x = 0.05 m/s, "
        f"sigma r = 0.005 rad/s), {r.seeds} seeds per scenario. RMSE from t = {RMSE_AFTER_S:g} s; "
        "median over seeds. "
        "'paper' is the stability-only Theorem 2 design on the same data, for reference.\n",
    ]


def _render_accuracy(r: AccuracyResults) -> list[str]:
    lines = [
        "## Accuracy\n",
        "| scenario | T_f RMSE observer [N m] | T_f RMSE EKF [N m] | **T_f ratio obs/EKF** "
        "| delta_f RMSE observer [rad] | delta_f RMSE EKF [rad] | **delta_f ratio obs/EKF** "
        f"| v_y RMSE obs / EKF [m/s] | T_f RMSE paper [N m] | T_f / delta_f ratio from t = {RMSE_LATE_S:g} s "
        "| time on the fast set |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for c in r.rows:
        cells = [c.scenario]
        for ch in CHANNELS:
            o = c.median("observer", "rmse", ch) or float("nan")
            e = c.median("EKF", "rmse", ch) or float("nan")
            cells += [f"{o:.4g}", f"{e:.4g}", f"**{o / e:.3f}**"]
        vo, ve = c.median("observer", "rmse", "v_y"), c.median("EKF", "rmse", "v_y")
        cells.append(f"{vo:.4g} / {ve:.4g}")
        cells.append(f"{c.median('paper', 'rmse', 'T_f'):.4g}")
        late = [_ratio(c, "observer", "rmse_late", ch) for ch in CHANNELS]
        cells.append(f"{late[0]:.3f} / {late[1]:.3f}")
        cells.append(f"{100 * r.fast_share[c.scenario]:.0f} %")
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def _render_error_sources(r: AccuracyResults) -> list[str]:
    lines = [
        "",
        f"## Where the torque-fault error comes from (window from t = {RMSE_LATE_S:g} s)\n",
        "The same scenarios without sensor noise (seed 0) give the error the estimator makes on the signal "
        "itself (tracking lag, model error); the noise part is sqrt(noisy^2 - noise-free^2). 'h2' is the "
        "robust design with `robust_cost='h2'` (cost bounded alone, decay rate certified separately), run on "
        "the same data.\n",
        "| scenario | T_f noise-free obs / EKF [N m] | T_f noise part obs / EKF [N m] "
        f"| 'h2' T_f ratio from {RMSE_AFTER_S:g} s / from {RMSE_LATE_S:g} s "
        f"| 'h2' noise part [N m] | 'h2' delta_f ratio from {RMSE_AFTER_S:g} s |",
        "|---|---|---|---|---|---|",
    ]
    for c, z in zip(r.rows, r.clean, strict=True):
        late_rmse = {e: c.median(e, "rmse_late", "T_f") or float("nan") for e in ("observer", "EKF", "h2")}
        free_rmse = {e: z.median(e, "rmse_late", "T_f") or float("nan") for e in ("observer", "EKF", "h2")}
        noise_rmse = {e: _noise_part(late_rmse[e], free_rmse[e]) for e in late_rmse}
        h2_3s = _ratio(c, "h2", "rmse", "T_f")
        h2_d = _ratio(c, "h2", "rmse", "delta_f")
        h2_late = late_rmse["h2"] / late_rmse["EKF"]
        lines.append(
            f"| {c.scenario} | {free_rmse['observer']:.3g} / {free_rmse['EKF']:.3g} "
            f"| {noise_rmse['observer']:.3g} / {noise_rmse['EKF']:.3g} | {h2_3s:.3f} / {h2_late:.3f} "
            f"| {noise_rmse['h2']:.3g} | {h2_d:.3f} |"
        )
    return lines


def _render_frozen(r: AccuracyResults) -> list[str]:
    lines = [
        "",
        "At a frozen premise (r = 0, v_y = 0) the error dynamics are linear and time-invariant; the steady "
        "state of each estimator under the design's noise model, against the Kalman filter of the same "
        "linear model (`synth.analysis.frozen_comparison`, the best any linear filter can do there):\n",
        "| v_x [m/s] | T_f RMS, sensor noise only: fast set / quiet set / 'h2' / Kalman [N m] "
        "| weighted cost: fast / quiet / 'h2' / Kalman | slowest pole: fast / quiet / 'h2' / Kalman |",
        "|---|---|---|---|",
    ]
    for v_x, sets in r.frozen:
        lines.append(
            f"| {v_x:g} | {' / '.join(f'{e.torque_noise_nm:.2f}' for e in sets)} "
            f"| {' / '.join(f'{e.cost:.3f}' for e in sets)} "
            f"| {' / '.join(f'{e.slowest_pole:.4f}' for e in sets)} |"
        )
    return lines


def _render_one_set(r: AccuracyResults) -> list[str]:
    fast_cert = r.one_set.certificate
    lines = [
        "",
        "## One gain set (`switching` null)\n",
        f"The robust design with one gain set, certified decay rate {fast_cert.decay_rate:.4f} "
        f"(its default, {ROBUST_DECAY_RATE:g}; guaranteed cost {fast_cert.performance['h2_cost_bound']:.3f}), "
        f"gains version {r.one_set.version}: the default design before switched gain sets, and the cheapest step. "
        "Same data as the first table; from the measurement, the section below.\n",
        f"| scenario | **T_f ratio one set/EKF** | **delta_f ratio one set/EKF** | T_f ratio from {RMSE_LATE_S:g} s |",
        "|---|---|---|---|",
    ]
    for c in r.rows:
        ratio = {ch: _ratio(c, "one set", "rmse", ch) for ch in CHANNELS}
        late_ratio = _ratio(c, "one set", "rmse_late", "T_f")
        lines.append(f"| {c.scenario} | **{ratio['T_f']:.3f}** | **{ratio['delta_f']:.3f}** | {late_ratio:.3f} |")
    return lines


def _render_as_deployed(r: AccuracyResults) -> list[str]:
    lines = [
        "",
        "## The paper's scenarios, started as the service starts an observer\n",
        "The paper starts its observer at [v_x, v_y, r] = [5, -1, 0] while the vehicle drives at about "
        "10 m/s, to show convergence, and the tables above keep that start for both estimators. The service "
        "starts an observer from the vehicle's first measurement (measured v_x and r, v_y = 0), as the "
        "highway and urban scenarios do. Here the paper's scenarios start that way too, the EKF with them "
        "(same seeds, same noise):\n",
        "| scenario | **T_f ratio obs/EKF** | **delta_f ratio obs/EKF** | T_f ratio one set/EKF "
        "| delta_f ratio one set/EKF | T_f RMSE EKF [N m] |",
        "|---|---|---|---|---|---|",
    ]
    for c in r.rows:
        if c.scenario not in r.as_deployed:
            continue
        started = r.as_deployed[c.scenario]
        deployed = {(e, ch): _ratio(started, e, "rmse", ch) for e in ("observer", "one set") for ch in CHANNELS}
        lines.append(
            f"| {c.scenario} | **{deployed['observer', 'T_f']:.3f}** | **{deployed['observer', 'delta_f']:.3f}** "
            f"| {deployed['one set', 'T_f']:.3f} | {deployed['one set', 'delta_f']:.3f} "
            f"| {started.median('EKF', 'rmse', 'T_f'):.4g} |"
        )
    return lines


def _render_detection(r: AccuracyResults) -> list[str]:
    rule = r.rule
    lines = [
        "",
        "## Detection (|estimate| above "
        f"{rule.torque_nm:g} N m / {rule.steer_rad:g} rad for {rule.hold_s:g} s; delay after onset, median)\n",
        "| scenario | T_f delay observer [s] | T_f delay EKF [s] | delta_f delay observer [s] | delta_f delay EKF [s] "
        "| false detections observer / EKF |",
        "|---|---|---|---|---|---|",
    ]
    for c in r.rows:
        d = [c.median(e, "detection_delay_s", ch) for ch in CHANNELS for e in ("observer", "EKF")]
        false = [sum(sum(s.false_detections.values()) for s in c.scores[e]) for e in ("observer", "EKF")]
        lines.append(
            f"| {c.scenario} | "
            + " | ".join("-" if v is None else f"{v:.2f}" for v in (d[0], d[1], d[2], d[3]))
            + f" | {false[0]} / {false[1]} |"
        )
    return lines


def _render_cost(r: AccuracyResults) -> list[str]:
    cost_ratio, single, memory = r.cost_ratio, r.single, r.rows[0].state_bytes
    runs_text = {name: ", ".join(f"{c['EKF'] / c['observer']:.1f}" for c in runs) for name, runs in r.costs.items()}
    return [
        "",
        "## Cost\n",
        f"One step for {BATCH} vehicles, median of 200 steps, each variant interleaved with the EKF alone, "
        f"{COST_REPEATS} runs (median of the runs). The default design's step also updates each vehicle's "
        "innovation statistic; it is pinned to its sets here (the probe's inputs are random, not trajectories). "
        "A batch with vehicles on both sets runs both sets' GEMMs and takes each vehicle's column from its "
        "set; a large fleet's batch is usually such a mixed one, with a few vehicles on the fast set after a "
        "start or a large innovation.\n",
        "| | observer [us] | EKF [us] | EKF / observer |",
        "|---|---|---|---|",
        *(
            f"| {'default, ' if name in r.variants else ''}{name} | "
            f"{statistics.median(c['observer'] for c in runs):.1f} | {statistics.median(c['EKF'] for c in runs):.1f} "
            f"| **{cost_ratio[name]:.1f}** (runs: {runs_text[name]}) |"
            for name, runs in r.costs.items()
        ),
        f"| default, 1 vehicle, settled | {single['observer']:.1f} | {single['EKF']:.1f} "
        f"| {single['EKF'] / single['observer']:.1f} |",
        "",
        f"State per vehicle: {memory['observer']} bytes for the observer (state, innovation statistic, fast-set "
        f"countdown), {memory['EKF']} for the EKF (state and covariance). Load average (1 min, {os.cpu_count()} "
        f"cores) {r.load_average[0]:.1f} before the cost measurements and {r.load_average[1]:.1f} after: "
        + ("the machine was shared with other work during them.\n" if max(r.load_average) > 1.0 else "idle.\n"),
        f"Where a mixed batch's time goes: the step for {BATCH} vehicles and two of its parts, each timed right "
        "after an EKF step (`mixed_batch_split`), medians of 200:\n",
        "| batch | whole step [us] | feature matrix Phi [us] | gain products [us] |",
        "|---|---|---|---|",
        *(
            f"| {name} | {s['step']:.1f} | {s['features']:.1f} | {s['gain products']:.1f} |"
            for name, s in r.mixed_split.items()
        ),
        "",
    ]


def _render_reading(r: AccuracyResults) -> list[str]:
    worst = {ch: _worst(_ratio(c, "observer", "rmse", ch) for c in r.rows) for ch in CHANNELS}
    deployed_worst = {ch: _worst(_ratio(_started(r, c), "observer", "rmse", ch) for c in r.rows) for ch in CHANNELS}
    # one gain set: the worst over both starts, the paper's (the rows) and the measurement's
    worst_one = {
        ch: _worst([_ratio(c, "one set", "rmse", ch) for c in r.rows] + [
            _ratio(_started(r, c), "one set", "rmse", ch) for c in r.rows
        ])
        for ch in CHANNELS
    }  # fmt: skip
    cost_ratio = r.cost_ratio
    default_ratios = [cost_ratio[name] for name in r.variants]
    return [
        "## Reading\n",
        f"Targets: accuracy ratio <= 1.0 on both channels, cost ratio >= 10 at {BATCH} vehicles. This run, the "
        f"default design over every scenario and both starts (the paper's and the measurement's): worst ratio "
        f"T_f {max(worst['T_f'], deployed_worst['T_f']):.3f}, delta_f "
        f"{max(worst['delta_f'], deployed_worst['delta_f']):.3f} "
        f"({'met' if max(*worst.values(), *deployed_worst.values()) <= 1.0 else 'not met on every scenario'}); "
        f"cost ratio {min(default_ratios):.1f} to {max(default_ratios):.1f} "
        f"({'met' if min(default_ratios) >= 10 else 'not met'}). One gain set: worst ratio T_f "
        f"{worst_one['T_f']:.3f}, delta_f {worst_one['delta_f']:.3f} "
        f"({'met' if max(worst_one.values()) <= 1.0 else 'not met on every scenario'}); cost ratio "
        f"{cost_ratio[ONE_SET_COST]:.1f}.",
        "",
        ANALYSIS,
    ]


ANALYSIS = """* **Against the paper's design.** The stability-only gains amplify sensor noise into torque-fault
  errors of thousands of N m. The robust design cuts that by a factor of about a thousand, and the
  certificate still covers the whole premise domain.
* **Against the EKF.**
  1. *What is reported.* The observer's state is a one-step prediction (it has seen y up to k - 1),
     while an EKF reports x_{k|k}, which has also seen y_k. The robust design now designs an output
     gain K_f together with its gains, and reports f_hat + K_f (y_k - C x_hat): the faults filtered
     with the current measurement (docs/math.md, section 10). On a one-point premise box its
     guaranteed cost equals the steady-state cost of the Kalman filter to 0.5 % (a test checks it
     against scipy). Before it, the recorded run (commit f8ed895) had worst ratios of 1.038 (T_f)
     and 1.035 (delta_f).
  2. *Why one gain set's torque ratio is above 1 on paper-1 and urban: the 'joint' cost form.* This
     is the one-set design, which was the default until 2026-11-24 and is now the default's fast set.
     Summing its ('joint') LMI over time gives trace Z >= E|z|^2 + (1 - alpha^2) E[e^T P e]: certifying
     the decay rate alpha in the same inequality adds a penalty on the error's Lyapunov energy,
     which is largest in the slow modes. The optimum therefore tracks the faults faster than the
     H2-optimal filter. At every frozen premise its slowest pole is faster than the Kalman filter's;
     at 0.995 its torque-fault error from sensor noise alone was about 40 % higher and its total
     cost about 10 % higher (the run at commit 543a8fc), and the default's fast set, at 0.994, is
     further off (the table above). The simulations show both sides. Without
     noise the one-set observer's torque error was below the EKF's on every scenario (faster
     tracking); with noise its noise part was about a third higher on the 6-11 m/s scenarios
     (paper-1, urban), which is what tips them over 1. On the highway the two noise parts are
     equal (the linear analysis does not cover what dominates there), and faster tracking wins.
     Ruled out before this was found (5 seeds, window from 8 s): the paper's wrong initial state,
     the steering fault, the turns, noise through the measured premise, and the EKF's drag
     Jacobian and model-error floor.
  3. *The 'h2' cost form removes the penalty* and certifies the same decay rate with LMIs of its
     own (docs/math.md, section 10). At every frozen premise its cost is within about 1 % of the
     Kalman filter's, and in the simulations its noise part falls to the EKF's. What it cannot do
     with one constant gain is the EKF's start: the EKF begins with a large covariance, converges
     fast and then settles to the steady-state gain. On paper-1, where both estimators start from
     the paper's wrong initial state (v_x 5 m/s off), the 'h2' form's slower transient dominates
     the window from 3 s; on the highway it loses the tracking advantage. Neither form meets the
     target on every scenario with one gain set; the default combines them (item 5). 'h2' alone is
     for fleets whose faults are steady and who want the least noise and one set
     (`agv-fe synth --robust-cost h2`, or `robust_cost` in a profile's design options).
  4. *The decay-rate knob trades paper-1 against urban.* robust_decay_rate 0.993 gave paper-1 1.009
     and urban 1.041; 0.997 gave paper-1 1.27 and urban 0.992 (window from 3 s), with one gain set,
     which stays at 0.995. Weighting the torque channel more (torque_fault_scale_nm 5 or 7 instead of 10) left
     the torque ratios unchanged. Minimising the mean of the per-rule-pair costs instead of their
     maximum made paper-1 slightly worse (1.045).
  5. *The default: two gain sets under one Lyapunov function* (docs/switched-gains.md). The EKF
     gets both a fast start and a quiet steady state because its gain varies in time. The default
     design gets part of that with two constant sets: the 'joint' one-set design as the fast set,
     after a start and for a second after a large innovation, and a quiet 'h2'-form set otherwise,
     designed in the same fuzzy Lyapunov function, so that the certified decay rate holds for any
     switching sequence. Opt-in at first, with the fast set at 0.995, it brought urban under 1
     (0.994) and paper-1 from the paper's start to 1.012: paper-1's sinusoidal steering fault keeps
     the innovation high, so the fast set runs most of that scenario, and the paper's start is
     cleared at the fast set's rate. With the fast set at 0.994 (2026-11-24, 5 seeds, both starts)
     every ratio was at most 0.992 on the torque fault and 0.986 on the steering fault; at 0.993 as
     well (at most 0.992 and 0.986), but Clarabel warned that its solution might be inaccurate (the
     design still verified). 0.994 became a switched design's default rate, and the switched design
     the default (`--no-switching`, or `"switching": null` in a profile's design options, for one set).
  6. *Paper-1's torque gap is the paper's start.* The paper starts both estimators 5 m/s below the
     measured speed. The EKF clears that with a gain that starts large and shrinks; a constant gain
     clears it at its designed rate, and the tail of that transient is still in the window from 3 s.
     Started from the measurement, as the service starts an observer (section above), one gain set
     is under 1 on paper-1 too. Urban, which always started from the measurement, stays about 1 %
     over with one gain set. Its decay-rate knob with both starts (2026-11-24, 5 seeds, window from
     3 s; robust_decay_rate 0.995 / 0.996 / 0.997):
     - paper-1 from the paper's start 1.032 / 1.109 / 1.274, from the measurement 0.995 / 0.989 / 0.987;
     - paper-2 from the paper's start 0.962 / 0.981 / 1.016, from the measurement 0.954 / 0.961 / 0.970;
     - highway 0.967 / 0.976 / 0.985; urban 1.007 / 0.997 / 0.992;
     - delta_f between 0.909 and 0.993 in every case.

     At 0.996 every scenario started from the measurement meets the target on both channels, and
     paper-1 from the paper's start misses it by 11 %. One gain set stays at 0.995: a faster
     certified convergence, and the paper's own test of convergence is not given up for 1 % on
     urban; the switched default meets both (item 5).
* **Cost.** The observer step is a few broadcast products on [x, V_x x', r x', V_x r x'] and two
  GEMMs over the fleet, one for the next state and a small one for the filtered estimate, with no
  covariance and no Jacobian. The EKF propagates a 5 x 5 covariance per vehicle, written with the
  same care: batched, contiguous operands, a Joseph update expanded exactly for the selection
  measurement matrix. The default's step adds each vehicle's innovation statistic (a few vector
  operations, with the innovation taken from the small GEMM on [y; z]) and, when some vehicles run
  the fast set and others the quiet one, both sets' GEMMs and a per-column pick: the mixed batch is
  the dearest (cost table). Both designs are far below the EKF, and at 1,000 vehicles and 100 Hz
  either takes under 1 % of a core.
* **What bounds a mixed batch** (issue 28, item 4). Its extra time is in the gain products (the
  split table): the feature matrix is the same for both sets, and the switching rule's bookkeeping
  (the mask, the countdown) cost nothing measurable (2026-11-26: a probe that skipped the second
  set's products with the same mask ran a 1-in-100 batch in 71.0 us against 71.3 us settled,
  medians of 800 steps each after an EKF step). The products
  of a mixed batch are one GEMM of both sets stacked (10 rows instead of 5 over the same features:
  about 7 us more at 1,000 vehicles, as it reads the features once) and one masked copy each for
  the next state and the reported rows (3 to 5 us each), each timed after an EKF step as in the
  cost table, at a load average of about 7. Taking only the fast vehicles' columns instead (their
  indices, a gather, a small GEMM, a scatter, for the state and again for the reported rows) was
  slower: 1 in 100 cost 13 to 23 us more than the stacked GEMM (five alternated runs), because after an EKF step each
  numpy call on the batch costs 3 to 12 us whatever its size (flatnonzero of 1,000 flags, a gather
  of 10 columns, a 5 x 28 by 28 x 10 product). The mixed batch needs at least the second set's
  products and a pick per vehicle; at one to three more numpy calls of a few us each on a step of
  about 50 to 70 us, its cost ratio stays about a fifth below the settled one's, which is what the
  cost table shows. The code is the stacked form, and of the reported rows it picks only those
  where the two sets differ: the two fault rows, where their output gains differ (the rest of the
  reported estimate is the state both sets share). That took 1 in 100 from 10.4-10.6 to 10.8-11.0
  and 1 in 10 from 9.8-10.1 to 10.3-10.5 (2026-11-26, load about 3, the two versions alternated
  three times, 3 runs each).
* **What the EKF does not give.** A stability certificate. The observer's error dynamics are proven
  to contract at the certified rate for every premise trajectory in the domain, and its guaranteed
  H2 cost bounds the variance of the reported fault errors under the stated noise model.

## History of the cost ratio

* 2026-11-27 22:39 UTC (commit b6e154e): the first run on an Intel Xeon 2-core machine
  (every earlier one ran on an AMD EPYC), idle (load 1.0): settled 9.2, 1 in 100 8.1, 1 in 10 7.7, all
  on the fast set 8.9, one gain set 11.2. The EKF's step took 7 % longer than on the EPYC (725 against
  674 us), the observer's 52 % (78.6 against 51.7 us settled): its feature matrix Phi, about twenty
  numpy calls on 1,000-element rows, took 46.7 against 24.5 us (the split table). Measured here
  (2026-11-27, `timeit`): one `np.multiply` of two 1,000-element rows 1.3 us, of a 5 x 1,000 block by a row
  4.2 us; the observer's step is bound by per-call cost, the EKF's by its 3 x 3 and 5 x 5 products. The
  target of 10 is met on the EPYC (the run below), not on this machine.
* 2026-11-27 07:14 UTC (commit 0812cad, AMD EPYC, idle): settled 13.0, 1 in 100 10.7, 1 in 10 10.3,
  all on the fast set 12.7, one gain set 15.6.
* 2026-11-24 23:56 UTC (commit 6f55360, machine load not recorded): settled 13.2, 1 in 100 on the
  fast set 10.7, 1 in 10 10.1, all on the fast set 12.8, one gain set 15.8.
* Commit be07ab9 (2026-11-24, docs/switched-gains.md): settled 10.4, 1 in 100 8.5, 1 in 10 7.9,
  the figures issue 28 quotes; the step was made cheaper before the run above.
* With colder caches than the cost table's, the same ratios fall back to those: with nine
  observers stepped in turn after the EKF (2026-11-26, load average about 6), settled 10.3 and
  1 in 100 8.4 (a probe, not this benchmark).
"""
