"""Recorded 100 Hz measurement streams (CSV): read with validation, write estimates.

Input columns (header required, any order, extra columns ignored):
``t`` [s], ``vx`` [m/s], ``r`` [rad/s], ``torque`` [N m] (demanded T_d),
``steer`` [rad] (demanded delta_d); optional ``grade`` [rad], the road grade
the vehicle reports (+ uphill, docs/protocol.md). Rows must be finite and
evenly spaced at the sample period (within 1 %). Errors name the file line.

Output columns of `agv-fe replay` (:data:`OUTPUT_COLUMNS`): ``t, vx_hat,
vy_hat, r_hat, torque_fault_hat, steer_fault_hat, in_domain, torque_level,
steer_level``. The two levels (``OK``, ``WARN`` or ``FAULT``) are the alarm
levels of the fault channels at each sample, as the service's alarm code
(service.fleet.alarms.FaultLevels) gives them for the same stream, with the
profile's thresholds, persistence, hysteresis and warm-up.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from synth.model import FloatArray

REQUIRED_COLUMNS = ("t", "vx", "r", "torque", "steer")
#: Columns a recording may have beside the required ones: the road grade [rad].
OPTIONAL_COLUMNS = ("grade",)
OUTPUT_COLUMNS = (
    "t",
    "vx_hat",
    "vy_hat",
    "r_hat",
    "torque_fault_hat",
    "steer_fault_hat",
    "in_domain",
    "torque_level",
    "steer_level",
)
#: Relative tolerance on the spacing of consecutive time stamps.
PERIOD_TOLERANCE = 0.01


class RecordingError(ValueError):
    """A recording that cannot be used, with the file line at fault."""


@dataclass(frozen=True)
class Recording:
    """A validated recording of K samples: t (K,), y = [vx, r] (K, 2), u = [torque, steer] (K, 2); grade (K,) the
    road grade [rad], None when the recording has no ``grade`` column."""

    t: FloatArray
    y: FloatArray
    u: FloatArray
    grade: FloatArray | None = None

    def __len__(self) -> int:
        return int(self.t.size)


def read_recording(path: str | Path, sample_period_s: float = 0.01) -> Recording:
    """Read and validate a recording; raise :class:`RecordingError` naming the line at fault."""
    path = Path(path)
    try:
        handle = path.open(newline="")
    except OSError as exc:
        raise RecordingError(f"{path}: cannot open: {exc.strerror}") from exc
    with handle:
        return parse_recording(handle, sample_period_s, source=str(path))


def parse_recording(lines: Iterable[str], sample_period_s: float = 0.01, source: str = "<input>") -> Recording:
    """Parse CSV text (header + rows) into a :class:`Recording`."""
    reader = csv.reader(lines)
    try:
        header = [h.strip() for h in next(reader)]
    except StopIteration:
        raise RecordingError(f"{source}: empty file, expected a header with {', '.join(REQUIRED_COLUMNS)}") from None
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        raise RecordingError(
            f"{source}, line 1: missing column(s) {', '.join(missing)}; the header must contain "
            f"{', '.join(REQUIRED_COLUMNS)} (found {', '.join(header) or 'nothing'})"
        )
    columns = REQUIRED_COLUMNS + tuple(c for c in OPTIONAL_COLUMNS if c in header)
    index = [header.index(c) for c in columns]
    rows: list[list[float]] = []
    for line_no, row in enumerate(reader, start=2):
        if not row or all(not cell.strip() for cell in row):
            continue
        if len(row) < len(header):
            raise RecordingError(f"{source}, line {line_no}: expected {len(header)} fields, found {len(row)}")
        values = []
        for column, k in zip(columns, index, strict=True):
            cell = row[k].strip()
            try:
                value = float(cell)
            except ValueError:
                raise RecordingError(f"{source}, line {line_no}: column {column!r} is not a number: {cell!r}") from None
            if not math.isfinite(value):
                raise RecordingError(f"{source}, line {line_no}: column {column!r} is not finite: {cell!r}")
            values.append(value)
        rows.append(values)
    if len(rows) < 2:
        raise RecordingError(f"{source}: needs at least 2 data rows, found {len(rows)}")
    data = np.array(rows)
    t = data[:, 0]
    dt = np.diff(t)
    bad = np.flatnonzero(np.abs(dt - sample_period_s) > PERIOD_TOLERANCE * sample_period_s)
    if bad.size:
        k = int(bad[0])
        raise RecordingError(
            f"{source}, line {k + 3}: time step {dt[k]:.6g} s from t = {t[k]:.6g} to t = {t[k + 1]:.6g}; "
            f"the stream must be sampled every {sample_period_s:g} s (within {PERIOD_TOLERANCE:.0%})"
        )
    grade = data[:, 5] if "grade" in columns else None
    return Recording(t=t, y=data[:, [1, 2]], u=data[:, [3, 4]], grade=grade)


def write_estimates(
    path: str | Path,
    t: FloatArray,
    x_hat: FloatArray,
    f_hat: FloatArray,
    in_domain: np.ndarray,
    torque_level: Sequence[str],
    steer_level: Sequence[str],
    extra: dict[str, FloatArray] | None = None,
) -> None:
    """Write the replay output: t (K,) [s], x_hat (K, 3), f_hat (K, 2), in_domain (K,) and the level names
    (OK, WARN, FAULT) of the torque and steering fault channels, (K,) each; ``extra`` columns (K,) after them
    (the effectiveness stage's bias and alpha)."""
    extra = extra or {}
    with Path(path).open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow([*OUTPUT_COLUMNS, *extra])
        for k in range(t.size):
            writer.writerow(
                [
                    f"{t[k]:.6f}",
                    *(f"{v:.9g}" for v in x_hat[k]),
                    *(f"{v:.9g}" for v in f_hat[k]),
                    int(in_domain[k]),
                    torque_level[k],
                    steer_level[k],
                    *(f"{column[k]:.9g}" for column in extra.values()),
                ]
            )


def write_recording(
    path: str | Path, t: FloatArray, y: FloatArray, u: FloatArray, extra: dict[str, FloatArray] | None = None
) -> None:
    """Write a recording in the input format (plus optional extra columns such as ground truth)."""
    extra = extra or {}
    with Path(path).open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow([*REQUIRED_COLUMNS, *extra])
        for k in range(t.size):
            writer.writerow(
                [
                    f"{t[k]:.6f}",
                    f"{y[k, 0]:.9g}",
                    f"{y[k, 1]:.9g}",
                    f"{u[k, 0]:.9g}",
                    f"{u[k, 1]:.9g}",
                    *(f"{col[k]:.9g}" for col in extra.values()),
                ]
            )
