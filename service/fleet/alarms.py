"""Alarms: a vectorised level detector with persistence and hysteresis, the fault-channel rule, and the alarm book.

:class:`LevelDetector` turns a stream of values per vehicle into a level
(0 OK, 1 WARN, 2 FAULT) for a whole batch at once. :class:`FaultLevels` is the
rule of the two fault channels (T_f and delta_f): a profile's thresholds and
the warm-up after an observer (re)start; the service's observer banks and
`agv-fe replay` both run it, so a replayed recording gets the service's levels.
:class:`AlarmBook` keeps the alarm records: raised when a condition starts,
latched until it is both cleared and acknowledged, each change an
:class:`agv_protocol.wire.Alarm` event.
"""

from __future__ import annotations

import time
import uuid
from dataclasses import dataclass, field, fields
from typing import Any, Literal, cast

import numpy as np

from agv_protocol.wire import LEVEL_CODES, Alarm, AlarmKind, AlarmState, Level
from service.fleet.cusum import CusumDetector
from service.fleet.grip import GripGate, GripLimits
from service.profiles import AlarmThresholds

#: The detectors' levels: their numbers are the protocol's level codes, which an estimate batch carries as they are.
OK, WARN, FAULT = LEVEL_CODES["OK"], LEVEL_CODES["WARN"], LEVEL_CODES["FAULT"]
LEVEL_NAMES: tuple[Level, Level, Level] = ("OK", "WARN", "FAULT")
RecordState = Literal["raised", "cleared"]
_NOT_HOLDING = np.iinfo(np.int64).min
_NONE = np.zeros(0, dtype=np.intp)
_NONE.flags.writeable = False


def level_rank(level: str) -> int:
    """A level's rank: its protocol code (OK < WARN < FAULT < STALE); KeyError for a name that is not a level."""
    return LEVEL_CODES[cast(Level, level)]


def seconds_to_ns(seconds: float) -> int:
    """A duration [s] in the integer nanoseconds [ns] that alarm rules count sample time in."""
    return round(seconds * 1e9)


class LevelDetector:
    """Two-level threshold detector with persistence and hysteresis, one row per vehicle slot.

    A value |x| >= ``warn`` (``fault``) held for ``raise_after_ns`` of sample
    time raises the level to WARN (FAULT). A raised level L drops by one when
    |x| < ``hysteresis`` x threshold_L has held for ``clear_after_ns``. All
    updates are vectorised over the rows of one batch; a row appears at most
    once per call.
    """

    def __init__(
        self,
        capacity: int,
        warn: float,
        fault: float,
        hysteresis: float,
        raise_after_ns: int,
        clear_after_ns: int,
    ) -> None:
        self.warn, self.fault, self.hysteresis = warn, fault, hysteresis
        self.raise_after_ns, self.clear_after_ns = raise_after_ns, clear_after_ns
        self.level = np.zeros(capacity, dtype=np.int8)
        # since when each condition has held without a break [ns], or _NOT_HOLDING
        self._above = np.full((2, capacity), _NOT_HOLDING, dtype=np.int64)  # |x| >= warn, |x| >= fault
        self._below = np.full((2, capacity), _NOT_HOLDING, dtype=np.int64)  # |x| < h warn, |x| < h fault

    def configure(self, warn: float, fault: float, hysteresis: float, raise_after_ns: int, clear_after_ns: int) -> None:
        self.warn, self.fault, self.hysteresis = warn, fault, hysteresis
        self.raise_after_ns, self.clear_after_ns = raise_after_ns, clear_after_ns

    def grow(self, capacity: int) -> None:
        extra = capacity - self.level.shape[0]
        if extra <= 0:
            return
        self.level = np.concatenate([self.level, np.zeros(extra, dtype=np.int8)])
        pad = np.full((2, extra), _NOT_HOLDING, dtype=np.int64)
        self._above = np.concatenate([self._above, pad], axis=1)
        self._below = np.concatenate([self._below, pad.copy()], axis=1)

    def reset(self, rows: np.ndarray, keep_level: bool = False) -> None:
        """Forget the timing of ``rows`` (after an observer restart); optionally the level too."""
        self._above[:, rows] = _NOT_HOLDING
        self._below[:, rows] = _NOT_HOLDING
        if not keep_level:
            self.level[rows] = OK

    def update(self, rows: np.ndarray, values: np.ndarray, t_ns: np.ndarray) -> np.ndarray:
        """Feed |values| at sample times ``t_ns`` for ``rows``; return the indices (into rows) whose level changed.

        A row at OK whose value is under both thresholds (most rows of a healthy fleet) stays at OK, and only its
        'above' timers break: that is all this does for it. Its 'below' timers are left as they were. They are
        read only to lower a raised level, and raising one takes values at or above the threshold, which reset
        them first (hysteresis <= 1). So the levels are exactly those of updating every row in full.
        """
        magnitude = np.abs(values)
        quiet = (magnitude < min(self.warn, self.fault)) & (self.level[rows] == OK)
        if quiet.all():
            self._above[:, rows] = _NOT_HOLDING
            return _NONE
        if not quiet.any():
            return self._update_in_full(rows, magnitude, t_ns)
        self._above[:, rows[quiet]] = _NOT_HOLDING
        busy = np.flatnonzero(~quiet)
        return busy[self._update_in_full(rows[busy], magnitude[busy], t_ns[busy])]

    def _update_in_full(self, rows: np.ndarray, magnitude: np.ndarray, t_ns: np.ndarray) -> np.ndarray:
        """Every timer and the level of ``rows`` for |values| ``magnitude``; indices (into rows) whose level changed."""
        thresholds = np.array([self.warn, self.fault])[:, None]
        above = magnitude[None, :] >= thresholds
        below = magnitude[None, :] < self.hysteresis * thresholds
        since_above = self._above[:, rows]
        since_below = self._below[:, rows]
        since_above = np.where(above, np.where(since_above == _NOT_HOLDING, t_ns, since_above), _NOT_HOLDING)
        since_below = np.where(below, np.where(since_below == _NOT_HOLDING, t_ns, since_below), _NOT_HOLDING)
        self._above[:, rows] = since_above
        self._below[:, rows] = since_below
        held_above = (since_above != _NOT_HOLDING) & (t_ns - since_above >= self.raise_after_ns)
        held_below = (since_below != _NOT_HOLDING) & (t_ns - since_below >= self.clear_after_ns)
        old = self.level[rows]
        new = old.copy()
        # escalate to the highest level whose condition has persisted
        up = np.where(held_above[1], FAULT, np.where(held_above[0], WARN, OK))
        new = np.maximum(new, up).astype(np.int8)
        # de-escalate one level at a time while the hysteresis band has been left long enough
        drop_fault = (new == FAULT) & held_below[1] & ~held_above[1]
        new[drop_fault] = WARN
        drop_warn = (new == WARN) & held_below[0] & ~held_above[0]
        new[drop_warn] = OK
        self.level[rows] = new
        return np.flatnonzero(new != old)


Detector = LevelDetector | CusumDetector


def _detectors(capacity: int, alarms: AlarmThresholds, sample_period_s: float) -> tuple[Detector, Detector]:
    """The torque and steering detectors of a rule: threshold (LevelDetector) or CUSUM (CusumDetector)."""
    raise_ns, clear_ns = seconds_to_ns(alarms.raise_after_s), seconds_to_ns(alarms.clear_after_s)
    channels = (
        (alarms.torque_warn_nm, alarms.torque_fault_nm, alarms.torque_block_sigma_nm),
        (alarms.steer_warn_rad, alarms.steer_fault_rad, alarms.steer_block_sigma_rad),
    )
    if alarms.rule == "cusum":
        block_n = max(1, round(alarms.cusum_block_s / sample_period_s))
        cusum = [
            CusumDetector(
                capacity,
                (warn, fault),
                float(sigma or 0.0),
                block_n,
                alarms.cusum_false_alarms_per_1000_h,
                block_n * sample_period_s,
                clear_ns,
            )
            for warn, fault, sigma in channels
        ]
        return cusum[0], cusum[1]
    torque, steer = (
        LevelDetector(capacity, warn, fault, alarms.hysteresis, raise_ns, clear_ns) for warn, fault, _ in channels
    )
    return torque, steer


def grip_limits(alarms: AlarmThresholds) -> GripLimits | None:
    """The grip gate's limits of a profile's alarm rules; None without a gate (``grip_limit_g`` null)."""
    if alarms.grip_limit_g is None:
        return None
    return GripLimits(alarms.grip_limit_g, alarms.grip_longitudinal_g, alarms.grip_cornering_g)


class FaultLevels:
    """The alarm levels of the fault channels T_f and delta_f, one row per vehicle slot.

    Two detectors (``torque`` on T_f [N m], ``steer`` on delta_f [rad]) of the
    profile's rule (:class:`AlarmThresholds`: ``rule`` 'threshold' gives
    :class:`LevelDetector`, 'cusum' :class:`service.fleet.cusum.CusumDetector`),
    and the warm-up rule: a row's fault estimates are evaluated only once
    ``warmup_s`` of sample time has passed since its observer (re)started
    (:meth:`restart`) and since its estimate last left the certified domain
    (:meth:`update`), and not until ``grip_hold_s`` after the vehicle's
    combined acceleration was last beyond the profile's grip limits
    (:class:`GripGate`, on the measurements :meth:`update` is given). Time is the samples' time stamps
    [ns]; ``sample_period_s`` sets the CUSUM's samples per block.
    """

    def __init__(self, capacity: int, alarms: AlarmThresholds, sample_period_s: float = 0.01) -> None:
        self.sample_period_s = sample_period_s
        self.rule = alarms.rule
        self.torque, self.steer = _detectors(capacity, alarms, sample_period_s)
        self.warmup_ns = seconds_to_ns(alarms.warmup_s)
        #: when each row's observer last (re)started [ns]
        self.started_t_ns = np.zeros(capacity, dtype=np.int64)
        self.grip = GripGate(capacity, grip_limits(alarms))
        self.grip_hold_ns = seconds_to_ns(alarms.grip_hold_s)
        #: per row: the levels are unjudged before this sample time, the tyres beyond the grip limit [ns]
        self.held_until_ns = np.full(capacity, _NOT_HOLDING, dtype=np.int64)
        #: samples the grip gate flagged (a counter for the service's statistics)
        self.beyond_grip = 0
        self._held_until_max = _NOT_HOLDING  # no row is held at or after this sample time [ns]

    def configure(self, alarms: AlarmThresholds) -> None:
        """New alarm settings; levels are kept, and timers too unless the rule changed (its statistics restart)."""
        raise_ns, clear_ns = seconds_to_ns(alarms.raise_after_s), seconds_to_ns(alarms.clear_after_s)
        torque, steer = self.torque, self.steer
        if alarms.rule == "threshold" and isinstance(torque, LevelDetector) and isinstance(steer, LevelDetector):
            torque.configure(alarms.torque_warn_nm, alarms.torque_fault_nm, alarms.hysteresis, raise_ns, clear_ns)
            steer.configure(alarms.steer_warn_rad, alarms.steer_fault_rad, alarms.hysteresis, raise_ns, clear_ns)
        else:
            self.torque, self.steer = _detectors(torque.level.shape[0], alarms, self.sample_period_s)
            self.torque.level[:], self.steer.level[:] = torque.level, steer.level
        self.rule = alarms.rule
        self.warmup_ns = seconds_to_ns(alarms.warmup_s)
        self.grip.configure(grip_limits(alarms))
        self.grip_hold_ns = seconds_to_ns(alarms.grip_hold_s)

    def grow(self, capacity: int) -> None:
        extra = capacity - self.started_t_ns.shape[0]
        if extra <= 0:
            return
        self.torque.grow(capacity)
        self.steer.grow(capacity)
        self.grip.grow(capacity)
        self.started_t_ns = np.concatenate([self.started_t_ns, np.zeros(extra, dtype=np.int64)])
        self.held_until_ns = np.concatenate([self.held_until_ns, np.full(extra, _NOT_HOLDING, dtype=np.int64)])

    def reset(self, rows: np.ndarray) -> None:
        """Forget everything of ``rows``: levels and timers (a slot given to another vehicle)."""
        self.torque.reset(rows)
        self.steer.reset(rows)
        self.grip.reset(rows)
        self.held_until_ns[rows] = _NOT_HOLDING

    def judged(self, rows: np.ndarray, t_ns: np.ndarray) -> np.ndarray:
        """(k,) bool: the rows whose levels a sample at ``t_ns`` is judged by (after the warm-up and the grip
        gate's hold)."""
        warm = t_ns - self.started_t_ns[rows] >= self.warmup_ns
        if not t_ns.shape[0] or self._held_until_max <= t_ns.min():  # the common tick: nobody is held
            return warm
        return warm & (t_ns >= self.held_until_ns[rows])

    def unjudged_because(self, rows: np.ndarray, t_ns: np.ndarray) -> list[list[str]]:
        """Per row, why its levels do not judge a sample at ``t_ns`` (an empty list: they do): 'warm-up' (the
        observer (re)started, or its estimate left the certified domain, less than warmup_s before), 'beyond
        grip' (the grip gate's hold). What :meth:`judged` decides, with its reasons; for status documents."""
        warm = (t_ns - self.started_t_ns[rows] >= self.warmup_ns).tolist()
        held = (t_ns < self.held_until_ns[rows]).tolist()
        return [
            [*(() if w else ("warm-up",)), *(("beyond grip",) if h else ())] for w, h in zip(warm, held, strict=True)
        ]

    def restart(self, rows: np.ndarray, t_ns: np.ndarray) -> None:
        """The observers of ``rows`` (re)start at sample times ``t_ns`` [ns]: the warm-up runs from there;
        the persistence timers are forgotten and the levels held until the warm-up is over."""
        self.started_t_ns[rows] = t_ns
        self.torque.reset(rows, keep_level=True)
        self.steer.reset(rows, keep_level=True)

    def update(
        self,
        rows: np.ndarray,
        f_hat: np.ndarray,
        t_ns: np.ndarray,
        usable: np.ndarray | None = None,
        certified: np.ndarray | None = None,
        measured: np.ndarray | None = None,
    ) -> np.ndarray:
        """Feed the fault estimates of one sample per row; return the indices (into rows) whose level changed.

        rows : (k,) distinct slots; f_hat : (k, 2) [T_f [N m], delta_f [rad]]; t_ns : (k,) sample times [ns];
        usable : (k,) bool, the rows whose estimate may be used (finite), None for all. A row still in its
        warm-up, or not usable, leaves its detectors untouched. An index may appear twice (both channels).
        certified : (k,) bool, the rows whose estimate the design's certificate covers (synth.observer.StepResult
        .certified), None for all. A row outside is judged as an observer that restarts there: its levels are
        held, its persistence timers forgotten, and its warm-up runs again from its last uncertified sample (the
        estimate carries what the model got wrong outside the box until the error has decayed).
        measured : (k, >= 2) the rows' measurements [v_x m/s, r rad/s, ...] for the grip gate, None for no gate. A
        row beyond the profile's grip limits (:func:`grip_limits`) has its persistence timers forgotten and its
        levels held until ``grip_hold_s`` after.
        """
        if certified is not None and not certified.all():
            outside = np.flatnonzero(~certified)
            self.restart(rows[outside], t_ns[outside])
        if measured is not None and self.grip.limits is not None:
            beyond = np.flatnonzero(self.grip.update(rows, measured[:, 0], measured[:, 1], t_ns))
            if len(beyond):
                held = rows[beyond]
                until = t_ns[beyond] + self.grip_hold_ns
                self.held_until_ns[held] = until
                self._held_until_max = max(self._held_until_max, int(until.max()))
                self.torque.reset(held, keep_level=True)
                self.steer.reset(held, keep_level=True)
                self.beyond_grip += len(beyond)
        warm = self.judged(rows, t_ns)
        if usable is None and warm.all():  # the common case: every row, no picking out
            torque = self.torque.update(rows, f_hat[:, 0], t_ns)
            steer = self.steer.update(rows, f_hat[:, 1], t_ns)
        else:
            w = np.flatnonzero(warm if usable is None else usable & warm)
            if not len(w):
                return _NONE
            torque = w[self.torque.update(rows[w], f_hat[w, 0], t_ns[w])]
            steer = w[self.steer.update(rows[w], f_hat[w, 1], t_ns[w])]
        if not len(steer):
            return torque
        return steer if not len(torque) else np.concatenate([torque, steer])


class EffectivenessLevels:
    """The alarm levels of the actuators' effectiveness (synth.effectiveness), one row per slot: raised only when
    the data identify a loss (docs/math.md section 14).

    Two :class:`LevelDetector` on the identified loss 1 - (alpha_hat + k sigma_alpha), k =
    ``effectiveness_confidence_k`` and sigma_alpha the stage's posterior standard deviation of alpha: WARN while
    that upper confidence bound is below ``effectiveness_warn``, FAULT below ``effectiveness_fault``, each held
    ``effectiveness_after_s``; cleared with the profile's hysteresis and ``clear_after_s``. Without excitation
    (a demand that holds still) alpha is unobservable, sigma_alpha grows and nothing is raised. They run beside
    :class:`FaultLevels`, with its warm-up.
    """

    def __init__(self, capacity: int, alarms: AlarmThresholds) -> None:
        self.torque = LevelDetector(capacity, 1.0, 1.0, 1.0, 0, 0)
        self.steer = LevelDetector(capacity, 1.0, 1.0, 1.0, 0, 0)
        self.k = alarms.effectiveness_confidence_k
        self.configure(alarms)

    def configure(self, alarms: AlarmThresholds) -> None:
        self.k = alarms.effectiveness_confidence_k
        settings = (
            1.0 - alarms.effectiveness_warn,
            1.0 - alarms.effectiveness_fault,
            alarms.hysteresis,
            seconds_to_ns(alarms.effectiveness_after_s),
            seconds_to_ns(alarms.clear_after_s),
        )
        self.torque.configure(*settings)
        self.steer.configure(*settings)

    def grow(self, capacity: int) -> None:
        self.torque.grow(capacity)
        self.steer.grow(capacity)

    def reset(self, rows: np.ndarray, keep_level: bool = False) -> None:
        self.torque.reset(rows, keep_level)
        self.steer.reset(rows, keep_level)

    def upper_bound(self, alpha: np.ndarray, alpha_sigma: np.ndarray) -> np.ndarray:
        """alpha's upper confidence bound alpha_hat + k sigma_alpha, the value the thresholds are compared with [-]."""
        return alpha + self.k * alpha_sigma

    def update(self, rows: np.ndarray, alpha: np.ndarray, alpha_sigma: np.ndarray, t_ns: np.ndarray) -> np.ndarray:
        """Feed alpha_hat and its posterior standard deviation, (k, 2) each [torque, steer], of one sample per row;
        the indices (into rows) whose level changed. A gain above 1 is no loss."""
        loss = np.maximum(1.0 - self.upper_bound(alpha, alpha_sigma), 0.0)
        torque = self.torque.update(rows, loss[:, 0], t_ns)
        steer = self.steer.update(rows, loss[:, 1], t_ns)
        if not len(steer):
            return torque
        return steer if not len(torque) else np.concatenate([torque, steer])


@dataclass
class AlarmRecord:
    """One alarm: latched from when it is raised until it is both cleared and acknowledged."""

    id: str
    vehicle: str
    profile: str
    kind: AlarmKind
    level: Level
    peak_level: Level
    state: RecordState = "raised"
    acknowledged: bool = False
    raised_t_ns: int = 0
    cleared_t_ns: int | None = None
    acknowledged_t_ns: int | None = None
    acknowledged_by: str | None = None
    value: float | None = None
    threshold: float | None = None
    message: str = ""
    occurrences: int = 1
    updated_t_ns: int = 0
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def closed(self) -> bool:
        """No longer latched: the condition is gone and an operator acknowledged it."""
        return self.state == "cleared" and self.acknowledged

    def event(self, state: AlarmState, t_ns: int) -> Alarm:
        return Alarm(
            vehicle=self.vehicle,
            id=self.id,
            kind=self.kind,
            level=self.level,
            state=state,
            value=self.value,
            threshold=self.threshold,
            t_ns=t_ns,
            message=self.message,
        )

    def to_dict(self) -> dict[str, Any]:
        """Every field but ``extra``, in the order they are declared (the REST schema AlarmInfo is derived alike)."""
        return {name: getattr(self, name) for name in _RECORD_FIELDS}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> AlarmRecord:
        keys = cls.__dataclass_fields__.keys() - {"extra"}
        return cls(**{k: data[k] for k in keys if k in data})


#: AlarmRecord's fields as stored and served (to_dict), in declaration order: all but ``extra``.
_RECORD_FIELDS = tuple(f.name for f in fields(AlarmRecord) if f.name != "extra")


@dataclass(frozen=True)
class AlarmChange:
    """A change of one record and the event it publishes."""

    record: AlarmRecord
    event: Alarm


class UnknownAlarm(KeyError):
    """No latched alarm has this id."""


class AlarmBook:
    """The latched alarms, at most one per (vehicle, kind)."""

    def __init__(self) -> None:
        self._by_key: dict[tuple[str, str], AlarmRecord] = {}
        self._by_id: dict[str, AlarmRecord] = {}

    def load(self, records: list[AlarmRecord], served: bool = True) -> None:
        """Restore latched alarms: after a restart, of vehicles taken over, or (``served`` False) the ``unserved``
        alarms of vehicles this replica does not serve (service/ownership.py). A replica that serves the vehicles
        loads an ``unserved`` alarm still raised as cleared now: it serves them, and the warden stores the clear."""
        for record in records:
            if served and record.kind == "unserved" and record.state == "raised":
                now_ns = time.time_ns()
                record.state, record.cleared_t_ns, record.updated_t_ns = "cleared", now_ns, now_ns
                record.message = "served again"
            if not record.closed:
                self._by_key[(record.vehicle, record.kind)] = record
                self._by_id[record.id] = record

    def latched(self) -> list[AlarmRecord]:
        return list(self._by_id.values())

    def forget(self, vehicles: set[str]) -> None:
        """Drop the latched alarms of ``vehicles`` from memory (another replica serves them now)."""
        for key in [k for k in self._by_key if k[0] in vehicles]:
            record = self._by_key.pop(key)
            self._by_id.pop(record.id, None)

    def for_vehicle(self, vehicle: str) -> list[AlarmRecord]:
        return [r for r in self._by_id.values() if r.vehicle == vehicle]

    def get(self, alarm_id: str) -> AlarmRecord | None:
        return self._by_id.get(alarm_id)

    def current(self, vehicle: str, kind: AlarmKind) -> AlarmRecord | None:
        return self._by_key.get((vehicle, kind))

    def raise_level(
        self,
        vehicle: str,
        profile: str,
        kind: AlarmKind,
        level: Level,
        t_ns: int,
        value: float | None,
        threshold: float | None,
        message: str,
    ) -> AlarmChange | None:
        """The condition of (vehicle, kind) holds at ``level``: raise, escalate, re-raise or change level."""
        record = self._by_key.get((vehicle, kind))
        if record is None:
            record = AlarmRecord(
                id=f"al-{uuid.uuid4().hex[:12]}",
                vehicle=vehicle,
                profile=profile,
                kind=kind,
                level=level,
                peak_level=level,
                raised_t_ns=t_ns,
            )
            self._by_key[(vehicle, kind)] = record
            self._by_id[record.id] = record
        elif record.state == "raised" and record.level == level:
            return None
        else:
            if record.state == "cleared":
                record.occurrences += 1
                record.cleared_t_ns = None
            if level_rank(level) > level_rank(record.level) and record.acknowledged:
                # an escalation needs a new acknowledgement
                record.acknowledged = False
                record.acknowledged_t_ns = None
                record.acknowledged_by = None
            record.state = "raised"
            record.level = level
            if level_rank(level) > level_rank(record.peak_level):
                record.peak_level = level
        record.value, record.threshold, record.message = value, threshold, message
        record.updated_t_ns = t_ns
        return AlarmChange(record, record.event("raised", t_ns))

    def clear(self, vehicle: str, kind: AlarmKind, t_ns: int, message: str = "") -> AlarmChange | None:
        """The condition of (vehicle, kind) is gone; the record stays latched until acknowledged."""
        record = self._by_key.get((vehicle, kind))
        if record is None or record.state == "cleared":
            return None
        record.state = "cleared"
        record.cleared_t_ns = t_ns
        record.updated_t_ns = t_ns
        if message:
            record.message = message
        change = AlarmChange(record, record.event("cleared", t_ns))
        self._forget_if_closed(record)
        return change

    def acknowledge(self, alarm_id: str, t_ns: int, by: str | None = None) -> AlarmChange:
        """An operator saw it. Idempotent; raise :class:`UnknownAlarm` if no latched alarm has this id."""
        record = self._by_id.get(alarm_id)
        if record is None:
            raise UnknownAlarm(alarm_id)
        if not record.acknowledged:
            record.acknowledged = True
            record.acknowledged_t_ns = t_ns
            record.acknowledged_by = by
            record.updated_t_ns = t_ns
        change = AlarmChange(record, record.event("acknowledged", t_ns))
        self._forget_if_closed(record)
        return change

    def _forget_if_closed(self, record: AlarmRecord) -> None:
        if record.closed:
            self._by_key.pop((record.vehicle, record.kind), None)
            self._by_id.pop(record.id, None)
