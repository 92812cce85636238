"""Accuracy and cost of the robust observer against the augmented-state EKF on identical noisy data."""

from __future__ import annotations

import statistics
from pathlib import Path

from agv_fe.benchmarks import report_header
from edge_client.evaluation import RMSE_AFTER_S, RMSE_LATE_S, DetectionRule, compare, step_cost_us
from edge_client.library import EVALUATION_SCENARIOS
from edge_client.simulation import ekf_factory, observer_factory
from synth.design import synthesize
from synth.options import DesignOptions

SEEDS = 5
BATCH = 1000
COST_REPEATS = 5


def run(out_dir: Path, seeds: int = SEEDS) -> Path:
    robust = synthesize(options=DesignOptions(design="robust"))
    paper = synthesize(options=DesignOptions(design="paper"))
    rule = DetectionRule()
    factories = {"observer": observer_factory(robust), "EKF": ekf_factory(robust), "paper": observer_factory(paper)}
    rows = []
    for name in EVALUATION_SCENARIOS:
        print(f"  {name} ...", flush=True)
        c = compare(name, factories, seeds, rule, batch=10)
        rows.append(c)
    costs = [step_cost_us({k: factories[k] for k in ("observer", "EKF")}, BATCH) for _ in range(COST_REPEATS)]
    ratios = [c["EKF"] / c["observer"] for c in costs]
    obs_us = statistics.median(c["observer"] for c in costs)
    ekf_us = statistics.median(c["EKF"] for c in costs)
    single = step_cost_us({k: factories[k] for k in ("observer", "EKF")}, 1)
    memory = rows[0].state_bytes
    cert = robust.certificate
    lines = [
        report_header("Accuracy: robust observer vs augmented-state EKF", "accuracy"),
        f"Observer: the default 'robust' design (H2 guaranteed cost, fault order {robust.options.fault_order}, "
        f"fuzzy Lyapunov matrix, certified decay rate {cert.decay_rate:.4f}, guaranteed cost "
        f"{cert.performance['h2_cost_bound']:.3f}), gains version {robust.version}. EKF: augmented state with "
        "random-walk faults, Joseph-form update, tuned from the same noise model (design options `noise`). "
        "Both run on the same simulated measurements, realistic sensor noise (sigma v_x = 0.05 m/s, "
        f"sigma r = 0.005 rad/s), {seeds} seeds per scenario. RMSE from t = {RMSE_AFTER_S:g} s; "
        "median over seeds. "
        "'paper' is the stability-only Theorem 2 design on the same data, for reference.\n",
        "## Accuracy\n",
        "| scenario | T_f RMSE observer [N m] | T_f RMSE EKF [N m] | **T_f ratio obs/EKF** "
        "| delta_f RMSE observer [rad] | delta_f RMSE EKF [rad] | **delta_f ratio obs/EKF** "
        f"| v_y RMSE obs / EKF [m/s] | T_f RMSE paper [N m] | T_f / delta_f ratio from t = {RMSE_LATE_S:g} s |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    worst = {"T_f": 0.0, "delta_f": 0.0}
    for c in rows:
        cells = [c.scenario]
        for ch in ("T_f", "delta_f"):
            o = c.median("observer", "rmse", ch) or float("nan")
            e = c.median("EKF", "rmse", ch) or float("nan")
            worst[ch] = max(worst[ch], o / e)
            cells += [f"{o:.4g}", f"{e:.4g}", f"**{o / e:.3f}**"]
        vo, ve = c.median("observer", "rmse", "v_y"), c.median("EKF", "rmse", "v_y")
        cells.append(f"{vo:.4g} / {ve:.4g}")
        cells.append(f"{c.median('paper', 'rmse', 'T_f'):.4g}")
        late = [
            (c.median("observer", "rmse_late", ch) or float("nan")) / (c.median("EKF", "rmse_late", ch) or float("nan"))
            for ch in ("T_f", "delta_f")
        ]
        cells.append(f"{late[0]:.3f} / {late[1]:.3f}")
        lines.append("| " + " | ".join(cells) + " |")
    lines += [
        "",
        "## Detection (|estimate| above "
        f"{rule.torque_nm:g} N m / {rule.steer_rad:g} rad for {rule.hold_s:g} s; delay after onset, median)\n",
        "| scenario | T_f delay observer [s] | T_f delay EKF [s] | delta_f delay observer [s] | delta_f delay EKF [s] "
        "| false detections observer / EKF |",
        "|---|---|---|---|---|---|",
    ]
    for c in rows:
        d = [c.median(e, "detection_delay_s", ch) for ch in ("T_f", "delta_f") for e in ("observer", "EKF")]
        false = [sum(sum(s.false_detections.values()) for s in c.scores[e]) for e in ("observer", "EKF")]
        lines.append(
            f"| {c.scenario} | "
            + " | ".join("-" if v is None else f"{v:.2f}" for v in (d[0], d[1], d[2], d[3]))
            + f" | {false[0]} / {false[1]} |"
        )
    lines += [
        "",
        "## Cost\n",
        "| | observer | EKF | EKF / observer |",
        "|---|---|---|---|",
        f"| step, {BATCH} vehicles, median of {COST_REPEATS} x 200 interleaved steps [us] | {obs_us:.1f} "
        f"| {ekf_us:.1f} | **{statistics.median(ratios):.1f}** (runs: {', '.join(f'{r:.1f}' for r in ratios)}) |",
        f"| step, 1 vehicle [us] | {single['observer']:.1f} | {single['EKF']:.1f} "
        f"| {single['EKF'] / single['observer']:.1f} |",
        f"| state per vehicle [bytes] | {memory['observer']} | {memory['EKF']} "
        f"| {memory['EKF'] / memory['observer']:.0f} |",
        "",
        "## Reading\n",
        f"Targets: accuracy ratio <= 1.0 on both channels, cost ratio >= 10 at {BATCH} vehicles. This run: "
        f"worst ratio T_f {worst['T_f']:.3f}, delta_f {worst['delta_f']:.3f} "
        f"({'met' if max(worst.values()) <= 1.0 else 'not met on every scenario'}); cost ratio "
        f"{statistics.median(ratios):.1f} ({'met' if statistics.median(ratios) >= 10 else 'not met'}).",
        "",
        ANALYSIS,
    ]
    path = out_dir / "accuracy.md"
    path.write_text("\n".join(lines) + "\n")
    return path


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
  2. *Where the torque ratio is still above 1.* Urban is within one percent of 1. Paper-1 is not,
     and its gap is steady-state noise, not a transient. In the window from 8 s (last column) the
     observer's torque-fault error is about 30 % above the EKF's. In the window from 3 s, the
     observer's faster response to the fault step at 5 s hides most of that. Measured in this
     session (5 seeds each, ratios of medians, window from 8 s), the gap stays when the cause is
     removed:
     - the paper's wrong initial state (both estimators started from the first measurement instead):
       1.29. From 3 s the ratio then drops from 1.03 to 0.995, so the initial state explains the
       3 s window's excess but not the steady state;
     - the sinusoidal steering fault: 1.37; the turns: 1.26;
     - noise entering through the measured premise (g and h evaluated at the true v_x and r): no
       change;
     - the drag damping in the EKF's Jacobian, or its model-error floor in Q: no change.
     At frozen premises the designed gains give a torque-fault error 5 % above the Kalman
     filter's of the same model (5.10 against 4.85 N m RMS at every speed), the price of the
     certified decay rate. That does not account for 30 %. The cause is open.
  3. *The decay-rate knob trades paper-1 against urban.* robust_decay_rate 0.993 gave paper-1 1.009
     and urban 1.041; 0.997 gave paper-1 1.27 and urban 0.992 (window from 3 s). The default stays
     at 0.995. Weighting the torque channel more (torque_fault_scale_nm 5 or 7 instead of 10) left
     the torque ratios unchanged. Minimising the mean of the per-rule-pair costs instead of their
     maximum made paper-1 slightly worse (1.045).
* **Cost.** The observer step is a few broadcast products on [x, V_x x, r x, V_x r x] and one GEMM
  over the fleet that yields both the next state and the filtered faults, with no covariance and
  no Jacobian. The EKF propagates a 5 x 5 covariance per vehicle, written with the same care:
  batched, contiguous operands, a Joseph update expanded exactly for the selection measurement
  matrix.
* **What the EKF does not give.** A stability certificate. The observer's error dynamics are proven
  to contract at the certified rate for every premise trajectory in the domain, and its guaranteed
  H2 cost bounds the variance of the reported fault errors under the stated noise model.
"""
