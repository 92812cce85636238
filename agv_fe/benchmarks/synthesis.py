"""Synthesis time of the observer LMIs: fuzzy-Lyapunov (32 vertex LMIs) and common-P designs."""

from __future__ import annotations

import statistics
import time
from pathlib import Path

from agv_fe.benchmarks import REFERENCE_CAR, report_header
from synth.design import synthesize
from synth.options import DesignOptions
from synth.params import OperatingBounds, VehicleParams

REPEATS = 5

#: A physical car as calibration makes it: wheel torque, effective mass, rolling resistance, cornering drag (two
#: more DMVT scalars), a steering lag; the box and design calibration chooses for such a car.
CALIBRATED_CAR = (
    REFERENCE_CAR,
    OperatingBounds(vy_min_mps=-0.5, vy_max_mps=0.5, steer_max_rad=0.15, front_lateral_force_max_n=9000.0),
)

#: (label, options, use_symmetry[, (params, bounds)]); the LMI counts in the labels are what each case solves.
CASES: list[
    tuple[str, DesignOptions, bool] | tuple[str, DesignOptions, bool, tuple[VehicleParams, OperatingBounds]]
] = [
    (
        "fuzzy P(h), Petersen form, mirror-reduced (8 LMIs of size 19)",
        DesignOptions(design="paper", lyapunov="fuzzy", lmi_form="petersen", optimise_decay_rate=False),
        True,
    ),
    (
        "fuzzy P(h), Petersen form, no reduction (16 LMIs of size 19)",
        DesignOptions(design="paper", lyapunov="fuzzy", lmi_form="petersen", optimise_decay_rate=False),
        False,
    ),
    (
        "fuzzy P(h), paper's vertex form, mirror-reduced (16 LMIs of size 18)",
        DesignOptions(design="paper", lyapunov="fuzzy", lmi_form="vertex", optimise_decay_rate=False),
        True,
    ),
    (
        "fuzzy P(h), paper's vertex form as printed (32 LMIs of size 18)",
        DesignOptions(design="paper", lyapunov="fuzzy", lmi_form="vertex", optimise_decay_rate=False),
        False,
    ),
    (
        "common P, Petersen form, mirror-reduced (2 LMIs)",
        DesignOptions(design="paper", lyapunov="common", lmi_form="petersen", optimise_decay_rate=False),
        True,
    ),
    (
        "fuzzy P(h), Petersen form, mirror-reduced, with decay-rate bisection",
        DesignOptions(design="paper", lyapunov="fuzzy", lmi_form="petersen"),
        True,
    ),
    (
        "robust design, 'h2' cost form (cost LMIs at rate 1, separate decay-rate LMIs), fault order 1",
        DesignOptions(robust_cost="h2"),
        True,
    ),
    (
        "robust H2 design with one gain set (`switching` null), filtered fault output, fault order 1, fuzzy P(h)",
        DesignOptions(switching=None),
        True,
    ),
    (
        "the product's default: the switched robust design, a fast set (the one-set design at decay rate 0.994) "
        "and a quiet set under one P(h) (two solves)",
        DesignOptions(),
        True,
    ),
    (
        "a calibrated car with the cornering drag (3 DMVT scalars: 4 x 4 x 8 vertex LMIs per gain set in numpy), "
        "the switched robust design at decay rate 0.999 as calibration chooses it",
        DesignOptions(robust_decay_rate=0.999),
        True,
        CALIBRATED_CAR,
    ),
]
#: The row the sub-second target is about: Theorem 2 with a fuzzy Lyapunov matrix at fault order 3.
TARGET_ROW = 0
TARGET_S = 1.0


def run(out_dir: Path, repeats: int = REPEATS) -> Path:
    rows = []
    for label, options, use_symmetry, *vehicle in CASES:
        params, bounds = vehicle[0] if vehicle else (None, None)
        walls, solver, compile_, decay = [], [], [], []
        for _ in range(repeats):
            started = time.perf_counter()
            gains = synthesize(params, bounds, options, use_symmetry=use_symmetry)
            walls.append(time.perf_counter() - started)
            t = gains.certificate.timings_s
            solver.append(t.get("solver_s", float("nan")))
            compile_.append(t.get("compile_s", float("nan")))
            decay.append(gains.certificate.decay_rate)
        rows.append((label, walls, solver, compile_, decay, gains.certificate))
        print(f"  {label}: median {statistics.median(walls):.2f} s", flush=True)
    lines = [
        report_header("Observer synthesis time", "synthesis"),
        "The paper's Table 1 and bounds; fault order 3 (augmented state n = 9) unless the row says otherwise; "
        f"median of {repeats} runs each.\n",
        "| design | wall time median [s] | min [s] | max [s] | Clarabel solve median [s] | cvxpy compile median [s] "
        "| iterations | Clarabel s per iteration | certified decay rate | LMIs solved / verified in numpy |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for label, walls, solver, compile_, decay, cert in rows:
        per_iter = statistics.median(solver) / cert.solver_iterations if cert.solver_iterations else float("nan")
        lines.append(
            f"| {label} | {statistics.median(walls):.2f} | {min(walls):.2f} | {max(walls):.2f} "
            f"| {statistics.median(solver):.2f} | {statistics.median(compile_):.2f} | {cert.solver_iterations} "
            f"| {per_iter:.3f} | {statistics.median(decay):.4f} | {cert.n_lmis_solved} / {cert.n_lmis_verified} |"
        )
    label, walls = rows[TARGET_ROW][0], rows[TARGET_ROW][1]
    wall = statistics.median(walls)
    verdict = f"**Against the target (this run).** {label}: median {wall:.2f} s, " + (
        f"under the {TARGET_S:.0f} s target." if wall < TARGET_S else f"above the {TARGET_S:.0f} s target."
    )
    default = rows[-1]  # the last case
    verdict += (
        f" The product's default design, which the service runs on every resynthesis, takes "
        f"{statistics.median(default[1]):.2f} s.\n"
    )
    path = out_dir / "synthesis.md"
    path.write_text("\n".join(lines) + "\n\n" + verdict + "\n" + ANALYSIS)
    return path


ANALYSIS = """## Reading

Wall time covers the existence check, building and compiling the cvxpy problem, the
Clarabel solve (one thread) and the numpy verification of all 32 vertex LMIs of the
paper's form plus the spectral radius on 15,129 grid points (about 0.1 s), whatever form
was solved.

**What brought it from the out-of-the-box 6-8 s to under a second.** Two exact
reformulations, each lossless, each re-checked by the same numpy certificate:

1. *Petersen's lemma.* The paper's form has, for every rule pair (i, j), two LMIs, one per
   DMVT vertex rho = -3 and rho = +3. They differ by the rank-one term Psi G_bar rho_row,
   affine in the scalar rho. Petersen's lemma, lossless for one scalar uncertainty, replaces
   each pair with one LMI of size 2n + 1 and a multiplier lambda_ij: 16 LMIs instead of 32.
2. *The vehicle's mirror symmetry* (synth/symmetry.py). Negating (v_y, r, delta_f) maps the
   rule at r_min onto the rule at r_max, and leaves C and the DMVT term unchanged. The LMIs'
   feasible set is convex and mirror-invariant, so the average of a solution and its mirror
   image is a solution: nothing is lost by searching only mirror-invariant points. There, LMI
   (i, j) and LMI (sigma i, sigma j) are the same condition, and R splits into an even and an
   odd block. This halves the LMIs again (8) and the free entries of R and P. It applies when
   the yaw-rate bounds are symmetric (r_min = -r_max), as in the paper. Asymmetric bounds are
   detected and solved in full; a test checks both paths.

The certified decay rate is the same with and without the reduction (compare the rows).
Clarabel's time per iteration falls faster than the LMI count. Its sparse LDL^T factor fills
in across LMIs that share the decision variables, so its cost grows faster than linearly with
the number and size of the blocks.

**What limits it now.** For the mirror-reduced fuzzy design, cvxpy's compile step and the
numpy verification are each of the same order as the solve itself. The remaining levers are
building Clarabel's matrices directly instead of through cvxpy, and warm starts on
resynthesis, which Clarabel does not offer. Earlier attempts on the solve itself, before the
reduction:

* looser tolerances: 1 iteration saved, no per-iteration gain;
* two threads: slower;
* disabling chordal decomposition: slower;
* passing Clarabel the dual problem: no faster per iteration, and it ends in NumericalError;
* Clarabel's linear-algebra backends: the default already picks faer; qdldl is no faster;
* CVXOPT through cvxpy: fails on this problem;
* SDPA through sdpa-python: about 1.0 s on the 16-LMI form, with a feasible point that
  certified a slower decay (0.975 against 0.950). Not adopted.
"""
