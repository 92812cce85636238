"""A recording from a vehicle's CAN log and its DBC file: the four signals the estimator needs on the 10 ms grid.

A vehicle carries v_x, r, the drive-torque demand and the steering demand as CAN
signals, in its own units and at its own rates. A mapping file names, for each of
the recording's columns, the DBC message and signal and the affine map to the
protocol's unit (docs/protocol.md), value = scale x decoded + offset; optionally
``grade`` too, the road's grade [rad, + uphill] (not the body's pitch), which then
fills the recording's grade column by the same rule:

.. code-block:: yaml

    vx:     {message: WHEEL_SPEEDS, signal: VehicleSpeed, scale: 0.2777777778}   # km/h -> m/s
    r:      {message: IMU_RATES, signal: YawRate, scale: 0.0174532925}          # deg/s -> rad/s
    torque: {message: DRIVE_DEMAND, signal: WheelTorqueDemand}                  # N m at the driven wheels
    steer:  {message: STEER_DEMAND, signal: RoadWheelAngleDemand}               # rad
    grade:  {message: ROAD_GRADE, signal: GradeDeg, scale: 0.0174532925}        # optional; deg -> rad

The log is read with python-can (candump ``.log``, Vector ``.asc`` and ``.blf``,
``.trc``, ``.csv``... by its extension) and decoded with cantools. Resampling (the rule of edge_client/grid.py):
the grid starts at the first time stamp at which every column has been received
and runs every ``sample_period_s``; each grid point takes the latest value
received at or before it (a zero-order hold, what a controller sampling the bus
would see). A column whose latest value is older than ``max_age_s`` at a grid
point ends the recording there with an error naming it and the time (a signal
that stopped), never a silent hold. Frames of other messages, or that fail to
decode, are counted and reported, not used.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from edge_client.grid import COLUMNS, hold_on_grid
from edge_client.recording import OPTIONAL_COLUMNS, Recording, RecordingError


class CanSignal(BaseModel):
    """Where one column comes from: a DBC message and signal, and value = scale x decoded + offset."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    message: str = Field(min_length=1, description="DBC message name")
    signal: str = Field(min_length=1, description="DBC signal name (its DBC factor and offset applied first)")
    scale: float = Field(1.0, allow_inf_nan=False, description="to the protocol's unit: multiply by this")
    offset: float = Field(0.0, allow_inf_nan=False, description="then add this")


class CanMapping(BaseModel):
    """The recording's four columns (and optionally its grade) as CAN signals, and the grid they are sampled on."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    vx: CanSignal
    r: CanSignal
    torque: CanSignal
    steer: CanSignal
    grade: CanSignal | None = Field(None, description="optional: the road's grade [rad], + uphill (not the pitch)")
    sample_period_s: float = Field(0.01, gt=0, le=1, description="the recording's sample period [s]")
    max_age_s: float = Field(0.1, gt=0, le=10, description="a value older than this at a grid point is missing [s]")

    def signals(self) -> dict[str, CanSignal]:
        """Column -> its signal: the four :data:`~edge_client.grid.COLUMNS`, then the optional ones mapped."""
        optional = [column for column in OPTIONAL_COLUMNS if getattr(self, column) is not None]
        return {column: getattr(self, column) for column in (*COLUMNS, *optional)}


@dataclass
class CanStats:
    """What the conversion read: frames used per mapped column, frames of other messages, frames that failed to
    decode."""

    frames: int = 0
    used: dict[str, int] = field(default_factory=lambda: dict.fromkeys(COLUMNS, 0))
    other: int = 0
    undecodable: int = 0
    first_complete_s: float | None = None


def load_mapping(path: str | Path) -> CanMapping:
    """Read a mapping file (YAML or JSON); a :class:`RecordingError` names the file and the field."""
    try:
        data = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise RecordingError(f"{path}: cannot read the mapping: {exc}") from exc
    try:
        return CanMapping.model_validate(data)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        raise RecordingError(f"{path}: invalid mapping: {problems}") from exc


def read_can_log(log: str | Path, dbc: str | Path, mapping: CanMapping) -> tuple[Recording, CanStats]:
    """Decode ``log`` with ``dbc`` and resample the mapped signals onto the grid (module docstring)."""
    import can

    database = load_dbc(dbc)
    wanted = resolve(database, mapping, dbc)
    try:
        messages: Iterable[Any] = can.LogReader(str(log))
        samples, stats = _decode(messages, database, wanted, tuple(mapping.signals()))
    except (OSError, ValueError, can.CanError) as exc:
        raise RecordingError(f"{log}: cannot read the CAN log: {exc}") from exc
    recording, stats.first_complete_s = hold_on_grid(samples, mapping.sample_period_s, mapping.max_age_s, str(log))
    return recording, stats


def resolve(database: Any, mapping: CanMapping, dbc: str | Path) -> dict[int, list[tuple[str, CanSignal]]]:
    """Frame id -> the columns it carries; every mapped message and signal must exist in the DBC."""
    wanted: dict[int, list[tuple[str, CanSignal]]] = {}
    for column, signal in mapping.signals().items():
        try:
            message = database.get_message_by_name(signal.message)
        except KeyError as exc:
            raise RecordingError(f"{dbc}: no message {signal.message!r} (mapped to {column})") from exc
        if signal.signal not in {s.name for s in message.signals}:
            raise RecordingError(
                f"{dbc}: message {signal.message!r} has no signal {signal.signal!r} (mapped to {column})"
            )
        wanted.setdefault(message.frame_id, []).append((column, signal))
    return wanted


def _decode(
    messages: Iterable[Any], database: Any, wanted: dict[int, list[tuple[str, CanSignal]]], columns: tuple[str, ...]
) -> tuple[dict[str, tuple[list[float], list[float]]], CanStats]:
    """Per mapped column (``columns``): (time stamps [s], values in the protocol's unit), in log order."""
    stats = CanStats(used=dict.fromkeys(columns, 0))
    samples: dict[str, tuple[list[float], list[float]]] = {column: ([], []) for column in columns}
    for frame in messages:
        stats.frames += 1
        carried = wanted.get(frame.arbitration_id)
        if carried is None:
            stats.other += 1
            continue
        decoded = decode_frame(database, frame, carried)
        if decoded is None:
            stats.undecodable += 1
            continue
        for column, value in decoded:
            times, values = samples[column]
            times.append(float(frame.timestamp))
            values.append(value)
            stats.used[column] += 1
    return samples, stats


def decode_frame(database: Any, frame: Any, columns: list[tuple[str, CanSignal]]) -> list[tuple[str, float]] | None:
    """The mapped columns a frame carries, in the protocol's units; None when it does not decode (a frame too short,
    a bad multiplexer, a mapped signal missing from it)."""
    from cantools.database.errors import DecodeError

    try:
        decoded = database.decode_message(frame.arbitration_id, bytes(frame.data), decode_choices=False)
    except (DecodeError, ValueError, KeyError, IndexError):
        return None
    out = []
    for column, signal in columns:
        value = decoded.get(signal.signal)
        if value is None:
            return None
        out.append((column, signal.scale * float(value) + signal.offset))
    return out


def load_dbc(dbc: str | Path) -> Any:
    """The DBC file as a cantools database; a :class:`RecordingError` says why it cannot be read."""
    import cantools
    from cantools.database.errors import UnsupportedDatabaseFormatError

    try:
        return cantools.database.load_file(str(dbc))
    except (OSError, UnsupportedDatabaseFormatError) as exc:
        raise RecordingError(f"{dbc}: cannot read the DBC file: {exc}") from exc
