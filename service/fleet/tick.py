"""What one ingest tick carries between the fleet engine's stages, and what it produces."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from agv_protocol.wire import EstimateBatch
from service.fleet.alarms import AlarmChange
from service.fleet.vehicle import Vehicle
from synth.model import FloatArray


@dataclass
class TickResult:
    """What one tick produced: estimates to publish, alarm changes to store then publish, new vehicles to store."""

    estimate_batches: list[EstimateBatch] = field(default_factory=list)
    alarms: list[AlarmChange] = field(default_factory=list)
    new_vehicles: list[Vehicle] = field(default_factory=list)
    received: int = 0
    accepted: int = 0

    @property
    def estimates(self) -> list[tuple[str, bytes]]:
        """(vehicle id, Estimate document) of every estimate of the tick."""
        return [pair for b in self.estimate_batches for pair in zip(b.vehicle_ids, b.documents(), strict=True)]


class Rows:
    """Samples of one profile collected during a tick, in arrival order."""

    __slots__ = ("later", "positions", "restart", "slots", "vehicles")

    def __init__(self) -> None:
        self.vehicles: list[Vehicle] = []
        self.slots: list[int] = []
        self.positions: list[int] = []  # where each sample sits in the tick's decoded headers
        self.later: list[tuple[int, int]] = []  # (position, round) of a vehicle's 2nd, 3rd... sample this tick
        self.restart: list[int] = []  # positions of the samples that restart their observer


@dataclass(slots=True)
class Checked:
    """A tick's frames after decoding and the plausibility check (stages 1-2 of :meth:`FleetEngine.process`).

    vehicles : the frames' vehicles, in arrival order; header : their decoded headers (MEASUREMENT_HEADER_DTYPE:
    seq and flags among them); values : (n, 4) [v_x, r, T_d, delta_d]; bank_of : each frame's profile ordinal;
    ok : plausible (conforming, finite, within limits); conforming, finite : the parts of ok that name a reject
    reason; grade : (n,) the road grade of the frames that carry one (flag bit 1), 0 for the others, or None when
    none does; graded : (n,) which frames carry one, or None when none does.
    """

    vehicles: list[Vehicle]
    header: np.ndarray
    values: FloatArray
    bank_of: np.ndarray
    ok: np.ndarray
    conforming: np.ndarray
    finite: np.ndarray
    grade: FloatArray | None = None
    graded: np.ndarray | None = None
