"""Helpers shared by the subcommands: profiles from files, designs from flags, readable errors."""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ValidationError

from service.profiles import PROFILE_NAME_RULE, AlarmThresholds, InputLimits, valid_profile_name
from synth.options import DesignOptions, EffectivenessOptions
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


#: The sections of a profile file: those of the body of ``PUT /profiles/{name}`` (service.profiles.ProfileSpec).
PROFILE_SECTIONS = ("params", "bounds", "design", "alarms", "limits", "effectiveness")
#: Plain fields a profile file may carry beside its sections.
PROFILE_FIELDS = ("name", "description")
_DESCRIPTION_MAX_CHARS = 500


@dataclass(frozen=True)
class VehicleProfileFile:
    """What --params gives: one vehicle profile, the body of ``PUT /profiles/{name}`` (ProfileSpec) as a file.

    params, bounds : the vehicle (Table 1) and its operating box (eq. 13); options : the design options as
    written (flags override them, :func:`design_options`); alarms : the alarm thresholds the service (and
    `agv-fe replay`) raise levels with; limits : the service's plausibility limits of a measurement;
    effectiveness : the loss-of-effectiveness stage's options (synth.effectiveness), run by replay when enabled;
    source : where it came from, for messages.
    """

    params: VehicleParams
    bounds: OperatingBounds
    options: dict[str, Any]
    alarms: AlarmThresholds = field(default_factory=AlarmThresholds)
    limits: InputLimits = field(default_factory=InputLimits)
    effectiveness: EffectivenessOptions = field(default_factory=EffectivenessOptions)
    name: str = ""
    description: str = ""
    source: str = "the defaults"


#: Profiles known by name to --params: ``paper`` is the paper's vehicle (Table 1), its operating box (eq. 13),
#: the default design options and the default alarm thresholds and input limits.
BUILTIN_PROFILES: dict[str, VehicleProfileFile] = {
    "paper": VehicleProfileFile(
        VehicleParams(),
        OperatingBounds(),
        {},
        name="paper",
        description="the paper's vehicle (Table 1) and operating box (eq. 13), default design and alarms",
        source="the built-in profile 'paper'",
    ),
}


def validation_message(exc: ValidationError, prefix: str) -> str:
    """One line per problem, naming the field path and the value."""
    lines = []
    for err in exc.errors():
        # a model-level rule (such as warn below fault) has no field of its own: name the model's prefix
        where = ".".join(str(p) for p in err["loc"]) or prefix.rstrip(".") or "(root)"
        value = err.get("input")
        shown = "" if isinstance(value, dict | list) else f" (got {value!r})"
        lines.append(f"  {prefix if err['loc'] else ''}{where}: {err['msg']}{shown}")
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
    """The profile --params names: None for the defaults, a name of :data:`BUILTIN_PROFILES`, or a JSON file.

    A file holds the body of ``PUT /profiles/{name}``: any of the sections params, bounds, design, alarms and
    limits, and optionally name and description; or the vehicle parameters alone. A missing section takes
    its defaults. Errors name the file and the field path.
    """
    if path is None:
        return VehicleProfileFile(VehicleParams(), OperatingBounds(), {})
    if str(path) in BUILTIN_PROFILES:
        return BUILTIN_PROFILES[str(path)]
    data = load_json(path)
    if not isinstance(data, dict):
        raise CommandError(f"{path}: expected a JSON object")
    if not set(PROFILE_SECTIONS) & data.keys():
        params = validate(VehicleParams, data, "params.")
        return VehicleProfileFile(params, OperatingBounds(), {}, source=str(path))
    unknown = set(data) - set(PROFILE_SECTIONS) - set(PROFILE_FIELDS)
    if unknown:
        raise CommandError(
            f"{path}: unknown section(s) {', '.join(sorted(unknown))}; allowed: {', '.join(PROFILE_SECTIONS)} "
            f"(and {', '.join(PROFILE_FIELDS)})"
        )
    params = validate(VehicleParams, data.get("params", {}), "params.")
    bounds = validate(OperatingBounds, data.get("bounds", {}), "bounds.")
    options = data.get("design", {})
    if not isinstance(options, dict):
        raise CommandError(f"{path}: 'design' must be an object")
    alarms = validate(AlarmThresholds, data.get("alarms", {}), "alarms.")
    limits = validate(InputLimits, data.get("limits", {}), "limits.")
    effectiveness = validate(EffectivenessOptions, data.get("effectiveness", {}), "effectiveness.")
    name, description = data.get("name", ""), data.get("description", "")
    if not isinstance(name, str) or (name and not valid_profile_name(name)):
        raise CommandError(f"{path}: name: expected {PROFILE_NAME_RULE} (got {name!r})")
    if not isinstance(description, str) or len(description) > _DESCRIPTION_MAX_CHARS:
        raise CommandError(f"{path}: description: expected text of at most {_DESCRIPTION_MAX_CHARS} characters")
    return VehicleProfileFile(
        params, bounds, options, alarms, limits, effectiveness, name, description, source=str(path)
    )


def add_design_arguments(parser: argparse.ArgumentParser, *, default_design: str) -> None:
    parser.add_argument(
        "--params",
        metavar="FILE.json",
        help="vehicle profile: a JSON file with the sections params, bounds, design, alarms and limits (the body of "
        "PUT /profiles/{name}; a missing section takes its defaults), or the name of a built-in profile: "
        f"{', '.join(BUILTIN_PROFILES)} (default: the paper's Table 1 and eq. 13, the default alarms)",
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


def synthesize_or_fail(
    args: argparse.Namespace, *, quiet: bool = False, profile: VehicleProfileFile | None = None
) -> Any:
    """Run the design selected by the flags (and ``profile``, read from --params if None); a design that cannot
    be certified becomes a CommandError."""
    from synth.design import synthesize
    from synth.errors import BadParameters, Infeasible, SynthesisError

    if profile is None:
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
        raise CommandError(
            f"the '{options.design}' design failed: {exc}\n\n{design_hints(profile, options)}", EXIT_NO_DESIGN
        ) from exc


def design_hints(profile: VehicleProfileFile, options: Any) -> str:
    """What to change when no certified design was found: the levers in the order they usually help."""
    b = profile.bounds
    hints = [
        f"the operating box is what the design must hold over: v_x {b.vx_min_mps:g} to {b.vx_max_mps:g} m/s "
        f"(a ratio of {b.vx_max_mps / b.vx_min_mps:.3g}), |r| up to {max(-b.r_min_radps, b.r_max_radps):g} rad/s, "
        f"v_y {b.vy_min_mps:g} to {b.vy_max_mps:g} m/s; narrow it to the vehicle's real range (bounds.vx_min_mps "
        "up, bounds.r_max_radps down), or split a wide speed range over two profiles",
    ]
    if options.design == "robust":
        hints.append(
            f"a slower certified decay: design.robust_decay_rate closer to 1 (now {options.robust_decay_rate:g})"
        )
    hints.append("check the vehicle parameters (`agv-fe calibrate` identifies them from healthy recordings)")
    return "What to try:\n" + "\n".join(f"  - {h}" for h in hints)


def gains_from_args(args: argparse.Namespace, profile: VehicleProfileFile | None = None) -> Any:
    """--gains FILE if given (hash and certificate re-checked), else a fresh synthesis for ``profile``
    (read from --params if None)."""
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
    return synthesize_or_fail(args, profile=profile)


def add_bag_argument(parser: argparse.ArgumentParser) -> None:
    """``--map``: the input is a ROS 2 bag read through a mapping file (edge_client/ros2.py), not a CSV."""
    parser.add_argument(
        "--map",
        metavar="MAPPING.yaml",
        help="read the input as a ROS 2 bag (rosbag2 directory, .db3 or .mcap) whose topics this mapping names "
        "(topic, message type, field, scale and offset per signal: docs/integration.md); needs the 'ros2' extra",
    )


def read_input(path: str, mapping_path: str | None, sample_period_s: float = 0.01) -> Any:
    """The recording at ``path``: a CSV, or with ``mapping_path`` a ROS 2 bag on the grid of its mapping (whose
    sample period must be ``sample_period_s``). A :class:`CommandError` says what is wrong."""
    from edge_client.recording import RecordingError, read_recording

    try:
        if mapping_path is None:
            return read_recording(path, sample_period_s)
        try:
            from edge_client.ros2 import load_ros_mapping, read_bag
        except ImportError as exc:  # rosbags missing
            raise CommandError(f"--map needs rosbags: pip install 'agv-fault-estimator[ros2]' ({exc})") from exc
        mapping = load_ros_mapping(mapping_path)
        if abs(mapping.sample_period_s - sample_period_s) > 1e-12:
            raise CommandError(
                f"{mapping_path}: sample_period_s {mapping.sample_period_s:g} s, the profile's is {sample_period_s:g} s"
            )
        recording, stats = read_bag(path, mapping)
        print(f"{path}: {stats.describe()}; {len(recording)} samples on the {sample_period_s * 1000:g} ms grid")
        return recording
    except RecordingError as exc:
        raise CommandError(str(exc)) from exc
