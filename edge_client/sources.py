"""Where the publisher's samples come from: a simulated batch of vehicles, or a recorded CSV.

A source yields one :class:`Tick` per sample period for all its vehicles at
once. Zenoh-free, so the publisher's transport and the simulation stay apart.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from edge_client.plant import PlantSimulator
from edge_client.recording import Recording
from edge_client.scenario import Scenario
from synth.model import FloatArray
from synth.params import VehicleParams


@dataclass(frozen=True)
class Tick:
    """Sample k of every vehicle of a source (nv vehicles).

    y : (nv, 2) measured [v_x [m/s], r [rad/s]]; u : (nv, 2) demanded [T_d [N m], delta_d [rad]];
    active : (nv,) the vehicle has a sample at k; x : (nv, 3) true state and f : (nv, 2) true faults,
    or None when the source does not know them (a recording); grade : (nv,) the road grade each vehicle reports
    [rad], NaN for one that reports none, or None when none reports one.
    """

    k: int
    y: FloatArray
    u: FloatArray
    active: NDArray[np.bool_]
    x: FloatArray | None = None
    f: FloatArray | None = None
    grade: FloatArray | None = None


class SampleSource(Protocol):
    """A fixed set of vehicles producing a sample every ``sample_period_s``."""

    @property
    def vehicle_ids(self) -> list[str]: ...

    @property
    def sample_period_s(self) -> float: ...

    @property
    def n_samples(self) -> int:
        """Samples the source can produce."""
        ...

    def prepare(self) -> None:
        """Do any slow set-up before the paced loop starts."""
        ...

    def next_tick(self) -> Tick: ...


class SimulatedSource:
    """A :class:`PlantSimulator` batch: ground truth included."""

    def __init__(
        self,
        vehicle_ids: Sequence[str],
        scenarios: Sequence[Scenario],
        params: VehicleParams | None = None,
        substeps: int = 10,
    ) -> None:
        if len(vehicle_ids) != len(scenarios):
            raise ValueError(f"{len(vehicle_ids)} vehicle ids for {len(scenarios)} scenarios")
        if len(set(vehicle_ids)) != len(vehicle_ids):
            raise ValueError("vehicle ids must be unique")
        self._ids = list(vehicle_ids)
        self.plant = PlantSimulator(scenarios, params=params, substeps=substeps)

    @property
    def vehicle_ids(self) -> list[str]:
        return self._ids

    @property
    def sample_period_s(self) -> float:
        return self.plant.sample_period_s

    @property
    def n_samples(self) -> int:
        return int(self.plant.n_samples.max())

    def prepare(self) -> None:
        """Compile the first chunk of every scenario (hundreds of ms for hundreds of vehicles)."""
        self.plant.prepare()

    def next_tick(self) -> Tick:
        sample = self.plant.step()
        return Tick(
            k=sample.k, y=sample.y, u=sample.u, active=sample.active, x=sample.x, f=sample.f, grade=sample.grade
        )


class OneVehicleSource:
    """What every source of a single vehicle shares: its id, its sample period [s] and ``_k``, the index of the
    next sample it gives."""

    def __init__(self, vehicle_id: str, sample_period_s: float) -> None:
        self._ids = [vehicle_id]
        self._period = sample_period_s
        self._k = 0

    @property
    def vehicle_ids(self) -> list[str]:
        return self._ids

    @property
    def sample_period_s(self) -> float:
        return self._period


class RecordingSource(OneVehicleSource):
    """One vehicle's recorded stream, sample by sample; no ground truth."""

    def __init__(self, vehicle_id: str, recording: Recording, sample_period_s: float = 0.01) -> None:
        super().__init__(vehicle_id, sample_period_s)
        self.recording = recording

    @property
    def n_samples(self) -> int:
        return len(self.recording)

    def prepare(self) -> None:
        """Nothing to do: the recording is in memory."""

    def next_tick(self) -> Tick:
        k = self._k
        if k >= len(self.recording):
            raise IndexError(f"the recording has {len(self.recording)} samples; sample {k} was asked for")
        self._k += 1
        return Tick(
            k=k,
            y=self.recording.y[k : k + 1],
            u=self.recording.u[k : k + 1],
            active=np.ones(1, dtype=bool),
            grade=None if self.recording.grade is None else self.recording.grade[k : k + 1],
        )
