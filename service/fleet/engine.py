"""The fleet engine: raw measurements in, estimates and alarm changes out.

Independent of Zenoh, FastAPI and SQLite: :meth:`FleetEngine.process` takes
the (key expression, payload) pairs that arrived since the last tick and
returns what to publish and store. Per tick, the samples of each profile are
stepped together, one round per sample index, so a vehicle whose samples
queued up is still stepped in sequence order.

What a real stream does, and what happens to it:

==================  ==================================================================
malformed           bad key, bad size, magic, version or id bytes: rejected, counted
id_mismatch         the payload's vehicle id differs from the key's: rejected, counted
unknown_vehicle     no such vehicle and ``unknown_vehicles = reject``: rejected, counted
duplicate           seq equal to the last one: dropped, counted
out_of_order        seq below the last one: dropped, counted
implausible_seq     seq jumped further ahead than the time stamps allow: dropped, counted, believed in nothing
reserved_bits       a flag bit this version does not define, or non-zero reserved bytes: rejected, counted
non_finite          NaN or infinite value: rejected, counted, observer untouched
out_of_range        outside the profile's plausibility limits: rejected, counted
no_gains            the profile has no active gains yet: rejected, counted
gap                 seq jumped: missing samples counted; a gap longer than
                    ``long_gap_s`` re-initialises the observer at the new sample
==================  ==================================================================

A sequence number is believed only as far as the time stamps carry it: a jump
of ``seq - last`` samples needs ``seq - last <= seq_jump_slack + 2 x (t - t_last)
/ sample_period`` (``t_last``, the time stamp of the sample at ``last``), so one
forged sequence number far ahead cannot make the vehicle's genuine samples look
late nor count billions of missing samples. A vehicle whose samples are refused
as late or implausible ``sequence_reject_count`` times in a row (its alarm rules)
raises ``sequence_rejected``, which clears at its next sample accepted in sequence.

A rejected sample never reaches the observer, and the values of a sample are
checked before its sequence number is believed: a non-finite or out-of-range
sample moves nothing, not the vehicle's sequence cursor either (a corrupted
sequence number must not make the vehicle's next good samples look late).
The vehicle's state is as if the sample had been lost; only its counters and
its last-seen time change.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from agv_protocol.wire import (
    FLAG_ROAD_GRADE,
    FLAG_SEQUENCE_RESTART,
    KNOWN_FLAGS,
    MAGIC,
    MEASUREMENT_HEADER_DTYPE,
    MEASUREMENT_HEADER_SIZE,
    PROTOCOL_VERSION,
    AlarmKind,
    Estimate,
    EstimateBatch,
    EstimateRow,
    Level,
    Measurement,
    ProtocolError,
    bucket_of,
    parse_vehicle_key,
)
from service.fleet.alarms import (
    FAULT,
    LEVEL_NAMES,
    OK,
    WARN,
    AlarmBook,
    AlarmChange,
    AlarmRecord,
    LevelDetector,
    seconds_to_ns,
)
from service.fleet.bank import ALPHAS, FAULTS, ProfileBank, StepOutput
from service.fleet.events import EventBus, FleetEvent
from service.fleet.tick import Checked, Rows, TickResult
from service.fleet.vehicle import BURST_REASONS, REJECT_REASONS, SEQUENCE_REASONS, RejectReason, Vehicle
from service.profiles import ProfileSpec
from synth.gains import ObserverGains
from synth.model import FloatArray
from synth.observer import RuntimeGains

#: Sequence numbers at or above this take the one-by-one path of a tick (exact Python integers there).
_FAST_SEQ_LIMIT = 1 << 62
#: What every measurement frame of this protocol version starts with: the magic, then the version byte.
_FRAME_PREFIX = MAGIC + bytes([PROTOCOL_VERSION])


def _limits_row(spec: ProfileSpec) -> tuple[float, float, float, float, float, float]:
    """(v_x min, v_x max, |r| max, |T_d| max, |delta_d| max, |grade| max) of a profile's plausibility limits."""
    lim = spec.limits
    return (
        lim.vx_min_mps,
        lim.vx_max_mps,
        lim.r_abs_max_radps,
        lim.torque_abs_max_nm,
        lim.steer_abs_max_rad,
        lim.grade_abs_max_rad,
    )


#: flag bits of a plain frame (one the plausibility stage checks without reading its bytes 56-63 as a grade)
_PLAIN_FLAGS = KNOWN_FLAGS & ~FLAG_ROAD_GRADE


def _note_grade(
    bank: ProfileBank, graded: np.ndarray, slots: np.ndarray, seq: np.ndarray, grade: FloatArray | None
) -> None:
    """Keep the road grade of the stepped samples of ``slots`` that carried one (``graded``), for the status."""
    if grade is not None and graded.any():
        bank.note_grade(slots[graded], seq[graded], grade[graded])


def _graded(header: np.ndarray) -> tuple[np.ndarray, FloatArray | None, np.ndarray | None]:
    """Which frames conform when a frame may carry a road grade (flag bit 1: bytes 56-63 are its grade, f64; zero
    without the flag), the grades (0 where a frame carries none) and which frames carry one; None, None when no
    frame does."""
    flags = header["flags"]
    known = (flags & ~np.uint8(KNOWN_FLAGS)) == 0
    graded = (flags & np.uint8(FLAG_ROAD_GRADE)) != 0
    if not graded.any():
        return known & (header["reserved"] == 0), None, None
    grade = np.where(graded, header["reserved"].view(np.float64), 0.0)
    return known & (graded | (header["reserved"] == 0)), grade, graded


def _classify(payload: bytes, vehicle_id: str) -> RejectReason:
    """Why a payload of the wrong size was refused: another vehicle's valid measurement, or garbage."""
    try:
        claimed = Measurement.decode(payload).vehicle_id
    except ProtocolError:
        return "malformed"
    return "id_mismatch" if claimed != vehicle_id else "malformed"


def _unjudged_because(bank: ProfileBank, slots: np.ndarray) -> list[list[str]]:
    """Why the fault levels of ``slots`` did not judge their latest sample (FaultLevels.unjudged_because at each
    slot's last sample time); an empty list: they did."""
    return bank.faults.unjudged_because(slots, bank.last_t_ns[slots])


class FleetError(Exception):
    """A request the fleet cannot carry out; the text says why."""


class UnknownVehicle(FleetError, KeyError):
    pass


class UnknownProfile(FleetError, KeyError):
    pass


@dataclass(frozen=True, slots=True)
class Stepped:
    """One observer step of a profile's rows, as the stages after it (detectors, publication) read it.

    idx : (k,) the rows' positions in ``rows``; slots : (k,) their slots in ``bank``; out : the step's output;
    t : (k,) the rows' sample time stamps [ns]; all_finite : every estimate is finite (no row needs picking out);
    measured : (k, 2) the rows' measurements [v_x m/s, r rad/s].
    """

    bank: ProfileBank
    rows: Rows
    idx: np.ndarray
    slots: np.ndarray
    out: StepOutput
    t: np.ndarray
    all_finite: bool
    measured: np.ndarray


@dataclass(frozen=True)
class EngineConfig:
    """The ingest settings the engine needs (a plain copy of :class:`service.settings.IngestSettings`)."""

    unknown_vehicles: Literal["register", "reject"] = "register"
    default_profile: str = "default"
    long_gap_s: float = 0.5
    seq_jump_slack: int = 100
    estimate_every_n: int = 1
    history_samples: int = 500
    prefix: str = "agv"


class FleetEngine:
    """Vehicles, profiles with their observer banks, and the alarm book."""

    def __init__(
        self,
        config: EngineConfig,
        *,
        events: EventBus | None = None,
        clock_ns: Callable[[], int] = time.time_ns,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        self.config = config
        self.events = events or EventBus()
        self.alarms = AlarmBook()
        self.banks: dict[str, ProfileBank] = {}
        self.vehicles: dict[str, Vehicle] = {}
        self._by_key: dict[str, Vehicle] = {}
        self._presence: dict[str, bool] = {}  # liveliness of vehicles not registered yet
        #: registered vehicles of a profile that could not be loaded: (profile, registration time [ns]); their
        #: samples are rejected as no_gains, not taken by the default profile
        self.held: dict[str, tuple[str, int]] = {}
        #: the stored payloads of held vehicles [kg], applied when their profile runs
        self.held_payloads: dict[str, float] = {}
        self._clock_ns = clock_ns
        self._monotonic = monotonic
        self.started_mono = monotonic()
        self.stats: dict[str, int] = {"received": 0, "accepted": 0, "estimates": 0, "published": 0}
        self.stats.update({"missing": 0, "gaps": 0, "restarts": 0, "numerical_restarts": 0})
        #: samples whose vehicle was beyond its profile's grip limit (fault levels held unjudged)
        self.stats["beyond_grip"] = 0
        self.rejected: dict[str, int] = dict.fromkeys(REJECT_REASONS, 0)
        #: plausibility limits of every profile, one row per bank ordinal (see _limits_row)
        self._limits = np.zeros((0, 6))
        self._ordinal: dict[str, int] = {}
        self._stale_count = 0  # vehicles marked stale now (a tick with none skips gathering the flags)
        # the common tick's shortcuts in stepping (one round, no restart, every estimate finite and published);
        # off, every tick takes the general path, which gives the same results (a test compares the two)
        self._shortcuts = True

    # ------------------------------------------------------------------ profiles and vehicles

    def _refresh_limits(self) -> None:
        self._ordinal = {name: k for k, name in enumerate(self.banks)}
        self._limits = np.array([_limits_row(bank.spec) for bank in self.banks.values()]).reshape(-1, 6)

    def add_profile(self, name: str, spec: ProfileSpec) -> ProfileBank:
        if name in self.banks:
            raise FleetError(f"profile {name!r} exists")
        bank = ProfileBank(name, spec, self.config.history_samples)
        self.banks[name] = bank
        self._refresh_limits()
        return bank

    def remove_profile(self, name: str) -> None:
        """Take back a profile that has no vehicle (one just added whose storage failed)."""
        bank = self.bank(name)
        if bank.used.any():
            raise FleetError(f"profile {name!r} has vehicles")
        del self.banks[name]
        self._refresh_limits()

    def hold(self, vehicle_id: str, profile: str, registered_t_ns: int) -> None:
        """Keep a registered vehicle of a profile that is not running for when it runs (see :meth:`release_held`)."""
        self.held[vehicle_id] = (profile, registered_t_ns)

    def release_held(self, profile: str) -> list[Vehicle]:
        """Register the held vehicles of ``profile``, which runs now."""
        ids = [vehicle_id for vehicle_id, (name, _) in self.held.items() if name == profile]
        released = [self.register(vehicle_id, profile, self.held[vehicle_id][1]) for vehicle_id in ids]
        self.load_payloads({v: self.held_payloads.pop(v) for v in ids if v in self.held_payloads})
        return released

    def update_profile_spec(self, name: str, spec: ProfileSpec) -> None:
        self.bank(name).set_spec(spec)
        self._refresh_limits()

    def activate(self, name: str, gains: ObserverGains, runtime: RuntimeGains | None = None) -> None:
        """Make ``gains`` the active gains of every vehicle of profile ``name``, atomically between ticks."""
        self.bank(name).activate(gains, runtime)

    @property
    def ready(self) -> bool:
        return bool(self.banks) and all(b.ready for b in self.banks.values())

    def bank(self, name: str) -> ProfileBank:
        """Profile ``name``'s bank, or UnknownProfile naming the known profiles."""
        try:
            return self.banks[name]
        except KeyError:
            raise UnknownProfile(f"no profile named {name!r}; known: {', '.join(sorted(self.banks))}") from None

    def register(
        self, vehicle_id: str, profile: str, registered_t_ns: int | None = None, announced: bool = False
    ) -> Vehicle:
        """Add a vehicle (or move it to ``profile``); its observer starts at its next measurement.

        ``announced``: registered through the API ahead of its first measurement, so it is not made STALE for
        sending nothing until it has sent something (a vehicle restored from storage, unannounced, is)."""
        bank = self.bank(profile)
        self.held.pop(vehicle_id, None)
        existing = self.vehicles.get(vehicle_id)
        if existing is not None:
            if existing.bank is bank:
                return existing
            for name, value in existing.bank.sample_counts(existing.slot).items():
                existing.base_counters[name] += value
            existing.bank.release(existing.slot)
            existing.bank = bank
            existing.slot = bank.allocate()
            bank.set_payload(existing.slot, existing.payload_kg)
            self._stagger(existing)
            return existing
        vehicle = Vehicle(
            vehicle_id,
            bank,
            bank.allocate(),
            self.config.prefix,
            self._clock_ns() if registered_t_ns is None else registered_t_ns,
        )
        vehicle.alive = self._presence.pop(vehicle_id, None)
        vehicle.announced = announced
        self._stagger(vehicle)
        self.vehicles[vehicle_id] = vehicle
        self._by_key[vehicle.meas_key] = vehicle
        if self.events.wants("vehicle"):
            self.events.publish(FleetEvent("vehicle", vehicle_id, {"event": "registered", "profile": profile}))
        return vehicle

    def set_payload(self, vehicle_id: str, payload_kg: float) -> Vehicle:
        """The vehicle carries ``payload_kg`` from its next sample on (docs/math.md 12.5).

        Raises UnknownVehicle, or ValueError for a payload that is not finite, negative, or more than the
        profile's vehicle mass (``mass_kg``): a load the model cannot stand for."""
        vehicle = self.vehicle(vehicle_id)
        limit = vehicle.bank.spec.params.mass_kg
        if not (math.isfinite(payload_kg) and 0.0 <= payload_kg <= limit):
            raise ValueError(
                f"payload_kg must be finite, >= 0 and at most the vehicle's mass ({limit:g} kg, profile "
                f"{vehicle.profile!r}), got {payload_kg!r}"
            )
        vehicle.payload_kg = float(payload_kg)
        vehicle.bank.set_payload(vehicle.slot, vehicle.payload_kg)
        if self.events.wants("vehicle"):
            self.events.publish(FleetEvent("vehicle", vehicle_id, {"event": "payload", "payload_kg": payload_kg}))
        return vehicle

    def load_payloads(self, payloads: dict[str, float]) -> list[str]:
        """The stored payloads of the vehicles served here (others are skipped; a held vehicle's waits for its
        profile); returns why any was refused (a profile whose vehicle is now lighter than its payload), that
        vehicle then running unloaded."""
        refused = []
        for vehicle_id, payload_kg in payloads.items():
            if vehicle_id in self.held:
                self.held_payloads[vehicle_id] = payload_kg
            elif vehicle_id in self.vehicles:
                try:
                    self.set_payload(vehicle_id, payload_kg)
                except ValueError as exc:
                    refused.append(f"{vehicle_id}: stored payload not applied: {exc}")
        return refused

    def adopt(self, vehicles: Iterable[tuple[str, str, int]], latched: Iterable[AlarmRecord]) -> list[str]:
        """Serve vehicles another replica served until now (bucket leases): their registry rows and latched
        alarms, as the shared database has them. Each observer starts at the vehicle's next measurement (as after
        a long gap), and a vehicle that sends nothing is STALE ``stale_after_s`` from now; one whose STALE alarm
        is still raised is stale already, so that its next measurement clears it. Returns the vehicles adopted."""
        now_mono = self._monotonic()
        adopted = []
        for vehicle_id, profile, registered_t_ns in vehicles:
            if vehicle_id in self.vehicles:
                continue
            if profile not in self.banks:
                self.hold(vehicle_id, profile, registered_t_ns)
                continue
            self.register(vehicle_id, profile, registered_t_ns).last_seen_mono = now_mono
            adopted.append(vehicle_id)
        records = list(latched)
        self.alarms.load(records)
        for record in records:
            vehicle = self.vehicles.get(record.vehicle)
            if vehicle is not None and record.kind == "stale" and record.state == "raised" and not vehicle.stale:
                vehicle.stale = True
                self._stale_count += 1
        return adopted

    def forget(self, vehicle_ids: Iterable[str]) -> None:
        """Stop serving vehicles another replica serves now (bucket leases): their observers, counters and
        latched alarms leave this replica's memory; the database keeps them for the next owner."""
        ids = set(vehicle_ids)
        for vehicle_id in ids:
            self.held.pop(vehicle_id, None)
            self._presence.pop(vehicle_id, None)
            vehicle = self.vehicles.pop(vehicle_id, None)
            if vehicle is None:
                continue
            self._by_key.pop(vehicle.meas_key, None)
            if vehicle.stale:
                self._stale_count -= 1
            vehicle.bank.release(vehicle.slot)
        self.alarms.forget(ids)

    def _stagger(self, vehicle: Vehicle) -> None:
        """Spread the published estimates of vehicles that register together over the N ticks of
        ``estimate_every_n``: after a service restart the whole fleet registers at once, and aligned
        phases would publish every vehicle's estimate on the same tick and none on the N - 1 others."""
        vehicle.bank.phase[vehicle.slot] = vehicle.slot % self.config.estimate_every_n

    def vehicle(self, vehicle_id: str) -> Vehicle:
        try:
            return self.vehicles[vehicle_id]
        except KeyError:
            raise UnknownVehicle(f"no vehicle {vehicle_id!r}") from None

    def level_of(self, vehicle: Vehicle) -> Level:
        if vehicle.stale:
            return "STALE"
        return LEVEL_NAMES[int(vehicle.bank.levels(vehicle.slot))]

    # ------------------------------------------------------------------ ingest

    def process(self, batch: Iterable[tuple[str, bytes]]) -> TickResult:
        """Validate, step and alarm on one tick's measurements (any order, any mix of vehicles).

        The tick is a pipeline of named stages: :meth:`_decode` (well-formed frames of known vehicles),
        :meth:`_plausibility` (every frame's values against its profile's limits, at once), sequencing
        (:meth:`_sequence_in_order` takes the common case at once, :meth:`_sequence_one_by_one` the rest in
        arrival order), then per profile :meth:`_step_bank` (the observer step), :meth:`_detectors` and
        :meth:`_publish_selection`. Each stage keeps its fast path as a guard inside it.
        """
        result = TickResult()
        now_mono = self._monotonic()
        now_ns = self._clock_ns()
        frame_vehicles, headers = self._decode(batch, result, now_mono)
        if not frame_vehicles:
            return result
        tick = self._plausibility(frame_vehicles, headers)
        per_bank: dict[str, Rows] = {}
        in_order = self._sequence_in_order(tick, per_bank, now_mono, now_ns, result)
        self._sequence_one_by_one(tick, ~in_order, per_bank, now_mono, now_ns, result)
        seq_all = tick.header["seq"].astype(np.int64)
        t_ns_all = tick.header["t_ns"].astype(np.int64)
        for name, rows in per_bank.items():
            self._step_bank(self.banks[name], rows, tick, seq_all, t_ns_all, now_mono, now_ns, result)
        return result

    def _decode(
        self, batch: Iterable[tuple[str, bytes]], result: TickResult, now_mono: float
    ) -> tuple[list[Vehicle], list[bytes]]:
        """Stage 1: the well-formed frames of known (or newly registered) vehicles, in arrival order, as their
        vehicles and their 64-byte headers; every other payload is rejected with its reason. The header's numbers
        (seq and flags among them) are read for the whole tick at once by :meth:`_plausibility`."""
        received = 0
        by_key = self._by_key.get
        prefix = _FRAME_PREFIX
        header_size = MEASUREMENT_HEADER_SIZE
        vehicles: list[Vehicle] = []
        headers: list[bytes] = []
        for key, payload in batch:
            received += 1
            vehicle = by_key(key)
            if vehicle is None:
                vehicle = self._resolve(key, payload, result, now_mono)
                if vehicle is None:
                    continue
            if len(payload) != vehicle.payload_len:
                self._reject(vehicle, _classify(payload, vehicle.id), now_mono, result)
                continue
            if not payload.startswith(prefix):  # the magic and the protocol version
                self._reject(vehicle, "malformed", now_mono, result)
                continue
            if not payload.endswith(vehicle.id_bytes):  # same length as expected: the id is the tail
                self._reject(vehicle, "id_mismatch", now_mono, result)
                continue
            vehicles.append(vehicle)
            headers.append(payload[:header_size])
        self.stats["received"] += received
        result.received = received
        return vehicles, headers

    def _plausibility(self, frame_vehicles: list[Vehicle], headers: list[bytes]) -> Checked:
        """Stage 2: the values of every frame at once, checked against its profile's limits before its sequence
        number is believed: finite, within limits, flag bits this version defines and zero reserved bytes (bytes
        56-63 of a frame with flag bit 1 are its road grade, checked as a value)."""
        header = np.frombuffer(b"".join(headers), dtype=MEASUREMENT_HEADER_DTYPE)
        values = np.column_stack([header["vx"], header["r"], header["torque"], header["steer"]])
        ordinal = self._ordinal
        if len(ordinal) == 1:  # one profile: no need to look at each vehicle's
            bank_of = np.zeros(len(frame_vehicles), dtype=np.intp)
        else:
            bank_of = np.array([ordinal[v.bank.name] for v in frame_vehicles], dtype=np.intp)
        lim = self._limits[bank_of]
        finite = np.isfinite(values).all(axis=1)
        conforming = ((header["flags"] & ~np.uint8(_PLAIN_FLAGS)) == 0) & (header["reserved"] == 0)
        grade = graded = None
        if not conforming.all():  # a frame with a road grade (even of 0), or one that breaks the format
            conforming, grade, graded = _graded(header)
            if grade is not None:
                finite &= np.isfinite(grade)
        with np.errstate(invalid="ignore"):
            ok = (
                conforming
                & finite
                & (values[:, 0] >= lim[:, 0])
                & (values[:, 0] <= lim[:, 1])
                & (np.abs(values[:, 1]) <= lim[:, 2])
                & (np.abs(values[:, 2]) <= lim[:, 3])
                & (np.abs(values[:, 3]) <= lim[:, 4])
            )
            if grade is not None:
                ok &= np.abs(grade) <= lim[:, 5]
        return Checked(frame_vehicles, header, values, bank_of, ok, conforming, finite, grade, graded)

    def _sequence_in_order(
        self, tick: Checked, per_bank: dict[str, Rows], now_mono: float, now_ns: int, result: TickResult
    ) -> np.ndarray:
        """Stage 3a, the common case at once: a plausible sample, the vehicle's only one in this tick and the next
        in its sequence (or its first), of a vehicle that is not stale and whose profile has gains. Returns which
        frames it took."""
        frame_vehicles = tick.vehicles
        fast = self._in_sequence(frame_vehicles, tick.header["seq"], tick.ok, tick.bank_of)
        fast_at = np.flatnonzero(fast)
        if not len(fast_at):
            return fast
        at_list = fast_at.tolist()
        fast_seq, fast_t = tick.header["seq"][fast_at].tolist(), tick.header["t_ns"][fast_at].tolist()
        for position, seq, t in zip(at_list, fast_seq, fast_t, strict=True):
            vehicle = frame_vehicles[position]
            vehicle.last_seen_mono = now_mono
            vehicle.last_seen_ns = now_ns
            vehicle.last_seq = seq
            vehicle.last_seq_t_ns = t
            if vehicle.seq_rejects:
                self._sequence_resumed(vehicle, now_ns, result)
        names = list(self.banks)
        fast_banks = tick.bank_of[fast_at]
        for o in [0] if len(names) == 1 else np.unique(fast_banks).tolist():
            at = at_list if len(names) == 1 else fast_at[fast_banks == o].tolist()
            rows = per_bank.get(names[o])
            if rows is None:
                rows = per_bank[names[o]] = Rows()
            rows.vehicles.extend([frame_vehicles[i] for i in at])
            rows.slots.extend([frame_vehicles[i].slot for i in at])
            rows.positions.extend(at)
        return fast

    def _sequence_one_by_one(
        self,
        tick: Checked,
        pending: np.ndarray,
        per_bank: dict[str, Rows],
        now_mono: float,
        now_ns: int,
        result: TickResult,
    ) -> None:
        """Stage 3b: every other sample, one by one in arrival order: rejects with their reasons, duplicates and
        late samples, sequence restarts and gaps (a long one restarts the observer), several samples of a vehicle
        in one tick (one round each)."""
        slow_at = np.flatnonzero(pending).tolist()
        if not slow_at:
            return
        good = tick.ok.tolist()
        t_list = tick.header["t_ns"].tolist()
        seq_list, flags_list = tick.header["seq"].tolist(), tick.header["flags"].tolist()
        touched: list[Vehicle] = []
        for position in slow_at:
            vehicle, seq, flags = tick.vehicles[position], seq_list[position], flags_list[position]
            vehicle.last_seen_mono = now_mono
            vehicle.last_seen_ns = now_ns
            if vehicle.stale:
                self._unstale(vehicle, now_ns, result)
            if not good[position]:
                reason: RejectReason = (
                    "reserved_bits"
                    if not tick.conforming[position]
                    else "non_finite"
                    if not tick.finite[position]
                    else "out_of_range"
                )
                self._reject(vehicle, reason, now_mono, result)
                continue
            restart = self._sequenced(vehicle, seq, flags, t_list[position], now_mono, result)
            if restart is None:
                continue
            vehicle.last_seq = seq
            vehicle.last_seq_t_ns = t_list[position]
            if vehicle.seq_rejects:
                self._sequence_resumed(vehicle, now_ns, result)
            if vehicle.bank.runtime is None:
                self._reject(vehicle, "no_gains", now_mono, result)
                continue
            rows = per_bank.get(vehicle.bank.name)
            if rows is None:
                rows = per_bank[vehicle.bank.name] = Rows()
            rnd = vehicle.pending
            if rnd == 0:
                touched.append(vehicle)
            else:
                rows.later.append((len(rows.vehicles), rnd))
            vehicle.pending = rnd + 1
            if restart:
                rows.restart.append(len(rows.vehicles))
            rows.vehicles.append(vehicle)
            rows.slots.append(vehicle.slot)
            rows.positions.append(position)
        for vehicle in touched:
            vehicle.pending = 0

    def _sequenced(
        self, vehicle: Vehicle, seq: int, flags: int, t_ns: int, now_mono: float, result: TickResult
    ) -> bool | None:
        """Whether a plausible sample's sequence number is believed: None (rejected, with its reason), or whether
        its observer must restart (a sequence restart the vehicle flagged, or a gap longer than long_gap_s)."""
        last = vehicle.last_seq
        if seq <= last:
            if flags & FLAG_SEQUENCE_RESTART and seq != last:
                return True
            self._reject(vehicle, "duplicate" if seq == last else "out_of_order", now_mono, result)
            return None
        if last >= 0 and seq > last + 1:
            if not self._believable_jump(vehicle, seq - last, t_ns):
                self._reject(vehicle, "implausible_seq", now_mono, result)
                return None
            missing = seq - last - 1
            vehicle.base_counters["missing"] += missing
            vehicle.base_counters["gaps"] += 1
            self.stats["missing"] += missing
            self.stats["gaps"] += 1
            return missing * vehicle.bank.spec.params.sample_period_s >= self.config.long_gap_s
        return False

    def _in_sequence(
        self, vehicles: list[Vehicle], seq: np.ndarray, plausible: np.ndarray, bank_of: np.ndarray
    ) -> np.ndarray:
        """Which frames pass 2 may take at once: plausible, their vehicle's only frame in the tick, the next
        sample of its sequence (or its first), not stale, with gains. Every other frame goes one by one."""
        n = len(vehicles)
        try:
            last = np.fromiter((v.last_seq for v in vehicles), dtype=np.int64, count=n)
        except OverflowError:  # a sequence number beyond int64 in the tick: those vehicles the exact way
            last = np.fromiter((min(v.last_seq, _FAST_SEQ_LIMIT) for v in vehicles), dtype=np.int64, count=n)
        ok = plausible & (seq < _FAST_SEQ_LIMIT) & (last < _FAST_SEQ_LIMIT)
        if len(set(vehicles)) < n:  # some vehicle sent several samples this tick: those go one by one
            identity = np.fromiter((id(v) for v in vehicles), dtype=np.uint64, count=n)
            _, inverse, counts = np.unique(identity, return_inverse=True, return_counts=True)
            ok &= counts[inverse] == 1
        if self._stale_count:
            ok &= ~np.fromiter((v.stale for v in vehicles), dtype=bool, count=n)
        if len(self.banks) > 1 or any(bank.runtime is None for bank in self.banks.values()):
            has_gains = np.array([bank.runtime is not None for bank in self.banks.values()], dtype=bool)
            ok &= has_gains[bank_of]
        next_seq = np.where(ok, seq, 0).astype(np.int64)  # exact: below 2^62 where it counts
        return np.asarray(ok & ((last < 0) | (next_seq == last + 1)))

    def _resolve(self, key: str, payload: bytes, result: TickResult, now_mono: float) -> Vehicle | None:
        """The slow path for a key not seen before: parse, check, register or reject."""
        try:
            vehicle_id, kind = parse_vehicle_key(key)
            if kind != "meas":
                raise ProtocolError(f"{key!r} is not a measurement key")
        except ProtocolError:
            self._reject(None, "malformed", now_mono, result)
            return None
        if key.split("/")[0] != self.config.prefix or key.split("/")[2] != bucket_of(vehicle_id):
            # a known vehicle's own counters say it too, as for every other reject of its samples
            self._reject(self.vehicles.get(vehicle_id), "malformed", now_mono, result)
            return None
        vehicle = self.vehicles.get(vehicle_id)
        if vehicle is not None:
            return vehicle
        try:
            claimed = Measurement.decode(payload).vehicle_id
        except ProtocolError:
            self._reject(None, "malformed", now_mono, result)
            return None
        if claimed != vehicle_id:
            self._reject(None, "id_mismatch", now_mono, result)
            return None
        if vehicle_id in self.held:  # its profile is not running
            self._reject(None, "no_gains", now_mono, result)
            return None
        if self.config.unknown_vehicles == "reject" or self.config.default_profile not in self.banks:
            self._reject(None, "unknown_vehicle", now_mono, result)
            return None
        vehicle = self.register(vehicle_id, self.config.default_profile)
        result.new_vehicles.append(vehicle)
        return vehicle

    def _believable_jump(self, vehicle: Vehicle, jump: int, t_ns: int) -> bool:
        """Whether a sequence jump of ``jump`` samples is carried by the time stamps: ``jump <= slack + 2 x
        elapsed / sample_period``, with ``elapsed`` from the time stamp of the vehicle's last sample in sequence
        (none if the clock went back). Exact integers: a forged seq may be anything up to 2^64 - 1."""
        period_ns = seconds_to_ns(vehicle.bank.spec.params.sample_period_s)
        elapsed_ns = max(t_ns - vehicle.last_seq_t_ns, 0)
        return jump * period_ns <= self.config.seq_jump_slack * period_ns + 2 * elapsed_ns

    def _sequence_resumed(self, vehicle: Vehicle, now_ns: int, result: TickResult) -> None:
        """A sample of a vehicle whose samples were refused as late or implausible was accepted in sequence."""
        vehicle.seq_rejects = 0
        change = self.alarms.clear(vehicle.id, "sequence_rejected", now_ns, "samples accepted in sequence again")
        self._emit(change, result)

    def _reject(self, vehicle: Vehicle | None, reason: RejectReason, now_mono: float, result: TickResult) -> None:
        self.rejected[reason] += 1
        if vehicle is None:
            return
        vehicle.rejected[reason] += 1
        if reason in SEQUENCE_REASONS:
            self._sequence_refused(vehicle, reason, result)
            return
        if reason not in BURST_REASONS:
            return
        alarms = vehicle.bank.spec.alarms
        times = vehicle.reject_times
        times.append(now_mono)
        while times and now_mono - times[0] > alarms.reject_burst_window_s:
            times.popleft()
        if len(times) >= alarms.reject_burst_count:
            change = self.alarms.raise_level(
                vehicle.id,
                vehicle.profile,
                "rejected_inputs",
                "WARN",
                self._clock_ns(),
                float(len(times)),
                float(alarms.reject_burst_count),
                f"{len(times)} rejected measurements within {alarms.reject_burst_window_s:g} s (last: {reason})",
            )
            self._emit(change, result)

    def _sequence_refused(self, vehicle: Vehicle, reason: RejectReason, result: TickResult) -> None:
        """One more sample of the vehicle refused as late or implausible; enough in a row raise an alarm."""
        vehicle.seq_rejects += 1
        count = vehicle.bank.spec.alarms.sequence_reject_count
        if vehicle.seq_rejects < count:
            return
        change = self.alarms.raise_level(
            vehicle.id,
            vehicle.profile,
            "sequence_rejected",
            "WARN",
            self._clock_ns(),
            float(vehicle.seq_rejects),
            float(count),
            f"{vehicle.seq_rejects} samples in a row refused as late or with an implausible sequence jump "
            f"(last: {reason}; last sample in sequence: seq {vehicle.last_seq})",
        )
        self._emit(change, result)

    def _step_bank(
        self,
        bank: ProfileBank,
        rows: Rows,
        tick: Checked,
        tick_seq: np.ndarray,
        tick_t_ns: np.ndarray,
        now_mono: float,
        now_ns: int,
        result: TickResult,
    ) -> None:
        """Step the validated samples of one profile, one round per sample index of a vehicle."""
        at = np.array(rows.positions, dtype=np.int64)
        values, seq, t_ns = tick.values[at], tick_seq[at], tick_t_ns[at]
        grade = None if tick.grade is None else tick.grade[at]
        slots = np.array(rows.slots, dtype=np.int64)
        if self._shortcuts and not rows.later and not rows.restart:  # the common tick: one sample each, no restart
            idx = np.arange(len(slots))
            out = bank.step(slots, values[:, :2], values[:, 2:], seq, t_ns, grade)
            if tick.graded is not None:
                _note_grade(bank, tick.graded[at], slots, seq, grade)
            self._after_step(bank, rows, idx, slots, out, seq, t_ns, values, result)
            result.accepted += len(slots)
            self.stats["accepted"] += len(slots)
            return
        rounds = np.zeros(len(slots), dtype=np.int64)
        if rows.later:
            later_at, rnd = np.array(rows.later, dtype=np.int64).T
            rounds[later_at] = rnd
        restart = np.zeros(len(slots), dtype=bool)
        restart[rows.restart] = True
        for rnd in range(int(rounds.max()) + 1 if len(rounds) else 0):
            idx = np.flatnonzero(rounds == rnd)
            if len(idx) == 0:
                continue
            s = slots[idx]
            again = idx[restart[idx]]
            if len(again):
                for i in again:
                    bank.restart(int(slots[i]))
                    rows.vehicles[i].base_counters["restarts"] += 1
                self.stats["restarts"] += len(again)
            round_grade = None if grade is None else grade[idx]
            out = bank.step(s, values[idx][:, [0, 1]], values[idx][:, [2, 3]], seq[idx], t_ns[idx], round_grade)
            if tick.graded is not None:
                _note_grade(bank, tick.graded[at[idx]], s, seq[idx], round_grade)
            self._after_step(bank, rows, idx, s, out, seq, t_ns, values, result)
        result.accepted += len(slots)
        self.stats["accepted"] += len(slots)

    def _after_step(
        self,
        bank: ProfileBank,
        rows: Rows,
        idx: np.ndarray,
        slots: np.ndarray,
        out: StepOutput,
        seq: np.ndarray,
        t_ns: np.ndarray,
        values: np.ndarray,
        result: TickResult,
    ) -> None:
        """Stages 5-6 after one observer step of a profile's rows: the detectors, then what to publish."""
        all_finite = bool(out.finite.all())  # the common case: no row needs picking out
        if not all_finite:
            self.stats["numerical_restarts"] += int((~out.finite).sum())
        step = Stepped(bank, rows, idx, slots, out, t_ns[idx], all_finite, values[idx, :2])
        self._detectors(step, result)
        self._publish_selection(step, seq, values, result)

    def _detectors(self, step: Stepped, result: TickResult) -> None:
        """Stage 5: the fault channels after the warm-up (FaultLevels, as `agv-fe replay` runs them), the domain
        always, the effectiveness when the profile runs its stage; alarm records follow the rows that changed."""
        bank, slots, t, out, all_finite = step.bank, step.slots, step.t, step.out, step.all_finite
        est, finite, certified = out.values, out.finite, out.certified
        usable = None if self._shortcuts and all_finite else finite
        before = bank.faults.beyond_grip
        changed = set(bank.faults.update(slots, est[:, FAULTS], t, usable, certified, step.measured).tolist())
        self.stats["beyond_grip"] += bank.faults.beyond_grip - before
        if self._shortcuts and all_finite:
            changed.update(bank.domain.update(slots, (~certified).astype(float), t).tolist())
        else:
            f = np.flatnonzero(finite)
            changed.update(f[bank.domain.update(slots[f], (~certified[f]).astype(float), t[f])].tolist())
        if bank.stage is not None:  # the effectiveness alarms, on alpha_hat and its sigma (finite rows)
            # after the fault channels' warm-up, which restarts where the estimate left the certified domain, as
            # `agv-fe replay` judges them
            f = np.flatnonzero(finite & bank.faults.judged(slots, t))
            sigma = bank.stage.alpha_sigma(slots[f])
            changed.update(f[bank.effectiveness.update(slots[f], est[f, ALPHAS], sigma, t[f])].tolist())
        for j in sorted(changed):
            self._alarm_transitions(bank, step.rows.vehicles[step.idx[j]], int(t[j]), est[j], result)

    def _publish_selection(self, step: Stepped, seq: np.ndarray, values: np.ndarray, result: TickResult) -> None:
        """Stage 6: the counts, and which estimates to publish (every n-th finite estimate of each vehicle) as the
        tick's batch of this profile, with the estimate events of the vehicles someone follows.

        seq : (n,) and values : (n, 4) the sequence numbers and measurements of the n rows of ``step.rows``, which
        ``step.idx`` indexes.
        """
        bank, idx, slots, t, out, all_finite = step.bank, step.idx, step.slots, step.t, step.out, step.all_finite
        est, in_domain, finite = out.values, out.in_domain, out.finite
        bank.accepted[slots] += 1
        every_n = self.config.estimate_every_n
        if self._shortcuts and all_finite and every_n == 1:  # every row's estimate, as it is
            bank.estimates[slots] += 1
            bank.published[slots] += 1
            self.stats["estimates"] += len(slots)
            pub_slots, pub_idx, pub_t, pub_est, pub_in_domain, fast = slots, idx, t, est, in_domain, out.fast
        else:
            done = slots[finite]
            bank.estimates[done] += 1
            phase = bank.phase[done]
            bank.phase[done] = (phase + 1) % every_n
            pub = np.flatnonzero(finite)[phase == 0]
            bank.published[slots[pub]] += 1
            self.stats["estimates"] += len(done)
            if not len(pub):
                return
            pub_slots, pub_idx, pub_t, pub_est, pub_in_domain = slots[pub], idx[pub], t[pub], est[pub], in_domain[pub]
            fast = None if out.fast is None else out.fast[pub]
        level = bank.levels(pub_slots)
        at = pub_idx.tolist()
        vehicles = step.rows.vehicles
        ids = [vehicles[i].id for i in at]
        # every vehicle of the tick had its STALE state cleared before it was stepped (stage 3); the detectors'
        # level numbers are the protocol's level codes (alarms.OK, WARN, FAULT)
        batch = EstimateBatch(
            ids, seq[pub_idx], pub_t, pub_est, pub_in_domain, level, bank.version or "", fast, bank.columns
        )
        result.estimate_batches.append(batch)
        if not self.events.wants("estimate"):
            return
        audience = self.events.audience("estimate")  # None: every vehicle
        for j, vehicle_id in enumerate(ids):
            if audience is not None and vehicle_id not in audience:
                continue
            self.events.publish(FleetEvent("estimate", vehicle_id, batch.estimate(j), tuple(values[at[j]].tolist())))

    def _alarm_transitions(
        self, bank: ProfileBank, vehicle: Vehicle, t_ns: int, x5: np.ndarray, result: TickResult
    ) -> None:
        """Bring the vehicle's alarm records in line with its detector levels."""
        a = bank.spec.alarms
        slot = vehicle.slot
        held = f"for {a.raise_after_s:g} s"
        channels: list[tuple[AlarmKind, int, float, float, float, str]] = [
            ("torque_fault", int(bank.torque.level[slot]), float(x5[3]), a.torque_warn_nm, a.torque_fault_nm,
             "|T_f| >= {threshold:g} N m " + held),
            ("steer_fault", int(bank.steer.level[slot]), float(x5[4]), a.steer_warn_rad, a.steer_fault_rad,
             "|delta_f| >= {threshold:g} rad " + held),
        ]  # fmt: skip
        if bank.stage is not None:
            channels += self._effectiveness_channels(bank, slot, x5)
        for kind, level, value, warn, fault, message in channels:
            self._sync_alarm(vehicle, kind, level, value, warn, fault, message, t_ns, result)
        domain_level = int(bank.domain.level[slot])
        current = self.alarms.current(vehicle.id, "out_of_domain")
        if domain_level >= WARN and (current is None or current.state != "raised"):
            change = self.alarms.raise_level(
                vehicle.id,
                vehicle.profile,
                "out_of_domain",
                "WARN",
                t_ns,
                float(x5[0]),
                None,
                f"premise or estimated v_y outside the design bounds for {a.out_of_domain_after_s:g} s "
                f"(v_x = {x5[0]:.2f} m/s, v_y = {x5[1]:.2f} m/s, r = {x5[2]:.3f} rad/s)",
            )
            self._emit(change, result)
        elif domain_level == OK and current is not None:
            self._emit(self.alarms.clear(vehicle.id, "out_of_domain", t_ns), result)

    @staticmethod
    def _effectiveness_channels(
        bank: ProfileBank, slot: int, x5: np.ndarray
    ) -> list[tuple[AlarmKind, int, float, float, float, str]]:
        """The effectiveness alarms' (kind, level, alpha_hat, warn, fault, message): the message says why, alpha_hat
        and its upper confidence bound alpha_hat + k sigma_alpha against the threshold (docs/math.md section 14)."""
        a = bank.spec.alarms
        levels = bank.effectiveness
        alpha = x5[ALPHAS]
        sigma = bank.stage.alpha_sigma(np.array([slot]))[0] if bank.stage is not None else np.zeros(2)
        bound = levels.upper_bound(alpha, sigma)
        out: list[tuple[AlarmKind, int, float, float, float, str]] = []
        names: tuple[tuple[AlarmKind, str, LevelDetector], ...] = (
            ("torque_effectiveness", "drive-torque", levels.torque),
            ("steer_effectiveness", "steering", levels.steer),
        )
        for c, (kind, name, detector) in enumerate(names):
            message = (
                f"{name} effectiveness identified below {{threshold:g}}: alpha_hat {alpha[c]:.3f}, upper bound "
                f"alpha_hat + {levels.k:g} sigma = {bound[c]:.3f} (sigma {sigma[c]:.3f}) for "
                f"{a.effectiveness_after_s:g} s"
            )
            level = int(detector.level[slot])
            out.append((kind, level, float(alpha[c]), a.effectiveness_warn, a.effectiveness_fault, message))
        return out

    def _sync_alarm(
        self,
        vehicle: Vehicle,
        kind: AlarmKind,
        level: int,
        value: float,
        warn: float,
        fault: float,
        message: str,
        t_ns: int,
        result: TickResult,
    ) -> None:
        """Raise, re-level or clear the vehicle's alarm of ``kind``; ``message`` is formatted with the threshold."""
        current = self.alarms.current(vehicle.id, kind)
        if level == OK:
            if current is not None:
                self._emit(self.alarms.clear(vehicle.id, kind, t_ns), result)
            return
        threshold = fault if level == FAULT else warn
        name = LEVEL_NAMES[level]
        change = self.alarms.raise_level(
            vehicle.id,
            vehicle.profile,
            kind,
            name,
            t_ns,
            value,
            threshold,
            message.format(threshold=threshold),
        )
        self._emit(change, result)

    def _emit(self, change: AlarmChange | None, result: TickResult | list[AlarmChange]) -> None:
        if change is None:
            return
        if isinstance(result, TickResult):
            result.alarms.append(change)
        else:
            result.append(change)
        if self.events.wants("alarm"):
            self.events.publish(FleetEvent("alarm", change.record.vehicle, change.event))

    # ------------------------------------------------------------------ staleness, liveliness, bursts

    def _unstale(self, vehicle: Vehicle, now_ns: int, result: TickResult) -> None:
        vehicle.stale = False
        self._stale_count -= 1
        self._emit(self.alarms.clear(vehicle.id, "stale", now_ns, "measurements resumed"), result)
        if self.events.wants("vehicle"):
            self.events.publish(FleetEvent("vehicle", vehicle.id, {"event": "resumed"}))

    def _make_stale(self, vehicle: Vehicle, now_ns: int, why: str, changes: list[AlarmChange]) -> None:
        vehicle.stale = True
        self._stale_count += 1
        vehicle.bank.restart(vehicle.slot)
        change = self.alarms.raise_level(vehicle.id, vehicle.profile, "stale", "STALE", now_ns, None, None, why)
        self._emit(change, changes)
        if self.events.wants("vehicle"):
            self.events.publish(FleetEvent("vehicle", vehicle.id, {"event": "stale", "reason": why}))

    def housekeeping(self) -> list[AlarmChange]:
        """Periodic checks: vehicles gone quiet become STALE; reject bursts that ended clear."""
        now_mono = self._monotonic()
        now_ns = self._clock_ns()
        changes: list[AlarmChange] = []
        for vehicle in self.vehicles.values():
            a = vehicle.bank.spec.alarms
            seen = vehicle.last_seen_mono if vehicle.last_seen_mono is not None else self.started_mono
            # a vehicle announced through the API that has not sent anything yet is not stale: it has not started
            announced = vehicle.last_seen_mono is None and vehicle.announced
            if not vehicle.stale and not announced and now_mono - seen > a.stale_after_s:
                self._make_stale(vehicle, now_ns, f"no measurement for {now_mono - seen:.1f} s", changes)
            times = vehicle.reject_times
            while times and now_mono - times[0] > a.reject_burst_window_s:
                times.popleft()
            if not times:
                current = self.alarms.current(vehicle.id, "rejected_inputs")
                if current is not None and current.state == "raised":
                    self._emit(self.alarms.clear(vehicle.id, "rejected_inputs", now_ns), changes)
        return changes

    def liveliness(self, vehicle_id: str, alive: bool) -> list[AlarmChange]:
        """A vehicle's liveliness token appeared or disappeared: a lost token makes it STALE at once."""
        changes: list[AlarmChange] = []
        vehicle = self.vehicles.get(vehicle_id)
        if vehicle is None:
            self._presence[vehicle_id] = alive
            return changes
        vehicle.alive = alive
        if not alive and not vehicle.stale:
            self._make_stale(vehicle, self._clock_ns(), "liveliness token lost", changes)
        return changes

    def acknowledge(self, alarm_id: str, by: str | None = None) -> AlarmChange:
        change = self.alarms.acknowledge(alarm_id, self._clock_ns(), by)
        if self.events.wants("alarm"):
            self.events.publish(FleetEvent("alarm", change.record.vehicle, change.event))
        return change

    # ------------------------------------------------------------------ views

    def vehicles_by_level(self) -> dict[str, dict[str, int]]:
        """Registered vehicles of each profile by level: OK, WARN, FAULT, and STALE (a stale vehicle counts as
        STALE whatever its detectors say). Counted from each bank's level arrays, with a pass over the vehicles
        only while some are stale: a scrape of a large fleet stays cheap on the event loop."""
        out: dict[str, dict[str, int]] = {}
        for name, bank in self.banks.items():
            counts = np.bincount(bank.levels(np.flatnonzero(bank.used)).astype(np.intp), minlength=len(LEVEL_NAMES))
            out[name] = {**dict(zip(LEVEL_NAMES, counts.tolist(), strict=True)), "STALE": 0}
        if self._stale_count:
            for vehicle in self.vehicles.values():
                if vehicle.stale:
                    by_level = out[vehicle.profile]
                    by_level[LEVEL_NAMES[int(vehicle.bank.levels(vehicle.slot))]] -= 1
                    by_level["STALE"] += 1
        return out

    def vehicle_status(self, vehicle: Vehicle) -> dict[str, Any]:
        return self.vehicle_statuses([vehicle])[0]

    def vehicle_statuses(self, vehicles: Sequence[Vehicle]) -> list[dict[str, Any]]:
        """Each vehicle's status document, in order. The per-vehicle arrays of each profile are read once for
        all its vehicles in the list (a few fancy indexings), not once per vehicle and field: GET /vehicles
        lists the whole fleet on the event loop that also runs ingest."""
        now_mono = self._monotonic()
        by_bank: dict[str, list[int]] = {}
        for i, vehicle in enumerate(vehicles):
            by_bank.setdefault(vehicle.bank.name, []).append(i)
        level: list[int] = [0] * len(vehicles)
        sample_counts: list[tuple[int, int, int]] = [(0, 0, 0)] * len(vehicles)
        gain_set: list[str | None] = [None] * len(vehicles)
        grade: list[tuple[float | None, int | None]] = [(None, None)] * len(vehicles)
        unjudged: list[list[str] | None] = [None] * len(vehicles)
        for positions in by_bank.values():
            bank = vehicles[positions[0]].bank
            slots = np.array([vehicles[i].slot for i in positions], dtype=np.intp)
            ranks = bank.levels(slots)
            columns = (bank.accepted[slots].tolist(), bank.estimates[slots].tolist(), bank.published[slots].tolist())
            counts = zip(*columns, strict=True)
            switched = bank.runtime is not None and bank.runtime.switched
            sets = np.where(bank.last_fast[slots], "fast", "quiet").tolist() if switched else [None] * len(positions)
            started = (bank.last_seq[slots] >= 0).tolist()
            for i, rank, count, chosen, seen in zip(positions, ranks.tolist(), counts, sets, started, strict=True):
                level[i], sample_counts[i], gain_set[i] = rank, count, chosen if seen else None
            for i, reasons, seen in zip(positions, _unjudged_because(bank, slots), started, strict=True):
                unjudged[i] = reasons if seen else None
            graded_seq = bank.grade_seq[slots].tolist()
            for i, seq, value in zip(positions, graded_seq, bank.grade_rad[slots].tolist(), strict=True):
                grade[i] = (value, seq) if seq >= 0 else (None, None)
        out = []
        for i, vehicle in enumerate(vehicles):
            counters = dict(vehicle.base_counters)
            accepted, estimates, published = sample_counts[i]
            counters["accepted"] += accepted
            counters["estimates"] += estimates
            counters["published"] += published
            out.append(
                {
                    "id": vehicle.id,
                    "profile": vehicle.profile,
                    "level": "STALE" if vehicle.stale else LEVEL_NAMES[level[i]],
                    "stale": vehicle.stale,
                    "alive": vehicle.alive,
                    "last_seq": vehicle.last_seq if vehicle.last_seq >= 0 else None,
                    "last_seen_ns": vehicle.last_seen_ns,
                    "seconds_since_seen": None
                    if vehicle.last_seen_mono is None
                    else round(now_mono - vehicle.last_seen_mono, 3),
                    "gain_version": vehicle.bank.version,
                    "gain_set": gain_set[i],
                    "payload_kg": vehicle.payload_kg,
                    "grade_rad": grade[i][0],
                    "grade_seq": grade[i][1],
                    "faults_judged": None if unjudged[i] is None else not unjudged[i],
                    "unjudged_because": unjudged[i] or [],
                    "counters": counters,
                    "rejected": dict(vehicle.rejected),
                }
            )
        return out

    def latest_estimate(self, vehicle: Vehicle) -> Estimate | None:
        bank, slot = vehicle.bank, vehicle.slot
        if bank.last_seq[slot] < 0:
            return None
        return Estimate(
            vehicle=vehicle.id,
            seq=int(bank.last_seq[slot]),
            t_ns=int(bank.last_t_ns[slot]),
            in_domain=bool(bank.last_in_domain[slot]),
            gain_version=bank.version or "",
            # the estimate's own level, as its document carried it: STALE is the vehicle's state, not an estimate's
            level=LEVEL_NAMES[int(bank.levels(slot))],
            gain_set=bank.gain_set(slot),
            **bank.named_values(bank.last_values[slot]),
        )

    def estimate_history(self, vehicle: Vehicle, limit: int) -> list[EstimateRow]:
        bank = vehicle.bank
        return [
            EstimateRow(seq=seq, t_ns=t_ns, in_domain=dom, **bank.named_values(values))
            for seq, t_ns, dom, values in bank.history(vehicle.slot, limit)
        ]
