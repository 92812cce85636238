"""The wire protocol between vehicles and the service: key expressions and encodings.

Both sides import this module; it imports neither zenoh nor FastAPI. The
human-readable specification is docs/protocol.md.

Key expressions (``prefix`` defaults to ``agv``; ``vN`` is the protocol major
version; ``bucket`` is the shard bucket of the vehicle, see :func:`bucket_of`):

    {prefix}/v1/{bucket}/{vehicle_id}/meas      vehicle -> service, binary Measurement, 100 Hz
    {prefix}/v1/{bucket}/{vehicle_id}/truth     simulator -> anyone, JSON GroundTruth (validation only)
    {prefix}/v1/{bucket}/{vehicle_id}/estimate  service -> anyone, JSON Estimate
    {prefix}/v1/{bucket}/{vehicle_id}/alarm     service -> anyone, JSON Alarm
    {prefix}/v1/{bucket}/{vehicle_id}/alive     liveliness token of a vehicle
    {prefix}/v1/service/{replica_id}/alive      liveliness token of a service replica
    {prefix}/v1/service/{replica_id}/ownership  service -> anyone, JSON: buckets a replica gained or gave up

A Measurement is 64 bytes plus the vehicle id; little-endian:

    offset size field
    0      4    magic b"AGVM"
    4      1    format version (1)
    5      1    flags (bit 0: the vehicle restarted its sequence; bit 1: bytes 56-63 carry the road grade; others 0)
    6      2    length L of the vehicle id in bytes (1..64)
    8      8    sequence number, u64, +1 per sample
    16     8    timestamp, i64 nanoseconds since the Unix epoch (vehicle clock)
    24     8    v_x [m/s], f64
    32     8    r [rad/s], f64
    40     8    demanded torque T_d [N m], f64
    48     8    demanded steering delta_d [rad], f64
    56     8    road grade [rad], f64, + uphill, with flag bit 1; zero without it
    64     L    vehicle id, UTF-8
"""

from __future__ import annotations

import functools
import math
import re
import struct
import zlib
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Annotated, Any, Literal, NamedTuple, Self, cast, get_args

import numpy as np
import orjson
from pydantic import BaseModel, ConfigDict, Field, JsonValue, create_model, model_validator

PROTOCOL_VERSION = 1
#: The newest revision of version 1's estimate record this side writes and reads (docs/protocol.md, Versioning):
#: 1 is revision 1.1, the loss-of-effectiveness fields. A document that carries a revision's fields says so in
#: its ``rev`` field; one of revision 1.0 has none.
ESTIMATE_REVISION = 1
DEFAULT_PREFIX = "agv"
#: Number of shard buckets; a vehicle's bucket is fixed by its id (:func:`bucket_of`).
N_BUCKETS = 16

MAGIC = b"AGVM"
_HEADER = struct.Struct("<4sBBHQqdddd8s")
_GRADE = struct.Struct("<d")
MEASUREMENT_HEADER_SIZE = _HEADER.size  # 64
#: The same header as a numpy record, to decode a tick's headers in one ``np.frombuffer``.
MEASUREMENT_HEADER_DTYPE = np.dtype(
    [
        ("magic", "S4"),
        ("version", "u1"),
        ("flags", "u1"),
        ("id_len", "<u2"),
        ("seq", "<u8"),
        ("t_ns", "<i8"),
        ("vx", "<f8"),
        ("r", "<f8"),
        ("torque", "<f8"),
        ("steer", "<f8"),
        ("reserved", "<u8"),
    ]
)
FLAG_SEQUENCE_RESTART = 0x01
#: Bytes 56-63 carry the road grade (f64, rad, + uphill); without this flag they are reserved and zero.
FLAG_ROAD_GRADE = 0x02
#: Every flag bit this version defines; the others, like the reserved bytes of a sample without a grade, must be
#: zero.
KNOWN_FLAGS = FLAG_SEQUENCE_RESTART | FLAG_ROAD_GRADE

VEHICLE_ID_PATTERN = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
BUCKET_PATTERN = re.compile(r"^b[0-9a-f]{2}$")
#: A shard bucket's name in a JSON message.
Bucket = Annotated[str, Field(pattern=BUCKET_PATTERN.pattern)]

Kind = Literal["meas", "truth", "estimate", "estimate.bin", "alarm", "alive", "payload"]
KINDS: tuple[Kind, ...] = get_args(Kind)


class ProtocolError(ValueError):
    """A message or key that does not follow the protocol; the text says what is wrong."""


def check_vehicle_id(vehicle_id: str) -> str:
    """Return ``vehicle_id`` if it is a valid id (1-64 of A-Z a-z 0-9 _ . -), else raise."""
    if not VEHICLE_ID_PATTERN.fullmatch(vehicle_id):  # fullmatch: '$' would let a trailing newline in
        raise ProtocolError(
            f"invalid vehicle id {vehicle_id!r}: use 1 to 64 characters from A-Z, a-z, 0-9, '_', '.', '-'"
        )
    return vehicle_id


def bucket_of(vehicle_id: str, n_buckets: int = N_BUCKETS) -> str:
    """The shard bucket of a vehicle: 'b' + two hex digits of crc32(id) mod n_buckets."""
    return f"b{zlib.crc32(vehicle_id.encode()) % n_buckets:02x}"


def all_buckets(n_buckets: int = N_BUCKETS) -> list[str]:
    return [f"b{k:02x}" for k in range(n_buckets)]


def shard_buckets(replica_index: int, n_replicas: int, n_buckets: int = N_BUCKETS) -> list[str]:
    """Buckets served by replica ``replica_index`` of ``n_replicas`` (round-robin)."""
    if not 0 <= replica_index < n_replicas:
        raise ProtocolError(f"replica index {replica_index} outside 0..{n_replicas - 1}")
    return [f"b{k:02x}" for k in range(n_buckets) if k % n_replicas == replica_index]


def vehicle_key(vehicle_id: str, kind: Kind, prefix: str = DEFAULT_PREFIX, n_buckets: int = N_BUCKETS) -> str:
    """The key expression of one vehicle's stream of ``kind``."""
    check_vehicle_id(vehicle_id)
    return f"{prefix}/v{PROTOCOL_VERSION}/{bucket_of(vehicle_id, n_buckets)}/{vehicle_id}/{kind}"


def bucket_selector(bucket: str, kind: Kind, prefix: str = DEFAULT_PREFIX) -> str:
    """Key expression matching ``kind`` for every vehicle in ``bucket``."""
    return f"{prefix}/v{PROTOCOL_VERSION}/{bucket}/*/{kind}"


def fleet_selector(kind: Kind, prefix: str = DEFAULT_PREFIX) -> str:
    """Key expression matching ``kind`` for every vehicle."""
    return f"{prefix}/v{PROTOCOL_VERSION}/*/*/{kind}"


def service_liveliness_key(replica_id: str, prefix: str = DEFAULT_PREFIX) -> str:
    check_vehicle_id(replica_id)
    return f"{prefix}/v{PROTOCOL_VERSION}/service/{replica_id}/alive"


def service_liveliness_selector(prefix: str = DEFAULT_PREFIX) -> str:
    """Key expression matching the liveliness tokens of every service replica."""
    return f"{prefix}/v{PROTOCOL_VERSION}/service/*/alive"


def fleet_estimates_key(replica_id: str, prefix: str = DEFAULT_PREFIX) -> str:
    """Where a replica publishes each tick's estimates as one :class:`FleetEstimates` message."""
    check_vehicle_id(replica_id)
    return f"{prefix}/v{PROTOCOL_VERSION}/service/{replica_id}/estimates"


def ownership_key(replica_id: str, prefix: str = DEFAULT_PREFIX) -> str:
    """Where a replica announces the buckets it gained or gave up (bucket leases), a JSON object."""
    check_vehicle_id(replica_id)
    return f"{prefix}/v{PROTOCOL_VERSION}/service/{replica_id}/ownership"


def ownership_selector(prefix: str = DEFAULT_PREFIX) -> str:
    """Key expression matching every replica's ownership announcements."""
    return f"{prefix}/v{PROTOCOL_VERSION}/service/*/ownership"


def fleet_estimates_selector(prefix: str = DEFAULT_PREFIX) -> str:
    """Key expression matching the fleet estimate messages of every service replica."""
    return f"{prefix}/v{PROTOCOL_VERSION}/service/*/estimates"


def parse_vehicle_key(key: str) -> tuple[str, Kind]:
    """(vehicle_id, kind) from a vehicle key expression; raise on anything else."""
    parts = key.split("/")
    if (
        len(parts) != 5
        or parts[1] != f"v{PROTOCOL_VERSION}"
        or not BUCKET_PATTERN.fullmatch(parts[2])  # e.g. the service replicas' 'service/<id>/alive'
        or parts[4] not in KINDS
    ):
        raise ProtocolError(f"not a vehicle key of protocol v{PROTOCOL_VERSION}: {key!r}")
    vehicle_id = check_vehicle_id(parts[3])
    return vehicle_id, parts[4]


@dataclass(frozen=True, slots=True)
class Measurement:
    """One 100 Hz sample from a vehicle: y = [v_x, r] and the demanded u_d = [T_d, delta_d]; with
    ``grade_rad`` the road's grade under it (flag bit 1 is then set by :meth:`encode`)."""

    vehicle_id: str
    seq: int
    timestamp_ns: int
    vx_mps: float
    r_radps: float
    torque_nm: float
    steer_rad: float
    flags: int = 0
    grade_rad: float | None = None

    def encode(self) -> bytes:
        vid = check_vehicle_id(self.vehicle_id).encode()
        graded = self.grade_rad is not None
        return (
            _HEADER.pack(
                MAGIC,
                PROTOCOL_VERSION,
                self.flags | FLAG_ROAD_GRADE if graded else self.flags & ~FLAG_ROAD_GRADE,
                len(vid),
                self.seq,
                self.timestamp_ns,
                self.vx_mps,
                self.r_radps,
                self.torque_nm,
                self.steer_rad,
                _GRADE.pack(self.grade_rad) if graded else bytes(8),
            )
            + vid
        )

    @classmethod
    def decode(cls, payload: bytes | bytearray | memoryview) -> Measurement:
        """Parse a payload; raise :class:`ProtocolError` saying what is wrong. Values are not range-checked here."""
        data = bytes(payload)
        if len(data) < MEASUREMENT_HEADER_SIZE:
            raise ProtocolError(f"measurement too short: {len(data)} bytes, need at least {MEASUREMENT_HEADER_SIZE}")
        magic, version, flags, id_len, seq, ts, vx, r, torque, steer, reserved = _HEADER.unpack_from(data)
        if magic != MAGIC:
            raise ProtocolError(f"bad magic {magic!r}, expected {MAGIC!r}")
        if version != PROTOCOL_VERSION:
            raise ProtocolError(
                f"unsupported measurement format version {version}, this side speaks {PROTOCOL_VERSION}"
            )
        if len(data) != MEASUREMENT_HEADER_SIZE + id_len:
            raise ProtocolError(
                f"measurement length {len(data)} does not match its header ({MEASUREMENT_HEADER_SIZE} + {id_len})"
            )
        try:
            vehicle_id = data[MEASUREMENT_HEADER_SIZE:].decode()
        except UnicodeDecodeError as exc:
            raise ProtocolError("vehicle id is not UTF-8") from exc
        check_vehicle_id(vehicle_id)
        grade = _GRADE.unpack(reserved)[0] if flags & FLAG_ROAD_GRADE else None
        return cls(vehicle_id, seq, ts, vx, r, torque, steer, flags, grade)

    def is_finite(self) -> bool:
        values = (self.vx_mps, self.r_radps, self.torque_nm, self.steer_rad)
        return all(math.isfinite(v) for v in values) and (self.grade_rad is None or math.isfinite(self.grade_rad))


class _Json(BaseModel):
    """A JSON message of the protocol: encoded by pydantic, decoded with a :class:`ProtocolError` on bad input."""

    def encode(self) -> bytes:
        return self.model_dump_json().encode()

    @classmethod
    def decode(cls, payload: bytes | bytearray | memoryview) -> Self:
        try:
            return cls.model_validate_json(bytes(payload))
        except ValueError as exc:
            raise ProtocolError(f"invalid {cls.__name__}: {exc}") from exc


class _Message(_Json):
    model_config = ConfigDict(frozen=True, extra="forbid")

    v: Literal[1] = Field(1, description="protocol version")
    vehicle: str = Field(description="vehicle id")


Level = Literal["OK", "WARN", "FAULT", "STALE"]
#: The levels by their code: the code is what :class:`EstimateBatch` carries and the binary estimate writes.
LEVELS: tuple[Level, ...] = ("OK", "WARN", "FAULT", "STALE")
#: The code of each level (its place in :data:`LEVELS`).
LEVEL_CODES: dict[Level, int] = {level: code for code, level in enumerate(LEVELS)}


def level_codes(levels: Iterable[str]) -> np.ndarray:
    """The codes of ``levels`` (names of :data:`LEVELS`) as an int8 array; KeyError names one that is not a level."""
    return np.array([LEVEL_CODES[cast(Level, level)] for level in levels], dtype=np.int8)


#: :data:`LEVELS` as a numpy object array: ``_LEVEL_OBJECTS[codes].tolist()`` names a batch's levels in one call.
_LEVEL_OBJECTS = np.array(LEVELS, dtype=object)
GainSetName = Literal["fast", "quiet"]


# ---------------------------------------------------------------------------------------------- the estimate record
#
# The estimate's fields are defined once, by the classes below: the per-vehicle JSON document (Estimate), the
# fleet stream's column group (FleetEstimateGroup, derived), the REST history row (EstimateRow), the ground
# truth (GroundTruth) and the service's arrays (ESTIMATE_COLUMNS) all take their fields from them. A float
# channel is a field annotated with a Column; adding one to a group adds it to every encoding.


class Column(NamedTuple):
    """Marks a float field of the estimate record as a column: its group and its unit."""

    group: Literal["state", "effectiveness"]
    unit: str


#: The revision of version 1 that added each column group (0: the first).
COLUMN_GROUP_REVISION = {"state": 0, "effectiveness": 1}


class _Sample(BaseModel):
    seq: int = Field(description="sequence number of the measurement this answers")
    t_ns: int = Field(description="timestamp of that measurement [ns]")


class _State(BaseModel):
    """The estimated state and total faults: every estimate carries them."""

    vx: Annotated[float, Column("state", "m/s")] = Field(description="estimated v_x [m/s]")
    vy: Annotated[float, Column("state", "m/s")] = Field(description="estimated v_y [m/s]")
    r: Annotated[float, Column("state", "rad/s")] = Field(description="estimated r [rad/s]")
    torque_fault: Annotated[float, Column("state", "N m")] = Field(description="estimated T_f [N m]")
    steer_fault: Annotated[float, Column("state", "rad")] = Field(description="estimated delta_f [rad]")


class _Effectiveness(BaseModel):
    """The loss-of-effectiveness stage's estimates (docs/math.md section 14): present when the vehicle's profile
    runs the stage, and then the state's torque_fault and steer_fault are the total faults b + (alpha - 1) u."""

    torque_bias: Annotated[float | None, Column("effectiveness", "N m")] = Field(
        None, description="estimated bias b of the drive-torque fault [N m]"
    )
    steer_bias: Annotated[float | None, Column("effectiveness", "rad")] = Field(
        None, description="estimated bias b of the steering fault [rad]"
    )
    torque_alpha: Annotated[float | None, Column("effectiveness", "1")] = Field(
        None, description="estimated effectiveness alpha of the drive torque [-] (1: healthy)"
    )
    steer_alpha: Annotated[float | None, Column("effectiveness", "1")] = Field(
        None, description="estimated effectiveness alpha of the steering actuator [-] (1: healthy)"
    )


class EstimateRow(_Effectiveness, _State, _Sample):
    """One estimate of one vehicle: the measurement it answers and its values (the REST history's row)."""

    in_domain: bool = Field(description="the measured premise lies in the design box")


def _columns(model: type[BaseModel], group: str) -> tuple[str, ...]:
    return tuple(
        name
        for name, info in model.model_fields.items()
        if any(isinstance(m, Column) and m.group == group for m in info.metadata)
    )


#: The float columns every estimate carries, in the order of the service's arrays and the documents.
STATE_COLUMNS = _columns(EstimateRow, "state")
#: The float columns of a profile that runs the loss-of-effectiveness stage, after the state columns.
EFFECTIVENESS_COLUMNS = _columns(EstimateRow, "effectiveness")
#: Every float column of the record, in the order of the service's arrays (:class:`EstimateBatch` ``values``).
ESTIMATE_COLUMNS = STATE_COLUMNS + EFFECTIVENESS_COLUMNS
#: The unit of each float column.
COLUMN_UNITS = {
    name: m.unit for name, info in EstimateRow.model_fields.items() for m in info.metadata if isinstance(m, Column)
}


ESTIMATE_EXAMPLE: dict[str, JsonValue] = {
    "v": 1,
    "vehicle": "truck-7",
    "seq": 1042,
    "t_ns": 1_700_000_010_420_000_000,
    "vx": 10.42,
    "vy": -0.031,
    "r": 0.012,
    "torque_fault": 29.7,
    "steer_fault": 0.0012,
    "in_domain": True,
    "gain_version": "3f9a1c0b7d2e",
    "level": "OK",
}


class Estimate(EstimateRow, _Message):
    """The service's estimate for one measurement (JSON).

    The service writes it with :meth:`EstimateBatch.documents` (the same JSON, faster);
    clients read it with :meth:`Estimate.decode`.
    """

    model_config = ConfigDict(json_schema_extra={"examples": [ESTIMATE_EXAMPLE]})

    gain_version: str = Field(description="version of the gains that produced it")
    level: Level = Field("OK", description="the vehicle's current alarm level")
    rev: Annotated[int, Field(ge=1)] | None = Field(
        None,
        description="the revision of protocol version v whose fields the document carries (1: revision 1.1, the "
        "effectiveness fields); absent: revision 1.0",
    )
    gain_set: GainSetName | None = Field(
        None,
        description="which gain set of a switched design made it, 'fast' or 'quiet' (absent for one set)",
    )

    @classmethod
    def decode(cls, payload: bytes | bytearray | memoryview) -> Self:
        """Read a document; one of a newer revision than this side knows (``rev`` > ESTIMATE_REVISION) is read
        for the fields this side knows, the others (additions of that revision) dropped. At a revision this side
        knows, an unknown field is an error."""
        return super().decode(_known_fields(bytes(payload), cls.model_fields))


#: The fields of an estimate that are one per message of the fleet stream rather than one per estimate.
_GROUP_SCALARS = ("v", "gain_version", "rev")


def revision_of(columns: Iterable[str]) -> int:
    """The revision of version 1 whose fields an estimate of these float ``columns`` carries (0: 1.0)."""
    groups = {m.group for name in columns for m in EstimateRow.model_fields[name].metadata if isinstance(m, Column)}
    return max((COLUMN_GROUP_REVISION[g] for g in groups), default=0)


def _known_fields(payload: bytes, known: Iterable[str]) -> bytes:
    """``payload`` as it is, or, for a JSON object of a newer revision than this side knows (``rev`` above
    :data:`ESTIMATE_REVISION`), without the fields not in ``known``. Malformed JSON is left to the validator."""
    if b'"rev"' not in payload:
        return payload
    try:
        data = orjson.loads(payload)
    except orjson.JSONDecodeError:
        return payload
    rev = data.get("rev") if isinstance(data, dict) else None
    if not isinstance(rev, int) or isinstance(rev, bool) or rev <= ESTIMATE_REVISION:
        return payload
    names = set(known)
    return orjson.dumps({k: v for k, v in data.items() if k in names})


@dataclass
class EstimateBatch:
    """Estimates of one gain version, as columns: what one profile step of the service produced.

    vehicle_ids : n; level_codes : (n,) int8, each row's level as its :data:`LEVEL_CODES` code (the service's
    detectors have them as numbers: a name is made only where a document is written); seq, t_ns : (n,) int64;
    values : (n, len(columns)) float64, the float columns named by ``columns`` (:data:`STATE_COLUMNS` and any
    optional group the profile runs); in_domain : (n,) bool; fast : (n,) bool, the row ran the fast gain set of
    a switched design (None: the gains have one set, and no ``gain_set`` is written). The caller guarantees
    finite floats, valid vehicle ids and a hex gain version, so nothing needs escaping. The columns are written
    as they are into the fleet stream (:func:`encode_fleet_estimates`); the per-vehicle documents are made only
    for the vehicles someone listens to (:meth:`documents`).
    """

    vehicle_ids: list[str]
    seq: np.ndarray
    t_ns: np.ndarray
    values: np.ndarray
    in_domain: np.ndarray
    level_codes: np.ndarray
    gain_version: str
    fast: np.ndarray | None = None
    columns: tuple[str, ...] = STATE_COLUMNS

    def __post_init__(self) -> None:
        codes = np.asarray(self.level_codes)
        if codes.dtype.kind not in "iu" or codes.shape != (len(self.vehicle_ids),):
            raise TypeError(f"level_codes: one integer code of LEVEL_CODES per row, got {codes.dtype} {codes.shape}")
        self.level_codes = codes.astype(np.int8, copy=False)

    def levels(self, rows: Sequence[int] | np.ndarray | slice = slice(None)) -> list[Level]:
        """The level names of ``rows`` (every row by default), in the order asked."""
        return cast(list[Level], _LEVEL_OBJECTS[self.level_codes[rows]].tolist())

    def __len__(self) -> int:
        return len(self.vehicle_ids)

    def documents(self, rows: Sequence[int] | None = None) -> list[bytes]:
        """The :class:`Estimate` document of each row (every row by default), in the order asked.

        One ``orjson.dumps`` call writes them all as an array, which is then cut into documents: the cut
        mark ``},{`` cannot occur inside these strings, and orjson never writes a raw newline. Floats are
        written in their shortest round-trip form.
        """
        pick: Sequence[int] = range(len(self)) if rows is None else rows
        if not len(pick):
            return []
        ids, version = self.vehicle_ids, self.gain_version
        if rows is None:
            seq, t_ns, values, domains, fast = self.seq, self.t_ns, self.values, self.in_domain, self.fast
            levels = self.levels()
        else:
            at = np.asarray(rows, dtype=np.intp)
            seq, t_ns, values, domains = self.seq[at], self.t_ns[at], self.values[at], self.in_domain[at]
            fast = None if self.fast is None else self.fast[at]
            levels = self.levels(at)
        document = _document_builder(self.columns)
        docs = [
            document(ids[i], sq, t, row, dom, version, level)
            for i, sq, t, row, dom, level in zip(
                pick, seq.tolist(), t_ns.tolist(), values.tolist(), domains.tolist(), levels, strict=True
            )
        ]
        if fast is not None:  # a switched design: which of its two gain sets made each estimate
            for doc, on in zip(docs, fast.tolist(), strict=True):
                doc["gain_set"] = "fast" if on else "quiet"
        array = orjson.dumps(docs)
        out = array[1:-1].replace(b"},{", b"}\n{").split(b"\n")
        if len(out) != len(pick):  # a string held the cut mark: only possible if a caller broke the contract
            raise ValueError("an estimate field contains '},{' or a newline")
        return out

    def estimate(self, j: int) -> Estimate:
        """Row j as an :class:`Estimate` (built without validation: the service made the values)."""
        values = dict(zip(self.columns, self.values[j].tolist(), strict=True))
        return Estimate.model_construct(
            vehicle=self.vehicle_ids[j],
            seq=int(self.seq[j]),
            t_ns=int(self.t_ns[j]),
            in_domain=bool(self.in_domain[j]),
            gain_version=self.gain_version,
            level=LEVELS[self.level_codes[j]],
            gain_set=None if self.fast is None else ("fast" if self.fast[j] else "quiet"),
            rev=revision_of(self.columns) or None,
            v=1,
            **values,
        )

    @classmethod
    def from_group(cls, group: dict[str, Any]) -> EstimateBatch:
        """The batch a :class:`FleetEstimateGroup` mapping (:meth:`group`, read back with orjson) was made from:
        the float columns in the group's order, so that :meth:`documents` writes the same documents. The group
        comes from a replica (trusted): a column missing or of the wrong length raises KeyError or ValueError."""
        ids = list(group["vehicle"])
        float_names = set(ESTIMATE_COLUMNS)
        columns = tuple(name for name in group if name in float_names)
        values = np.array([group[name] for name in columns], dtype=np.float64).reshape(len(columns), len(ids)).T
        gain_set = group.get("gain_set")
        return cls(
            ids,
            np.asarray(group["seq"], dtype=np.int64),
            np.asarray(group["t_ns"], dtype=np.int64),
            np.ascontiguousarray(values),
            np.asarray(group["in_domain"], dtype=np.bool_),
            level_codes(group["level"]),
            group["gain_version"],
            None if gain_set is None else np.array([s == "fast" for s in gain_set], dtype=np.bool_),
            columns,
        )

    def group(self) -> dict[str, Any]:
        """The batch as a :class:`FleetEstimateGroup` mapping, numpy columns left as they are for orjson."""
        values = np.ascontiguousarray(self.values.T)
        revision = revision_of(self.columns)
        return (
            {
                "gain_version": self.gain_version,
                **({"rev": revision} if revision else {}),
                "vehicle": self.vehicle_ids,
                "seq": np.ascontiguousarray(self.seq, dtype=np.int64),
                "t_ns": np.ascontiguousarray(self.t_ns, dtype=np.int64),
            }
            | dict(zip(self.columns, values, strict=True))
            | {"in_domain": np.ascontiguousarray(self.in_domain, dtype=np.bool_), "level": self.levels()}
            | ({} if self.fast is None else {"gain_set": ["fast" if on else "quiet" for on in self.fast.tolist()]})
        )


def encode_fleet_estimates(replica_id: str, batches: Iterable[EstimateBatch]) -> bytes:
    """A :class:`FleetEstimates` message: one column group per batch, written by one orjson call.

    The columns go to orjson as numpy arrays (no Python float per value): measured 0.1 us per estimate
    at 1,000 vehicles, against 0.7 us for the array of per-vehicle documents.
    """
    message = {"v": 1, "replica": replica_id, "groups": [b.group() for b in merge_by_gain_version(batches) if len(b)]}
    return orjson.dumps(message, option=orjson.OPT_SERIALIZE_NUMPY)


def merge_by_gain_version(batches: Iterable[EstimateBatch]) -> list[EstimateBatch]:
    """One batch per gain version, in the order the versions first appear: a profile stepped twice in one tick
    (a vehicle with two samples in it) gives two batches of one version, and a message must not carry two
    groups of one version (docs/protocol.md). Each vehicle's rows keep their order."""
    by_version: dict[str, list[EstimateBatch]] = {}
    for batch in batches:
        if len(batch):
            by_version.setdefault(batch.gain_version, []).append(batch)
    return [parts[0] if len(parts) == 1 else _concatenated(parts) for parts in by_version.values()]


#: The arguments of a document builder (:func:`_document_builder`), by the Estimate field each one fills.
_DOCUMENT_ARGUMENTS = ("vehicle", "seq", "t_ns", "in_domain", "gain_version", "level")


@functools.cache
def _document_builder(columns: tuple[str, ...]) -> Callable[..., dict[str, Any]]:
    """A function (vehicle, seq, t_ns, values, in_domain, gain_version, level) -> the :class:`Estimate` document
    as a dict, its keys in the order of the record's fields, for a batch of these float ``columns``.

    Written as one dict display from the record's field names and compiled once per column set: 0.43 us per
    document at 1,000 vehicles, against 0.74 us for ``dict(zip(keys, values))`` (measured on this project's
    2-core machine). ``gain_set`` is added by the caller; a field the record gains that is neither a float
    column nor one of the arguments fails here, at the first batch, rather than go missing from documents.
    """
    items = []
    for name in Estimate.model_fields:
        if name == "v":
            items.append(f"'v': {PROTOCOL_VERSION}")
        elif name in _DOCUMENT_ARGUMENTS:
            items.append(f"{name!r}: {name}")
        elif name in columns:
            items.append(f"{name!r}: values[{columns.index(name)}]")
        elif name == "rev":  # written only by a document that carries a later revision's fields
            if revision_of(columns):
                items.append(f"'rev': {revision_of(columns)}")
        elif name != "gain_set" and name not in ESTIMATE_COLUMNS:
            raise TypeError(f"the estimate field {name!r} has no source in EstimateBatch")
    if not all(name.isidentifier() for name in Estimate.model_fields):
        raise TypeError("estimate field names must be identifiers")
    source = f"lambda {', '.join(_DOCUMENT_ARGUMENTS[:3])}, values, {', '.join(_DOCUMENT_ARGUMENTS[3:])}: "
    return cast(Callable[..., dict[str, Any]], eval(source + "{" + ", ".join(items) + "}", {}))


def _concatenated(parts: Sequence[EstimateBatch]) -> EstimateBatch:
    fast = [p.fast for p in parts]
    if len({p.columns for p in parts}) != 1:
        raise ValueError(f"cannot merge batches of different columns: {sorted({p.columns for p in parts})}")
    return EstimateBatch(
        [vehicle for p in parts for vehicle in p.vehicle_ids],
        np.concatenate([p.seq for p in parts]),
        np.concatenate([p.t_ns for p in parts]),
        np.concatenate([p.values for p in parts]),
        np.concatenate([p.in_domain for p in parts]),
        np.concatenate([p.level_codes for p in parts]),
        parts[0].gain_version,
        None if any(f is None for f in fast) else np.concatenate([f for f in fast if f is not None]),
        parts[0].columns,
    )


def encode_estimate(estimate: Estimate) -> bytes:
    """The JSON of one :class:`Estimate`, as the service writes it (:meth:`EstimateBatch.documents`)."""
    columns = tuple(name for name in ESTIMATE_COLUMNS if getattr(estimate, name) is not None)
    batch = EstimateBatch(
        [estimate.vehicle],
        np.array([estimate.seq], dtype=np.int64),
        np.array([estimate.t_ns], dtype=np.int64),
        np.array([[getattr(estimate, name) for name in columns]], dtype=np.float64),
        np.array([estimate.in_domain]),
        level_codes([estimate.level]),
        estimate.gain_version,
        None if estimate.gain_set is None else np.array([estimate.gain_set == "fast"]),
        columns,
    )
    return batch.documents()[0]


class _FleetGroup(BaseModel):
    """The estimates of one gain version within a :class:`FleetEstimates` message, as columns: element i
    of every list belongs to one estimate, and reads as the :class:`Estimate` of the per-vehicle key.
    The columns are the :class:`Estimate` fields (all but ``v`` and ``gain_version``, which the group
    carries once); optional fields are optional columns."""

    model_config = ConfigDict(extra="forbid")

    gain_version: str = Field(description="version of the gains that produced these estimates")
    rev: Annotated[int, Field(ge=1)] | None = Field(
        None, description="the revision whose columns the group carries, as an Estimate's rev; absent: 1.0"
    )

    @model_validator(mode="after")
    def _same_lengths(self) -> Self:
        lengths = {name: len(column) for name, column in self._columns().items()}
        wrong = {k: n for k, n in lengths.items() if n != lengths["vehicle"]}
        if wrong:
            raise ValueError(f"every column must have {lengths['vehicle']} entries, as 'vehicle' has: {wrong}")
        return self

    def _columns(self) -> dict[str, list[Any]]:
        return {
            name: getattr(self, name)
            for name in type(self).model_fields
            if name not in _GROUP_SCALARS and getattr(self, name) is not None
        }

    def estimates(self) -> list[Estimate]:
        columns = self._columns()
        return [
            Estimate(
                gain_version=self.gain_version,
                rev=self.rev,
                **{name: column[i] for name, column in columns.items()},
            )
            for i in range(len(columns["vehicle"]))
        ]


def _column_type(annotation: Any) -> tuple[Any, bool]:
    """The list type of a column of values of ``annotation``, and whether the column is optional."""
    args = get_args(annotation)
    optional = type(None) in args
    if optional:
        (annotation,) = (a for a in args if a is not type(None))
    return cast(Any, list)[annotation], optional


def _fleet_group_fields() -> dict[str, Any]:
    fields: dict[str, Any] = {}
    for name, info in Estimate.model_fields.items():
        if name in _GROUP_SCALARS:
            continue
        column, optional = _column_type(info.annotation)
        description = "vehicle ids" if name == "vehicle" else info.description
        fields[name] = (
            (column | None, Field(None, description=description))
            if optional and info.default is None
            else (
                column,
                Field(description=description),
            )
        )
    return fields


if TYPE_CHECKING:
    FleetEstimateGroup = _FleetGroup
else:
    FleetEstimateGroup = create_model(
        "FleetEstimateGroup", __base__=_FleetGroup, __doc__=_FleetGroup.__doc__, **_fleet_group_fields()
    )


class FleetEstimates(_Json):
    """Every estimate one service replica published in one ingest tick (JSON, columns), on
    ``{prefix}/v1/service/{replica_id}/estimates``: one message instead of one per vehicle, for
    consumers that follow the whole fleet (docs/protocol.md)."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [
                {
                    "v": 1,
                    "replica": "replica-0",
                    "groups": [
                        {
                            "gain_version": "3f9a1c0b7d2e",
                            "vehicle": ["truck-7", "truck-9"],
                            "seq": [1042, 77],
                            "t_ns": [1_700_000_010_420_000_000, 1_700_000_010_421_000_000],
                            "vx": [10.42, 8.1],
                            "vy": [-0.031, 0.002],
                            "r": [0.012, -0.004],
                            "torque_fault": [29.7, 0.4],
                            "steer_fault": [0.0012, -0.0001],
                            "in_domain": [True, True],
                            "level": ["OK", "OK"],
                        }
                    ],
                }
            ]
        },
    )

    v: Literal[1] = Field(1, description="protocol version")
    replica: str = Field(description="the replica that published it")
    groups: list[FleetEstimateGroup] = Field(description="the tick's estimates, one column group per gain version")

    def estimates(self) -> list[Estimate]:
        """Every estimate of the message, in the order the service made them."""
        return [e for g in self.groups for e in g.estimates()]

    @classmethod
    def decode(cls, payload: bytes | bytearray | memoryview) -> Self:
        """Read a message; a group of a newer revision than this side knows (its ``rev`` above
        ESTIMATE_REVISION) is read for the columns this side knows, as :meth:`Estimate.decode` reads a document."""
        data = bytes(payload)
        if b'"rev"' in data:
            try:
                message = orjson.loads(data)
                groups = message["groups"]
                known = FleetEstimateGroup.model_fields
                message["groups"] = [orjson.loads(_known_fields(orjson.dumps(g), known)) for g in groups]
                data = orjson.dumps(message)
            except (orjson.JSONDecodeError, KeyError, TypeError):
                pass  # left to the validator, which names what is wrong
        return super().decode(data)


class OwnershipChange(_Json):
    """Buckets a service replica took or handed over (bucket leases), on ``{prefix}/v1/service/{replica_id}/ownership``
    (JSON): one message per change, from the replica that made it (docs/deployment.md)."""

    model_config = ConfigDict(
        frozen=True,
        extra="forbid",
        json_schema_extra={
            "examples": [
                {
                    "v": 1,
                    "replica": "host-a-4711",
                    "gained": ["b08", "b09"],
                    "lost": [],
                    "buckets": ["b00", "b01", "b08", "b09"],
                    "vehicles": 6,
                    "t_ns": 1_700_000_012_000_000_000,
                }
            ]
        },
    )

    v: Literal[1] = Field(1, description="protocol version")
    replica: str = Field(description="the replica that took or handed over the buckets")
    gained: list[Bucket] = Field(description="buckets it serves from now on")
    lost: list[Bucket] = Field(description="buckets it no longer serves")
    buckets: list[Bucket] = Field(description="every bucket it serves after the change")
    vehicles: int = Field(ge=0, description="vehicles of the buckets taken over (as registered) or handed over")
    t_ns: int = Field(description="when the change happened [ns since the epoch, service clock]")


class PayloadReport(_Json):
    """What a vehicle carries now, reported by the vehicle itself on its ``payload`` key (JSON, rarely: when the
    load changes). The service models the vehicle with it (docs/math.md 12.5), as after
    ``PUT /vehicles/{id}/payload``; the vehicle id is the key's."""

    model_config = ConfigDict(
        frozen=True, extra="forbid", json_schema_extra={"examples": [{"v": 1, "payload_kg": 120.0}]}
    )

    v: Literal[1] = Field(1, description="protocol version")
    payload_kg: float = Field(ge=0.0, allow_inf_nan=False, description="the load on board [kg]; 0 when unloaded")


AlarmKind = Literal[
    "torque_fault",
    "steer_fault",
    "torque_effectiveness",
    "steer_effectiveness",
    "out_of_domain",
    "stale",
    "unserved",
    "rejected_inputs",
    "sequence_rejected",
]
AlarmState = Literal["raised", "cleared", "acknowledged"]


class Alarm(_Message):
    """An alarm event (JSON): raised, cleared (condition gone) or acknowledged (by an operator).

    ``raised`` is sent when the condition starts and again, with the same id,
    each time its level changes or a latched alarm's condition returns.
    """

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "v": 1,
                    "vehicle": "truck-7",
                    "id": "al-000017",
                    "kind": "torque_fault",
                    "level": "FAULT",
                    "state": "raised",
                    "value": 212.5,
                    "threshold": 200.0,
                    "t_ns": 1_700_000_012_000_000_000,
                    "message": "|T_f| >= 200 N m for 0.5 s",
                }
            ]
        }
    )

    id: str = Field(description="alarm id, stable across its events")
    kind: AlarmKind
    level: Level
    state: AlarmState
    value: float | None = Field(None, description="the quantity that triggered it (fault estimate, reject rate...)")
    threshold: float | None = None
    t_ns: int = Field(description="when the event happened [ns since the epoch, service clock]")
    message: str = ""


class GroundTruth(_State, _Sample, _Message):
    """What a simulator knows and a real vehicle does not: for validation and dashboards (JSON)."""


# ---------------------------------------------------------------------------------------------- binary estimates
#
# A vehicle that closes its loop on its own estimates reads them from its own key. Beside the JSON document on
# ``.../<vehicle>/estimate`` the service writes the same record in a fixed binary layout on
# ``.../<vehicle>/estimate.bin`` (docs/protocol.md, "Estimate (binary, per vehicle)"; include/agv_fe/estimate.h):
# a 40-byte header and the record's float columns in ESTIMATE_COLUMNS order, little-endian. The vehicle is the key's; a
# column the record does not carry (a later revision's, or an optional group the profile does not run) is NaN.
# A service that publishes for 1,000 vehicles at 100 Hz writes a batch of them with one numpy call instead of
# one JSON document each.

#: Key kind of the binary per-vehicle estimate (:func:`vehicle_key` accepts it like the kinds of :data:`KINDS`).
BINARY_ESTIMATE_KIND: Kind = "estimate.bin"
ESTIMATE_BINARY_MAGIC = b"AGVE"
#: The header: magic, protocol version, revision of the record's fields (0: 1.0), flags, level code, the
#: measurement's seq and t_ns, the gain version (ASCII, NUL-padded), the number of float columns that follow, 0.
ESTIMATE_BINARY_HEADER_DTYPE = np.dtype(
    [
        ("magic", "S4"),
        ("version", "u1"),
        ("revision", "u1"),
        ("flags", "u1"),
        ("level", "u1"),
        ("seq", "<u8"),
        ("t_ns", "<i8"),
        ("gain_version", "S12"),
        ("n_columns", "<u2"),
        ("reserved", "<u2"),
    ]
)
ESTIMATE_BINARY_HEADER_SIZE = ESTIMATE_BINARY_HEADER_DTYPE.itemsize  # 40
#: Flags of the binary estimate: the premise was in the design box; the gains have two sets (then the next bit
#: says which made it: set for 'fast', clear for 'quiet').
BINARY_FLAG_IN_DOMAIN = 0x01
BINARY_FLAG_GAIN_SET = 0x02
BINARY_FLAG_FAST = 0x04
_BINARY_KNOWN_FLAGS = BINARY_FLAG_IN_DOMAIN | BINARY_FLAG_GAIN_SET | BINARY_FLAG_FAST
_GAIN_VERSION_BYTES = ESTIMATE_BINARY_HEADER_DTYPE["gain_version"].itemsize


@functools.cache
def estimate_binary_dtype(n_columns: int) -> np.dtype:
    """The numpy layout of a binary estimate with ``n_columns`` float columns: the header, then ``values``."""
    return np.dtype([*ESTIMATE_BINARY_HEADER_DTYPE.descr, ("values", "<f8", (n_columns,))])


def encode_binary_estimates(batch: EstimateBatch, rows: Sequence[int] | None = None) -> list[bytes]:
    """The binary estimate of each row of ``batch`` (every row by default), in the order asked.

    The rows are written into one structured array and cut into records: one numpy pass for the whole batch.
    """
    positions = [ESTIMATE_COLUMNS.index(name) for name in batch.columns]
    n_columns = max(positions, default=-1) + 1
    pick: Sequence[int] = range(len(batch)) if rows is None else rows
    if not len(pick):
        return []
    if len(batch.gain_version) > _GAIN_VERSION_BYTES or not batch.gain_version.isascii():
        raise ValueError(f"gain version {batch.gain_version!r}: at most {_GAIN_VERSION_BYTES} ASCII characters")
    at = slice(None) if rows is None else np.asarray(rows, dtype=np.intp)
    records = np.zeros(len(pick), estimate_binary_dtype(n_columns))
    records["magic"] = ESTIMATE_BINARY_MAGIC
    records["version"] = PROTOCOL_VERSION
    records["revision"] = revision_of(batch.columns)
    flags = batch.in_domain[at].astype(np.uint8)
    if batch.fast is not None:
        flags |= BINARY_FLAG_GAIN_SET | np.where(batch.fast[at], BINARY_FLAG_FAST, 0).astype(np.uint8)
    records["flags"] = flags
    records["level"] = batch.level_codes[at]
    records["seq"] = batch.seq[at]
    records["t_ns"] = batch.t_ns[at]
    records["gain_version"] = batch.gain_version.encode("ascii")
    records["n_columns"] = n_columns
    if positions == list(range(n_columns)):
        records["values"] = batch.values[at]
    else:  # a column group the batch does not carry sits between two it does: NaN there
        values = np.full((len(pick), n_columns), np.nan)
        values[:, positions] = batch.values[at]
        records["values"] = values
    data = records.tobytes()
    size = records.dtype.itemsize
    return [data[i : i + size] for i in range(0, len(data), size)]


def decode_binary_estimate(payload: bytes | bytearray | memoryview, vehicle_id: str) -> Estimate:
    """Read a binary estimate received on ``vehicle_id``'s key; raise :class:`ProtocolError` naming what is wrong.

    A record of a later revision than this side knows is read for the columns it knows; at a revision this side
    knows, more columns than the record has is an error."""
    data = bytes(payload)
    if len(data) < ESTIMATE_BINARY_HEADER_SIZE:
        raise ProtocolError(f"binary estimate: {len(data)} bytes, the header alone is {ESTIMATE_BINARY_HEADER_SIZE}")
    head = np.frombuffer(data, ESTIMATE_BINARY_HEADER_DTYPE, count=1)[0]
    if bytes(head["magic"]) != ESTIMATE_BINARY_MAGIC:
        raise ProtocolError(f"binary estimate: magic {bytes(head['magic'])!r}, expected {ESTIMATE_BINARY_MAGIC!r}")
    version, reserved = int(head["version"]), int(head["reserved"])
    if version != PROTOCOL_VERSION:
        raise ProtocolError(f"binary estimate: protocol version {version}, this side reads {PROTOCOL_VERSION}")
    flags, level, revision = int(head["flags"]), int(head["level"]), int(head["revision"])
    if flags & ~_BINARY_KNOWN_FLAGS or reserved:
        raise ProtocolError(f"binary estimate: reserved bits set (flags {flags:#04x}, reserved {reserved})")
    if level >= len(LEVELS):
        raise ProtocolError(f"binary estimate: unknown level code {level}")
    n_columns = int(head["n_columns"])
    expected = ESTIMATE_BINARY_HEADER_SIZE + 8 * n_columns
    if len(data) != expected:
        raise ProtocolError(f"binary estimate: {len(data)} bytes, {n_columns} columns make {expected}")
    if n_columns > len(ESTIMATE_COLUMNS) and revision <= ESTIMATE_REVISION:
        raise ProtocolError(
            f"binary estimate: {n_columns} columns at revision {revision}, which has {len(ESTIMATE_COLUMNS)}"
        )
    values = np.frombuffer(data, "<f8", count=n_columns, offset=ESTIMATE_BINARY_HEADER_SIZE).tolist()
    fields: dict[str, Any] = {
        name: value for name, value in zip(ESTIMATE_COLUMNS, values, strict=False) if not math.isnan(value)
    }
    if revision and revision <= ESTIMATE_REVISION:
        fields["rev"] = revision
    if flags & BINARY_FLAG_GAIN_SET:
        fields["gain_set"] = "fast" if flags & BINARY_FLAG_FAST else "quiet"
    try:
        gain_version = bytes(head["gain_version"]).rstrip(b"\0").decode("ascii")
        return Estimate.model_validate(
            {
                "v": PROTOCOL_VERSION,
                "vehicle": vehicle_id,
                "seq": int(head["seq"]),
                "t_ns": int(head["t_ns"]),
                "in_domain": bool(flags & BINARY_FLAG_IN_DOMAIN),
                "gain_version": gain_version,
                "level": LEVELS[level],
                **fields,
            }
        )
    except ValueError as exc:  # UnicodeDecodeError and pydantic's ValidationError are ValueErrors
        raise ProtocolError(f"invalid binary estimate: {exc}") from exc
