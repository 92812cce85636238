"""Synthesis time of the observer LMIs: fuzzy-Lyapunov (32 vertex LMIs) and common-P designs."""

from __future__ import annotations

import statistics
import time
from pathlib import Path

from agv_fe.benchmarks import report_header
from synth.design import synthesize
from synth.options import DesignOptions

REPEATS = 5

CASES: list[tuple[str, DesignOptions]] = [
    (
        "fuzzy P(h), Petersen form (16 LMIs of size 19)",
        DesignOptions(design="paper", lyapunov="fuzzy", lmi_form="petersen", optimise_decay_rate=False),
    ),
    (
        "fuzzy P(h), paper's vertex form (32 LMIs of size 18)",
        DesignOptions(design="paper", lyapunov="fuzzy", lmi_form="vertex", optimise_decay_rate=False),
    ),
    (
        "common P, Petersen form (4 LMIs)",
        DesignOptions(design="paper", lyapunov="common", lmi_form="petersen", optimise_decay_rate=False),
    ),
    (
        "common P, vertex form (8 LMIs)",
        DesignOptions(design="paper", lyapunov="common", lmi_form="vertex", optimise_decay_rate=False),
    ),
    (
        "fuzzy P(h), Petersen form, with decay-rate bisection",
        DesignOptions(design="paper", lyapunov="fuzzy", lmi_form="petersen"),
    ),
    (
        "the product's default: robust H2 design, fault order 1, fuzzy P(h)",
        DesignOptions(),
    ),
]
#: The row the sub-second target is about: Theorem 2 with a fuzzy Lyapunov matrix at fault order 3.
TARGET_ROW = 0
TARGET_S = 1.0


def run(out_dir: Path, repeats: int = REPEATS) -> Path:
    rows = []
    for label, options in CASES:
        walls, solver, compile_, decay = [], [], [], []
        for _ in range(repeats):
            started = time.perf_counter()
            gains = synthesize(options=options)
            walls.append(time.perf_counter() - started)
            t = gains.certificate.timings_s
            solver.append(t.get("solver_s", float("nan")))
            compile_.append(t.get("compile_s", float("nan")))
            decay.append(gains.certificate.decay_rate)
        rows.append((label, walls, solver, compile_, decay, gains.certificate))
        print(f"  {label}: median {statistics.median(walls):.2f} s", flush=True)
    lines = [
        report_header("Observer synthesis time", "make bench (agv-fe bench --only synthesis)"),
        "The paper's Table 1 and bounds; fault order 3 (augmented state n = 9) unless the row says otherwise; "
        f"median of {repeats} runs each.\n",
        "| design | wall time median [s] | min [s] | max [s] | Clarabel solve median [s] | cvxpy compile median [s] "
        "| iterations | Clarabel s per iteration | certified decay rate |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for label, walls, solver, compile_, decay, cert in rows:
        per_iter = statistics.median(solver) / cert.solver_iterations if cert.solver_iterations else float("nan")
        lines.append(
            f"| {label} | {statistics.median(walls):.2f} | {min(walls):.2f} | {max(walls):.2f} "
            f"| {statistics.median(solver):.2f} | {statistics.median(compile_):.2f} | {cert.solver_iterations} "
            f"| {per_iter:.3f} | {statistics.median(decay):.4f} |"
        )
    label, walls = rows[TARGET_ROW][0], rows[TARGET_ROW][1]
    wall = statistics.median(walls)
    verdict = f"**Against the target (this run).** {label}: median {wall:.2f} s, " + (
        f"under the {TARGET_S:.0f} s target." if wall < TARGET_S else f"above the {TARGET_S:.0f} s target."
    )
    default = rows[-1]
    verdict += (
        f" The product's default design, which the service runs on every resynthesis, takes "
        f"{statistics.median(default[1]):.2f} s.\n"
    )
    path = out_dir / "synthesis.md"
    path.write_text("\n".join(lines) + "\n\n" + verdict + "\n" + ANALYSIS)
    return path


ANALYSIS = """## Reading

Wall time covers the existence check, building and compiling the cvxpy problem, the
Clarabel solve (one thread) and the numpy verification of all vertex LMIs plus the
spectral radius on 15,129 grid points (about 0.1 s).

**What changed against the out-of-the-box 6-7 s.** The paper's form has, for every rule
pair (i, j), two LMIs, one per DMVT vertex rho = -3 and rho = +3. They differ by the
rank-one term Psi G_bar rho_row, affine in the scalar rho. Petersen's lemma, which is
lossless for one scalar uncertainty, replaces each pair with one LMI of size 2n + 1 and
a multiplier lambda_ij. That gives 16 LMIs instead of 32. The numpy check still verifies
the 32 vertex LMIs of the paper's form, so the certificate is the same.

**What limits it.** The per-iteration column. Clarabel factorises its KKT system with a
sparse LDL^T. The decision variables (P_i, R, X_i, the multipliers) appear in every LMI,
and each LMI of size 19 is a dense block of 190 entries, so the factor fills in: the cost
per iteration grows faster than linearly with the number of LMIs (compare the common-P,
fuzzy Petersen and vertex rows). We tried:

* looser tolerances: 1 iteration saved, no per-iteration gain;
* two threads: slower;
* disabling chordal decomposition: slower;
* passing Clarabel the dual problem: no faster per iteration, and it ends in NumericalError;
* Clarabel's linear-algebra backends: the default already picks faer; qdldl is no faster;
* CVXOPT through cvxpy: fails on this problem;
* SDPA (a Schur-complement interior-point method, through sdpa-python): the fuzzy Petersen
  design in about 1.0 s wall, verified, but its feasible point certified a slower decay
  (0.975 against Clarabel's 0.950); not adopted: a new native dependency for a few tenths
  of a second, with worse gains.

What would reach well under a second: a solver that exploits the LMIs' block structure
in its Schur complement and accepts a warm start from the previous design on
resynthesis. Clarabel offers neither today.
"""
