"""Helpers shared by the subcommands: profiles from files, designs from flags, readable errors."""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ValidationError

from synth.options import DesignOptions
from synth.params import OperatingBounds, VehicleParams

#: Exit codes: bad input (files, flags, values), and designs that cannot be certified.
EXIT_BAD_INPUT = 2
EXIT_NO_DESIGN = 3

DESIGN_CHOICES = ("paper", "paper-decoupled", "robust")


class CommandError(Exception):
    """A user-facing error: printed without a traceback, with an exit code."""

    def __init__(self, message: str, exit_code: int = EXIT_BAD_INPUT) -> None:
        super().__init__(message)
        self.exit_code = exit_code


@dataclass(frozen=True)
class VehicleProfileFile:
    """What a --params file holds: vehicle parameters, operating bounds and (optionally) design options."""

    params: VehicleParams
    bounds: OperatingBounds
    options: dict[str, Any]


def validation_message(exc: ValidationError, prefix: str) -> str:
    """One line per problem, naming the field path and the value."""
    lines = []
    for err in exc.errors():
        where = ".".join(str(p) for p in err["loc"]) or "(root)"
        value = err.get("input")
        shown = "" if isinstance(value, dict | list) else f" (got {value!r})"
        lines.append(f"  {prefix}{where}: {err['msg']}{shown}")
    return "\n".join(lines)


def validate(model: type[BaseModel], data: Any, prefix: str) -> Any:
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise CommandError(f"invalid {model.__name__}:\n{validation_message(exc, prefix)}") from exc


def load_json(path: str | Path) -> Any:
    try:
        return json.loads(Path(path).read_text())
    except OSError as exc:
        raise CommandError(f"{path}: cannot read: {exc.strerror}") from exc
    except json.JSONDecodeError as exc:
        raise CommandError(f"{path}: not valid JSON: {exc.msg} at line {exc.lineno}, column {exc.colno}") from exc


def load_profile_file(path: str | Path | None) -> VehicleProfileFile:
    """Read a --params file: {"params": {...}, "bounds": {...}, "design": {...}}, or the params alone."""
    if path is None:
        return VehicleProfileFile(VehicleParams(), OperatingBounds(), {})
    data = load_json(path)
    if not isinstance(data, dict):
        raise CommandError(f"{path}: expected a JSON object")
    sections = {"params", "bounds", "design"}
    if sections & data.keys():
        unknown = set(data) - sections - {"name", "description"}
        if unknown:
            raise CommandError(
                f"{path}: unknown section(s) {', '.join(sorted(unknown))}; allowed: {', '.join(sorted(sections))}"
            )
        params = validate(VehicleParams, data.get("params", {}), "params.")
        bounds = validate(OperatingBounds, data.get("bounds", {}), "bounds.")
        options = data.get("design", {})
        if not isinstance(options, dict):
            raise CommandError(f"{path}: 'design' must be an object")
        return VehicleProfileFile(params, bounds, options)
    return VehicleProfileFile(validate(VehicleParams, data, "params."), OperatingBounds(), {})


def add_design_arguments(parser: argparse.ArgumentParser, *, default_design: str) -> None:
    parser.add_argument(
        "--params", metavar="FILE.json", help="vehicle parameters and bounds (default: the paper's Table 1 and eq. 13)"
    )
    parser.add_argument(
        "--design", choices=DESIGN_CHOICES, default=None, help=f"observer design (default: {default_design})"
    )
    parser.add_argument(
        "--fault-order", type=int, choices=(1, 2, 3), default=None, help="order of the fault model (the paper's is 3)"
    )
    parser.add_argument(
        "--lyapunov", choices=("fuzzy", "common"), default=None, help="fuzzy P(h) (default) or one common P"
    )
    parser.add_argument(
        "--lmi-form",
        choices=("petersen", "vertex"),
        default=None,
        help="LMI form solved (both are verified as vertex LMIs)",
    )
    parser.add_argument(
        "--no-decay-rate", action="store_true", help="skip the decay-rate bisection (faster, stability only)"
    )
    parser.add_argument(
        "--robust-cost",
        choices=("joint", "h2"),
        default=None,
        help="robust design: 'joint' (default) certifies cost and decay rate with the same LMIs and tracks faults "
        "faster; 'h2' bounds the H2 cost alone (decay rate certified separately): less steady-state noise",
    )
    parser.add_argument(
        "--switching",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="robust design: a quiet gain set beside the fast one, under the same Lyapunov function, with the "
        "fast set at a start and after large innovations (the default; the rule's settings go in a profile's "
        "'switching' options). --no-switching: one gain set, certified decay rate 0.995",
    )
    parser.set_defaults(default_design=default_design)


def design_options(args: argparse.Namespace, profile: VehicleProfileFile) -> DesignOptions:
    """Options from the profile file, overridden by explicit flags."""
    data = dict(profile.options)
    data.setdefault("design", args.default_design)
    overrides = {
        "design": args.design,
        "fault_order": args.fault_order,
        "lyapunov": args.lyapunov,
        "lmi_form": args.lmi_form,
        "robust_cost": args.robust_cost,
    }
    data.update({k: v for k, v in overrides.items() if v is not None})
    if args.no_decay_rate:
        data["optimise_decay_rate"] = False
    switching = getattr(args, "switching", None)
    if switching and data.get("switching") is None:
        data["switching"] = {}
    elif switching is False:
        data["switching"] = None
    options: DesignOptions = validate(DesignOptions, data, "design.")
    return options


def add_estimator_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--estimator",
        choices=("observer", "ekf"),
        default="observer",
        help="the certified fuzzy observer (default) or the augmented-state EKF baseline, tuned from the same "
        "design options (noise model, fault order)",
    )


def estimator_factory(args: argparse.Namespace, gains: Any) -> Any:
    """The estimator selected by --estimator, for these gains (the EKF takes their params and tuning)."""
    from edge_client.simulation import ekf_factory, observer_factory

    return ekf_factory(gains) if args.estimator == "ekf" else observer_factory(gains)


def fail(exc: CommandError) -> int:
    print(f"agv-fe: error: {exc}", file=sys.stderr)
    return exc.exit_code


def synthesize_or_fail(args: argparse.Namespace, *, quiet: bool = False) -> Any:
    """Run the design selected by the flags; a design that cannot be certified becomes a CommandError."""
    from synth.design import synthesize
    from synth.errors import BadParameters, Infeasible, SynthesisError

    profile = load_profile_file(getattr(args, "params", None))
    options = design_options(args, profile)
    if not quiet:
        print(f"synthesising the '{options.design}' observer (fault order {options.fault_order}) ...", file=sys.stderr)
    try:
        return synthesize(profile.params, profile.bounds, options)
    except Infeasible as exc:
        raise CommandError(f"the '{options.design}' design is impossible.\n\n{exc.reason}", EXIT_NO_DESIGN) from exc
    except BadParameters as exc:
        raise CommandError(str(exc)) from exc
    except SynthesisError as exc:
        raise CommandError(f"the '{options.design}' design failed: {exc}", EXIT_NO_DESIGN) from exc


def gains_from_args(args: argparse.Namespace) -> Any:
    """--gains FILE if given (hash and certificate re-checked), else a fresh synthesis."""
    from synth.errors import SynthesisError
    from synth.gains import ObserverGains

    if getattr(args, "gains", None):
        data = load_json(args.gains)
        if not isinstance(data, dict):
            raise CommandError(f"{args.gains}: expected a JSON object")
        try:
            return ObserverGains.from_dict(data)
        except (SynthesisError, KeyError, TypeError, ValueError) as exc:
            raise CommandError(f"{args.gains}: unusable gains: {exc}") from exc
    return synthesize_or_fail(args)
