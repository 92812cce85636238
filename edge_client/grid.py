"""The four signals on the 10 ms grid: how a recording or a live bridge turns asynchronous messages into samples.

Vehicles carry v_x, r, the drive-torque demand and the steering demand on their own buses (CAN frames, ROS 2
topics) at their own rates and phases, and some the road's grade. Both the offline converters
(edge_client/can_log.py, edge_client/ros2.py) and the live bridges (edge_client/can_bridge.py,
edge_client/ros2_bridge.py) put them on the grid by one rule, the four :data:`COLUMNS` and, when the mapping names
it, the optional ``grade`` [rad] (a recording's :attr:`~edge_client.recording.Recording.grade`, a measurement's
``grade_rad``) alike:

* **zero-order hold**: a grid point takes, for each column, the latest value received at or before it (what a
  controller sampling the bus would see); nothing is interpolated, so no value from the future leaks in;
* **start**: the grid starts at the first instant every column has been received;
* **late or missing**: a column whose latest value is older than ``max_age_s`` at a grid point is stale. Offline,
  the recording ends there with an error naming the column and the time (a signal that stopped is never held
  silently); live, no measurement is sent for that grid point and the stale column is counted by name, so the
  service sees a gap (its ``long_gap_s`` rule re-initialises the observer after a long one).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from edge_client.recording import OPTIONAL_COLUMNS, Recording, RecordingError
from edge_client.sources import OneVehicleSource, Tick
from synth.model import FloatArray

COLUMNS = ("vx", "r", "torque", "steer")
#: The optional column a mapping may name beside :data:`COLUMNS`: the road's grade [rad, + uphill].
GRADE = "grade"
#: Time stamps this close are the same instant [s]: a candump log's resolution (an absolute time stamp of 1.7e9 s
#: carries 0.2 us of rounding).
TIME_RESOLUTION_S = 1e-6


def held_columns(mapped: Iterable[str]) -> tuple[str, ...]:
    """The columns held on the grid for a mapping of the columns ``mapped``: :data:`COLUMNS`, then the optional
    ones (edge_client/recording.py's ``OPTIONAL_COLUMNS``) among ``mapped``."""
    names = set(mapped)
    return COLUMNS + tuple(column for column in OPTIONAL_COLUMNS if column in names)


def hold_on_grid(
    samples: dict[str, tuple[list[float], list[float]]], sample_period_s: float, max_age_s: float, source: str
) -> tuple[Recording, float]:
    """The recording of ``samples`` (per column: time stamps [s], values in the protocol's units, in arrival order;
    the four :data:`COLUMNS` and, when the mapping names it, ``grade``) on the grid, by the module's rule; and the
    grid's first time stamp [s] on the samples' clock."""
    columns = held_columns(samples)
    missing = [column for column in columns if not samples[column][0]]
    if missing:
        raise RecordingError(f"{source}: no value of {', '.join(missing)} in the input (check the mapping)")
    series = {c: (np.asarray(samples[c][0]), np.asarray(samples[c][1])) for c in columns}
    for column, (times, _) in series.items():
        if np.any(np.diff(times) < 0):
            raise RecordingError(f"{source}: the time stamps of {column} go backwards")
    # from the first time every column is known to the input's last value: a column that stops before the others
    # is found stale below, not cut off silently
    start = max(times[0] for times, _ in series.values())
    end = max(times[-1] for times, _ in series.values())
    n = int(np.floor((end - start) / sample_period_s + 1e-9)) + 1
    if n < 2:
        raise RecordingError(f"{source}: under two samples in which every column is known")
    grid = start + sample_period_s * np.arange(n)
    out = np.empty((n, len(columns)))
    for i, column in enumerate(columns):
        times, values = series[column]
        latest = np.searchsorted(times, grid + TIME_RESOLUTION_S, side="right") - 1
        age = grid - times[latest]
        stale = np.flatnonzero(age > max_age_s)
        if stale.size:
            k = int(stale[0])
            raise RecordingError(
                f"{source}: {column} not received for {age[k]:.3f} s at t = {grid[k] - start:.2f} s of the recording "
                f"(more than max_age_s = {max_age_s:g} s): the signal stopped or its message is mapped wrong"
            )
        out[:, i] = values[latest]
    if not np.isfinite(out).all():
        raise RecordingError(f"{source}: a decoded value is not finite")
    t: FloatArray = sample_period_s * np.arange(n)  # not grid - start: absolute time stamps are large numbers
    grade = out[:, columns.index(GRADE)].copy() if GRADE in columns else None
    return Recording(t=t, y=out[:, :2].copy(), u=out[:, 2:4].copy(), grade=grade), float(start)


@dataclass(frozen=True)
class GridSample:
    """One grid point of a live stream: the four values [vx, r, torque, steer] and the road grade [rad] (None when
    the grade is not held), or the columns that were stale."""

    values: tuple[float, float, float, float] | None
    stale: tuple[str, ...] = ()
    grade: float | None = None


class LiveHold:
    """The latest value of each column and when it came (ns, any monotonic clock): the live side of the rule.

    ``columns`` are the held ones (:func:`held_columns`). ``update`` is called from the transport's threads,
    ``sample`` from the grid's loop; a lock keeps each pair of value and time together.
    """

    def __init__(self, max_age_s: float, columns: tuple[str, ...] = COLUMNS) -> None:
        self.max_age_ns = round(max_age_s * 1e9)
        self.columns = columns
        self._value = dict.fromkeys(columns, 0.0)
        self._received_ns: dict[str, int | None] = dict.fromkeys(columns, None)
        self._lock = threading.Lock()

    def update(self, column: str, value: float, received_ns: int) -> None:
        with self._lock:
            self._value[column] = value
            self._received_ns[column] = received_ns

    def sample(self, now_ns: int) -> GridSample:
        """The values held at ``now_ns``; before every column has come once, or with one older than ``max_age_s``,
        no values and the names of the columns at fault."""
        with self._lock:
            stale = tuple(
                c for c in self.columns if (t := self._received_ns[c]) is None or now_ns - t > self.max_age_ns
            )
            if stale:
                return GridSample(None, stale)
            v = self._value
            return GridSample((v["vx"], v["r"], v["torque"], v["steer"]), grade=v.get(GRADE))


#: A live source runs until stopped: the publisher is told it has this many samples.
ENDLESS = 2**62


class LiveSource(OneVehicleSource):
    """One vehicle's live signals as a :class:`~edge_client.sources.SampleSource` on the grid (the module's rule).

    A bridge (ROS 2, CAN) feeds :attr:`hold` from its transport's threads and counts what it refused; this class
    samples the hold at each of the publisher's ticks: a tick with every column fresh is a measurement, one with a
    stale column is not sent (its sequence number is skipped, so the service counts the gap) and is counted under
    that column's name. :meth:`prepare` waits for the first instant every column is fresh. ``mapped`` names the
    columns the bridge's mapping maps: with ``grade`` among them, the grade is held too (a stale grade is a stale
    column like the others) and every tick carries it.
    """

    def __init__(
        self,
        vehicle_id: str,
        sample_period_s: float,
        max_age_s: float,
        wait_s: float,
        clock: Callable[[], int],
        mapped: Iterable[str] = COLUMNS,
    ) -> None:
        super().__init__(vehicle_id, sample_period_s)
        self.hold = LiveHold(max_age_s, held_columns(mapped))
        self.wait_s = wait_s
        self.ticks = 0
        self.sampled = 0
        self.stale_ticks = dict.fromkeys(self.hold.columns, 0)
        self._clock = clock
        self._first = threading.Event()
        #: values used per column, and values refused as not finite (transport threads count under the lock)
        self.used = dict.fromkeys(self.hold.columns, 0)
        self.non_finite = 0
        self.lock = threading.Lock()

    def received(self, values: list[tuple[str, float]]) -> None:
        """Fresh values of columns from one message (on a transport's thread), at the source's clock now; a value
        that is not finite is counted and not held."""
        now = self._clock()
        for column, value in values:
            with self.lock:
                if not math.isfinite(value):
                    self.non_finite += 1
                    continue
                self.used[column] += 1
            self.hold.update(column, value, now)
        if not self._first.is_set() and self.hold.sample(self._clock()).values is not None:
            self._first.set()

    def used_text(self) -> str:
        return ", ".join(f"{column} {count}" for column, count in self.used.items())

    @property
    def n_samples(self) -> int:
        return ENDLESS

    def describe_missing(self, columns: tuple[str, ...]) -> str:
        """Where the stale ``columns`` come from, for the error of :meth:`prepare` (a bridge says more)."""
        return ", ".join(columns)

    def prepare(self) -> None:
        """Wait (at most ``wait_s``) until every column is fresh now: the grid starts there, with seq 0.

        An instant that has passed does not count: when every column came while the publisher was still starting
        and one has gone stale since, this waits for the next fresh instant, so that seq 0, sampled right after,
        is a measurement."""
        deadline = time.monotonic() + self.wait_s
        while True:
            if self._first.wait(max(deadline - time.monotonic(), 0.0)):
                if self.hold.sample(self._clock()).values is not None:
                    return
                self._first.clear()  # received() sets it again at the next message that leaves every column fresh
            if time.monotonic() >= deadline:
                missing = self.hold.sample(self._clock()).stale
                raise RecordingError(
                    f"no instant within {self.wait_s:g} s at which every signal was fresher than max_age_s = "
                    f"{self.hold.max_age_ns / 1e9:g} s; missing or stale: {self.describe_missing(missing)}"
                )

    def next_tick(self) -> Tick:
        sample = self.hold.sample(self._clock())
        k = self._k
        self._k += 1
        self.ticks += 1
        if sample.values is None:
            for column in sample.stale:
                self.stale_ticks[column] += 1
        else:
            self.sampled += 1
        values = sample.values or (0.0, 0.0, 0.0, 0.0)
        grade = None if GRADE not in self.hold.columns else np.array([sample.grade or 0.0])
        return Tick(
            k=k,
            y=np.array([values[:2]]),
            u=np.array([values[2:]]),
            active=np.array([sample.values is not None]),
            grade=grade,
        )

    def describe_grid(self) -> str:
        stale = ", ".join(f"{column} {count}" for column, count in self.stale_ticks.items() if count) or "none"
        return f"grid: {self.sampled} of {self.ticks} ticks sampled; ticks not sent for a stale column: {stale}"
