"""One vehicle as the fleet engine knows it, and why its samples can be refused."""

from __future__ import annotations

from collections import deque
from typing import Literal, get_args

from agv_protocol.wire import MEASUREMENT_HEADER_SIZE, vehicle_key
from service.fleet.bank import ProfileBank

RejectReason = Literal[
    "malformed",
    "id_mismatch",
    "unknown_vehicle",
    "duplicate",
    "out_of_order",
    "implausible_seq",
    "reserved_bits",
    "non_finite",
    "out_of_range",
    "no_gains",
]
REJECT_REASONS: tuple[RejectReason, ...] = get_args(RejectReason)
#: Rejects that count towards a vehicle's rejected-input burst alarm (duplicates and late samples do not).
BURST_REASONS = frozenset({"malformed", "id_mismatch", "reserved_bits", "non_finite", "out_of_range"})
#: Rejects of samples whose sequence number is not believed; enough in a row raise ``sequence_rejected``.
SEQUENCE_REASONS = frozenset({"out_of_order", "implausible_seq"})


class Vehicle:
    """What the engine knows of one vehicle; its observer state lives in its profile's bank."""

    __slots__ = (
        "alive",
        "announced",
        "bank",
        "base_counters",
        "id",
        "id_bytes",
        "last_seen_mono",
        "last_seen_ns",
        "last_seq",
        "last_seq_t_ns",
        "meas_key",
        "payload_kg",
        "payload_len",
        "pending",
        "registered_t_ns",
        "reject_times",
        "rejected",
        "seq_rejects",
        "slot",
        "stale",
    )

    def __init__(self, vehicle_id: str, bank: ProfileBank, slot: int, prefix: str, registered_t_ns: int) -> None:
        self.id = vehicle_id
        self.bank = bank
        self.slot = slot
        self.meas_key = vehicle_key(vehicle_id, "meas", prefix)
        self.id_bytes = vehicle_id.encode()
        self.payload_len = MEASUREMENT_HEADER_SIZE + len(self.id_bytes)
        self.last_seq = -1
        self.last_seq_t_ns = 0  # the time stamp of the sample at last_seq [ns, vehicle clock]
        self.seq_rejects = 0  # samples refused as late or implausible since the last one accepted in sequence
        self.last_seen_mono: float | None = None
        self.last_seen_ns: int | None = None
        self.registered_t_ns = registered_t_ns
        #: Event counts kept per vehicle; the per-sample counts (accepted, estimates, published) live in
        #: the bank's arrays and are added here when the vehicle moves to another profile.
        self.base_counters = {"accepted": 0, "estimates": 0, "published": 0, "missing": 0, "gaps": 0, "restarts": 0}
        self.rejected: dict[str, int] = dict.fromkeys(REJECT_REASONS, 0)
        self.pending = 0
        self.reject_times: deque[float] = deque()
        self.stale = False
        self.alive: bool | None = None
        #: registered through the API before its first measurement: not STALE until it has sent one
        self.announced = False
        #: what it carries [kg] (PUT /vehicles/{id}/payload): the model's torque follows it
        self.payload_kg = 0.0

    @property
    def profile(self) -> str:
        return self.bank.name

    @property
    def counters(self) -> dict[str, int]:
        """Samples accepted, estimates made and published, samples missing, gaps, restarts (a copy)."""
        out = dict(self.base_counters)
        for name, value in self.bank.sample_counts(self.slot).items():
            out[name] += value
        return out
