"""`agv-fe simulate`: run a scenario through the plant and an estimator; write CSV, figures and RMSE."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from agv_fe.common import (
    CommandError,
    add_design_arguments,
    add_estimator_argument,
    estimator_factory,
    fail,
    gains_from_args,
)


def register(sub: Any) -> None:
    parser = sub.add_parser(
        "simulate",
        help="simulate a scenario and estimate its faults",
        description="Simulate the nonlinear plant (RK4 at 1 ms) on a scenario, run the observer on its "
        "100 Hz measurements, write a CSV, PNG figures like the paper's Figs. 3-6, and print RMSE per signal.",
    )
    parser.add_argument(
        "--scenario", required=True, help="built-in name (paper-1, paper-2, ...) or a .json/.yaml scenario file"
    )
    parser.add_argument(
        "--noise",
        default=None,
        help="sensor noise: 'none', 'realistic' (sigma v_x 0.05 m/s, r 0.005 rad/s) or 'SIGMA_VX,SIGMA_R'; "
        "default: the scenario's own",
    )
    parser.add_argument("--seed", type=int, default=None, help="noise seed (default: the scenario's)")
    parser.add_argument("--gains", metavar="gains.json", help="use stored gains instead of synthesising")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    add_design_arguments(parser, default_design="robust")
    add_estimator_argument(parser)
    parser.set_defaults(handler=run)


def parse_noise(text: str | None) -> Any:
    """The --noise flag as a SensorNoise, or None for the scenario's own."""
    from edge_client.scenario import REALISTIC_NOISE, SensorNoise

    if text is None:
        return None
    if text == "none":
        return SensorNoise()
    if text == "realistic":
        return REALISTIC_NOISE
    try:
        sigma_vx, sigma_r = (float(v) for v in text.split(","))
    except ValueError:
        raise CommandError(f"--noise: expected 'none', 'realistic' or 'SIGMA_VX,SIGMA_R', got {text!r}") from None
    if not (np.isfinite(sigma_vx) and np.isfinite(sigma_r)) or sigma_vx < 0 or sigma_r < 0:
        raise CommandError(f"--noise: sigmas must be finite and >= 0, got {text!r}")
    return SensorNoise(vx_sigma_mps=sigma_vx, r_sigma_radps=sigma_r)


def resolve_scenario(name: str, noise: Any, seed: int | None) -> Any:
    """A built-in scenario or a file, with the --noise and --seed overrides applied."""
    from edge_client.library import BUILTIN_SCENARIOS, builtin_scenario
    from edge_client.scenario import ScenarioError, load_scenario

    if name in BUILTIN_SCENARIOS:
        scenario = builtin_scenario(name)
    elif Path(name).suffix.lower() in (".json", ".yaml", ".yml"):
        try:
            scenario = load_scenario(name)
        except ScenarioError as exc:
            raise CommandError(str(exc)) from exc
    else:
        raise CommandError(
            f"--scenario: unknown scenario {name!r}; built-in: {', '.join(BUILTIN_SCENARIOS)}, or a .json/.yaml file"
        )
    updates: dict[str, Any] = {}
    if noise is not None:
        updates["noise"] = noise
    if seed is not None:
        updates["seed"] = seed
    return scenario.model_copy(update=updates) if updates else scenario


def run(args: argparse.Namespace) -> int:
    from edge_client.plots import plot_faults, plot_states
    from edge_client.simulation import run as simulate

    try:
        scenario = resolve_scenario(args.scenario, parse_noise(args.noise), args.seed)
        gains = gains_from_args(args)
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
    except CommandError as exc:
        return fail(exc)
    except OSError as exc:
        return fail(CommandError(f"{args.out}: cannot create: {exc.strerror}"))
    result = simulate([scenario], estimator_factory(args, gains))
    write_csv(out / "simulation.csv", result)
    who = "EKF" if args.estimator == "ekf" else f"{gains.options.design} observer"
    title = f"{scenario.name}: {who}"
    plot_states(result, out / "states.png", title=title)
    plot_faults(result, out / "faults.png", title=title)
    rmse_all = {k: float(v[0]) for k, v in result.rmse().items()}
    rmse_late = {k: float(v[0]) for k, v in result.rmse(after_s=3.0).items()}
    summary = {
        "scenario": scenario.name,
        "estimator": args.estimator,
        "design": gains.options.design,
        "gain_version": gains.version,
        "noise": scenario.noise.model_dump(),
        "payload_kg": scenario.payload_kg,
        "road_grade": None if scenario.road_grade is None else scenario.road_grade.model_dump(),
        "rmse": rmse_all,
        "rmse_after_3s": rmse_late,
        "fault_amplitude": dict(zip(("T_f", "delta_f"), result.fault_amplitude()[0].tolist(), strict=True)),
        "in_domain_fraction": float(result.in_domain.mean()),
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"{scenario.name}: {len(result.t)} samples, {who} (gains version {gains.version})")
    print(f"{'signal':<10}{'RMSE':>14}{'RMSE t>=3s':>14}  unit")
    units = {"v_x": "m/s", "v_y": "m/s", "r": "rad/s", "T_f": "N m", "delta_f": "rad"}
    for name, unit in units.items():
        print(f"{name:<10}{rmse_all[name]:>14.5g}{rmse_late[name]:>14.5g}  {unit}")
    print(f"premise in the design domain {summary['in_domain_fraction']:.1%} of the time")
    print(f"written {out / 'simulation.csv'}, {out / 'states.png'}, {out / 'faults.png'}, {out / 'summary.json'}")
    return 0


def write_csv(path: Path, result: Any) -> None:
    """Every signal of vehicle 0, one row per sample; the first five columns are a replayable recording (with
    the last, ``grade``, on a road with one)."""
    columns = {
        "t": result.t,
        "vx": result.y[:, 0, 0],
        "r": result.y[:, 0, 1],
        "torque": result.u[:, 0, 0],
        "steer": result.u[:, 0, 1],
        "vx_true": result.x[:, 0, 0],
        "vy_true": result.x[:, 0, 1],
        "r_true": result.x[:, 0, 2],
        "torque_fault": result.f[:, 0, 0],
        "steer_fault": result.f[:, 0, 1],
        "wind": result.wind[:, 0],
        "X": result.pose[:, 0, 0],
        "Y": result.pose[:, 0, 1],
        "psi": result.pose[:, 0, 2],
        "vx_hat": result.x_hat[:, 0, 0],
        "vy_hat": result.x_hat[:, 0, 1],
        "r_hat": result.x_hat[:, 0, 2],
        "torque_fault_hat": result.f_hat[:, 0, 0],
        "steer_fault_hat": result.f_hat[:, 0, 1],
        "in_domain": result.in_domain[:, 0].astype(float),
    }
    if result.grade is not None:  # the road grade the vehicle reported: replay and calibrate take it
        columns["grade"] = result.grade[:, 0]
    data = np.column_stack(list(columns.values()))
    np.savetxt(path, data, delimiter=",", header=",".join(columns), comments="", fmt="%.17g")
