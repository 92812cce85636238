"""`agv-fe demo`: the first thing a new user runs."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any


def register(sub: Any) -> None:
    parser = sub.add_parser(
        "demo",
        help="run the demonstration",
        description="Synthesise the observer, simulate the paper's two scenarios and write figures.",
    )
    parser.add_argument("--out", default="out/demo", metavar="DIR", help="output folder (default: out/demo)")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from agv_fe.commands.synth import format_summary
    from edge_client.library import builtin_scenario
    from edge_client.plots import plot_faults, plot_states
    from edge_client.simulation import observer_factory
    from edge_client.simulation import run as simulate
    from synth.design import synthesize

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print("1. synthesising the observer (Theorem 2, no exact decoupling) ...", flush=True)
    gains = synthesize()
    print(format_summary(gains.certificate))
    for k, name in enumerate(("paper-1", "paper-2"), start=2):
        print(f"{k}. simulating {name} ...", flush=True)
        result = simulate([builtin_scenario(name)], observer_factory(gains))
        rmse = result.rmse(after_s=3.0)
        amp = result.fault_amplitude()[0]
        plot_states(result, out / f"{name}-states.png", title=f"{name}: states")
        plot_faults(result, out / f"{name}-faults.png", title=f"{name}: faults")
        print(
            f"   torque fault RMSE (t >= 3 s) {rmse['T_f'][0]:.3g} N m of {amp[0]:.3g} N m; "
            f"steering fault RMSE {rmse['delta_f'][0]:.3g} rad of {amp[1]:.3g} rad"
        )
    print(f"figures written to {out}/")
    return 0
