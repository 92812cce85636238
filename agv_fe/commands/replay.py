"""`agv-fe replay`: run the observer over a recorded 100 Hz stream."""

from __future__ import annotations

import argparse
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
        "replay",
        help="estimate faults from a recorded CSV stream",
        description="Run the observer over a recorded 100 Hz stream with columns t, vx, r, torque, steer "
        "(others ignored) and write t, vx_hat, vy_hat, r_hat, torque_fault_hat, steer_fault_hat, in_domain.",
    )
    parser.add_argument("input", metavar="INPUT.csv", help="recorded stream")
    parser.add_argument("--out", required=True, metavar="OUTPUT.csv", help="estimates")
    parser.add_argument("--gains", metavar="gains.json", help="use stored gains instead of synthesising")
    parser.add_argument(
        "--initial-state",
        metavar="VX,VY,R",
        help="observer initial [v_x, v_y, r] (default: measured v_x, r and v_y = 0)",
    )
    add_design_arguments(parser, default_design="robust")
    add_estimator_argument(parser)
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from edge_client.recording import RecordingError, read_recording, write_estimates

    try:
        x0 = _initial_state(args.initial_state)
        gains = gains_from_args(args)
        try:
            recording = read_recording(args.input, gains.params.sample_period_s)
        except RecordingError as exc:
            raise CommandError(str(exc)) from exc
    except CommandError as exc:
        return fail(exc)
    observer = estimator_factory(args, gains)(recording.y[:1], x0)
    n = len(recording)
    x_hat = np.zeros((n, 3))
    f_hat = np.zeros((n, 2))
    in_domain = np.zeros(n, dtype=bool)
    for k in range(n):
        step = observer.step(recording.y[k], recording.u[k])
        x_hat[k], f_hat[k], in_domain[k] = step.state[0], step.faults[0], step.in_domain[0]
    try:
        write_estimates(args.out, recording.t, x_hat, f_hat, in_domain)
    except OSError as exc:
        return fail(CommandError(f"{args.out}: cannot write: {exc.strerror}"))
    print(
        f"replayed {n} samples ({recording.t[-1] - recording.t[0]:.2f} s) with the "
        f"{'EKF' if args.estimator == 'ekf' else repr(gains.options.design) + ' observer'} "
        f"(gains version {gains.version}); premise in domain {in_domain.mean():.1%} of the time"
    )
    print(f"written {Path(args.out)}")
    return 0


def _initial_state(text: str | None) -> Any:
    if text is None:
        return None
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise CommandError(f"--initial-state: expected three numbers VX,VY,R, got {text!r}") from None
    if len(values) != 3 or not np.all(np.isfinite(values)):
        raise CommandError(f"--initial-state: expected three finite numbers VX,VY,R, got {text!r}")
    return np.array([values])
