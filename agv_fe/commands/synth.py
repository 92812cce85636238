"""`agv-fe synth`: design certified observer gains and write them with their certificate."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from agv_fe.common import CommandError, add_design_arguments, fail, synthesize_or_fail


def register(sub: Any) -> None:
    parser = sub.add_parser(
        "synth",
        help="design certified observer gains (LMIs of Theorem 2)",
        description="Solve the observer LMIs, verify the result in numpy and write gains + certificate as JSON.",
    )
    add_design_arguments(parser, default_design="robust")
    parser.add_argument("--out", required=True, metavar="gains.json", help="where to write gains and certificate")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    try:
        gains = synthesize_or_fail(args)
    except CommandError as exc:
        return fail(exc)
    out = Path(args.out)
    try:
        out.write_text(json.dumps(gains.to_dict(), indent=1))
    except OSError as exc:
        return fail(CommandError(f"{out}: cannot write: {exc.strerror}"))
    print(format_summary(gains.certificate))
    print(f"written       {out}")
    return 0


def format_summary(c: Any) -> str:
    """The certificate's headline figures as aligned lines."""
    timings = c.timings_s
    parts = [f"solve {timings.get('solve_s', 0):.2f} s"]
    if "bisection_s" in timings:
        parts.append(f"decay-rate bisection {timings['bisection_s']:.2f} s")
    where = c.spectral_radius_at
    speed, yaw_rate = where.get("speed_mps", float("nan")), where.get("yaw_rate_radps", float("nan"))
    worst = f"v_x = {speed:.1f} m/s, r = {yaw_rate:.2f} rad/s"
    switched = "fast_set_h2_cost_bound" in c.performance
    sets = ", switched: fast and quiet gain sets, one Lyapunov function" if switched else ""
    lines = [
        f"design        {c.design}, fault order {c.fault_order}, {c.lyapunov} Lyapunov matrix{sets}",
        f"LMIs          {c.n_lmis_solved} solved ({c.lmi_form} form); "
        f"{c.n_lmis_verified} vertex LMIs verified in numpy, min eigenvalue {c.lmi_min_eigenvalue:.3g}",
        f"decay rate    {c.decay_rate:.4f} certified (error shrinks at least x{c.decay_rate:.4f} per sample)",
        f"verification  passed: max spectral radius {c.spectral_radius_max:.4f} over {c.grid_points} grid points "
        f"(worst at {worst})",
        f"solver        {c.solver} ({c.solver_version}), status {c.solver_status}, {c.solves} solve(s)",
        f"time          {timings.get('total_s', 0):.2f} s ({', '.join(parts)})",
        f"version       {c.content_hash[:12]}",
    ]
    for key, value in c.performance.items():
        lines.append(f"{key:<13} {value:.6g}")
    return "\n".join(lines)
