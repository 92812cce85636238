"""Response and request bodies of the REST API, with OpenAPI examples."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any, Literal, get_type_hints

from pydantic import BaseModel, ConfigDict, Field, JsonValue, create_model

from agv_protocol.wire import Estimate, EstimateRow, Level
from service.calibration import GUST_N
from service.fleet.alarms import AlarmRecord
from service.profiles import ProfileSpec

_COUNTERS_EXAMPLE: dict[str, JsonValue] = {
    "accepted": 12000,
    "estimates": 12000,
    "published": 1200,
    "missing": 3,
    "gaps": 1,
    "restarts": 0,
}
_REJECTED_EXAMPLE: dict[str, JsonValue] = {
    "malformed": 0,
    "id_mismatch": 0,
    "unknown_vehicle": 0,
    "duplicate": 2,
    "out_of_order": 1,
    "implausible_seq": 0,
    "reserved_bits": 0,
    "non_finite": 0,
    "out_of_range": 0,
    "no_gains": 0,
}


class StorageStatus(BaseModel):
    """The storage writer: every database write is queued and applied in order on its own thread."""

    state: Literal["ok", "degraded"] = Field(description="'degraded': the latest write failed and is being retried")
    reason: str | None = Field(None, description="why the latest write failed, while degraded")
    pending_writes: int = Field(description="writes queued for the database")
    failures: int = Field(description="failed write attempts since start")
    lost_writes: int = Field(description="writes given up since start (queue full, or a write that cannot succeed)")
    degraded_for_s: float | None = Field(None, description="how long the storage has been degraded [s]")


class Health(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={"examples": [{"status": "ok", "replica": "replica-0", "buckets": ["b00"], "uptime_s": 12.5}]}
    )

    status: Literal["ok", "failed"] = Field(
        "ok", description="'failed': a background task cannot be kept running and the process is about to exit (503)"
    )
    replica: str
    buckets: list[str]
    uptime_s: float
    storage: StorageStatus | None = Field(None, description="the database writer: healthy or degraded, and why")
    tasks: dict[str, str] = Field(
        default_factory=dict, description="background tasks not running now (ingest, housekeeping), and why"
    )
    ingest_heartbeat_age_s: float | None = Field(None, description="time since the ingest loop's latest iteration [s]")
    router_connected: bool | None = Field(
        None, description="client mode: whether the Zenoh session has a router now (null in router mode)"
    )


class Replicas(BaseModel):
    """The service replicas of the Zenoh network, by their liveliness tokens."""

    model_config = ConfigDict(
        json_schema_extra={"examples": [{"replica": "r0", "replicas": ["r0", "r1"], "lease_replicas": 2}]}
    )

    replica: str = Field(description="the replica that answers")
    replicas: list[str] = Field(description="every replica whose liveliness token is alive now, by name")
    lease_replicas: int | None = Field(
        None, description="with bucket leases: the live replicas the shared database counts (null otherwise)"
    )
    unowned_buckets: list[str] | None = Field(
        None,
        description="with a shared database: the buckets no replica holds now, whose vehicles nobody estimates "
        "(null: not known, without a shared database or while the database is unreachable)",
    )


class MissingGains(BaseModel):
    """Why a profile has no active gains."""

    state: Literal["designing", "failed", "interrupted", "superseded", "succeeded", "no_job"] = Field(
        description="'designing' while its job is queued or runs; else how its latest job ended"
    )
    job: str | None = Field(description="the profile's synthesis job (GET /jobs/{id})")
    error: str | None = Field(None, description="the failed job's error class, such as 'infeasible'")
    reason: str | None = Field(description="'designing' while the job runs, else why the design failed")


class Readiness(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "ready": False,
                    "transport": True,
                    "profiles": {"default": "3f9a1c0b7d2e", "van": None},
                    "missing_gains": {
                        "van": {
                            "state": "failed",
                            "job": "job-5c1d2e3f4a5b",
                            "error": "infeasible",
                            "reason": "The paper's design with exact wind decoupling ... is impossible.",
                        }
                    },
                    "detail": "profile 'van' has no active gains: its design failed (infeasible): The paper's ...",
                }
            ]
        }
    )

    ready: bool = Field(
        description="every profile has active gains, Zenoh is up (with a router, in client mode), the ingest loop "
        "runs, every background task runs and the database accepts writes"
    )
    transport: bool
    profiles: dict[str, str | None] = Field(description="active gain version per profile (null: none yet)")
    missing_gains: dict[str, MissingGains] = Field(
        default_factory=dict, description="every profile without active gains, and why"
    )
    detail: str | None = Field(None, description="why the service is not ready, in words (null when ready)")
    failed_profiles: dict[str, str] = Field(
        default_factory=dict,
        description="stored profiles that could not be loaded at start-up, and why: they do not run (the others "
        "do) until a valid PUT /profiles/{name} replaces them",
    )
    storage: StorageStatus | None = Field(None, description="the database writer (503 while degraded)")
    tasks: dict[str, str] = Field(
        default_factory=dict, description="background tasks not running now, and why (503 while any is down)"
    )
    router_connected: bool | None = Field(
        None, description="client mode: whether the Zenoh session has a router now (503 if not); null in router mode"
    )


class VehicleStatus(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "id": "truck-7",
                    "profile": "default",
                    "level": "OK",
                    "stale": False,
                    "served": True,
                    "alive": True,
                    "last_seq": 12003,
                    "last_seen_ns": 1_700_000_120_030_000_000,
                    "seconds_since_seen": 0.004,
                    "gain_version": "3f9a1c0b7d2e",
                    "gain_set": None,
                    "payload_kg": 0.0,
                    "grade_rad": 0.021,
                    "grade_seq": 12003,
                    "faults_judged": True,
                    "unjudged_because": [],
                    "counters": _COUNTERS_EXAMPLE,
                    "rejected": _REJECTED_EXAMPLE,
                }
            ]
        }
    )

    id: str
    profile: str
    level: Level
    stale: bool
    served: bool = Field(
        True,
        description="false for a vehicle of a bucket no replica serves now (a shared database's replica died): "
        "nobody estimates it, its level is STALE and it has no counters",
    )
    alive: bool | None = Field(description="liveliness token present (null: the vehicle declares none)")
    last_seq: int | None
    last_seen_ns: int | None = Field(description="service clock when the last measurement arrived [ns]")
    seconds_since_seen: float | None
    gain_version: str | None
    gain_set: Literal["fast", "quiet"] | None = Field(
        None,
        description="switched designs: the gain set of the latest estimate (fast after a start or a large "
        "innovation, quiet once settled); null for one gain set or before the first estimate",
    )
    payload_kg: float = Field(
        0.0,
        description="what the vehicle carries [kg] (PUT /vehicles/{id}/payload): its model's drive torque follows "
        "it, so that a load does not read as a torque fault; 0 for the profile's vehicle as calibrated",
    )
    grade_rad: float | None = Field(
        None,
        description="the road grade [rad, + uphill] of the last accepted sample that carried one (measurement flag "
        "bit 1, docs/protocol.md): the model's drive torque takes the weight's pull on it out, so that a hill does "
        "not read as a torque fault; null when no sample has carried one",
    )
    grade_seq: int | None = Field(
        None,
        description="that sample's sequence number: last_seq when the latest sample carried a grade, lower when the "
        "vehicle has stopped sending it (its later samples are modelled on level ground); null when none has",
    )
    faults_judged: bool | None = Field(
        None,
        description="whether the fault alarms judged the latest estimate: false while the observer warms up (after "
        "a start, a restart or an estimate outside the certified domain) or the vehicle drives beyond the grip "
        "limits (docs/protocol.md, alarm rules), where a fault level is held as it was; null before the first "
        "estimate",
    )
    unjudged_because: list[Literal["warm-up", "beyond grip"]] = Field(
        default_factory=list, description="why faults_judged is false; empty when it is true or null"
    )
    counters: dict[str, int] = Field(
        description="accepted samples, estimates computed and published, missing samples, gaps, observer restarts"
    )
    rejected: dict[str, int] = Field(description="rejected or dropped samples by reason")


def _required_fields(record: type[Any], leave_out: set[str]) -> dict[str, Any]:
    """The fields of the dataclass ``record``, but ``leave_out``, as pydantic field definitions: the same names,
    types and order, each required (the answer always carries every one)."""
    hints = get_type_hints(record)
    return {f.name: (hints[f.name], ...) for f in dataclasses.fields(record) if f.name not in leave_out}


if TYPE_CHECKING:
    _AlarmFields = BaseModel
else:
    #: the fields of an alarm as AlarmRecord.to_dict gives them (all but ``extra``, kept in memory only): a field
    #: added to AlarmRecord is in the API too
    _AlarmFields = create_model("_AlarmFields", **_required_fields(AlarmRecord, {"extra"}))

_ALARM_EXAMPLE = AlarmRecord(
    id="al-3c5d0e1f2a4b",
    vehicle="truck-7",
    profile="default",
    kind="torque_fault",
    level="FAULT",
    peak_level="FAULT",
    raised_t_ns=1_700_000_012_000_000_000,
    value=212.5,
    threshold=200.0,
    message="|T_f| >= 200 N m for 0.5 s",
    updated_t_ns=1_700_000_012_000_000_000,
).to_dict()


# an alarm (AlarmRecord, field for field) and whether it is still latched; no docstring: the OpenAPI schema of
# AlarmInfo has no description
class AlarmInfo(_AlarmFields):
    model_config = ConfigDict(json_schema_extra={"examples": [{**_ALARM_EXAMPLE, "latched": True}]})

    latched: bool = Field(description="shown until the condition is cleared and an operator acknowledged it")


class AlarmDetail(AlarmInfo):
    events: list[dict[str, Any]] = Field(description="every published event of this alarm, oldest first")


class VehicleDetail(VehicleStatus):
    latest_estimate: Estimate | None
    alarms: list[AlarmInfo] = Field(description="latched alarms of the vehicle")


class EstimateHistory(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "vehicle": "truck-7",
                    "gain_version": "3f9a1c0b7d2e",
                    "estimates": [
                        {
                            "seq": 12003,
                            "t_ns": 1_700_000_120_030_000_000,
                            "vx": 10.4,
                            "vy": -0.03,
                            "r": 0.01,
                            "torque_fault": 29.8,
                            "steer_fault": 0.001,
                            "in_domain": True,
                        }
                    ],
                }
            ]
        }
    )

    vehicle: str
    gain_version: str | None
    estimates: list[EstimateRow] = Field(description="oldest first")


class PayloadReport(BaseModel):
    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{"payload_kg": 120.0}]})

    payload_kg: float = Field(
        ge=0.0,
        allow_inf_nan=False,
        description="the load the vehicle carries now [kg], at most its profile's vehicle mass (mass_kg); 0 when "
        "unloaded",
    )


class VehicleAssignment(BaseModel):
    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{"profile": "van"}]})

    profile: str = Field(description="name of an existing profile")


class JobInfo(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "id": "job-8d2f00c1a9e3",
                    "profile": "van",
                    "kind": "update",
                    "status": "failed",
                    "spec": {"bounds": {"vx_min_mps": 5.0}},
                    "created_t_ns": 1_700_000_000_000_000_000,
                    "started_t_ns": 1_700_000_000_001_000_000,
                    "finished_t_ns": 1_700_000_004_000_000_000,
                    "duration_s": 3.0,
                    "gain_version": None,
                    "certificate": None,
                    "error": "infeasible",
                    "reason": "The decoupling condition M D = 0 leaves delta_f unobservable at r = 0.00 rad/s ...",
                    "superseded_by": None,
                }
            ]
        }
    )

    id: str
    profile: str
    kind: Literal["initial", "create", "update", "resynthesis"]
    status: Literal["queued", "running", "succeeded", "failed", "superseded", "interrupted"]
    spec: dict[str, Any] = Field(description="the profile spec the job designs for, as given")
    created_t_ns: int
    started_t_ns: int | None
    finished_t_ns: int | None
    duration_s: float | None
    gain_version: str | None = Field(description="the version activated by a succeeded job")
    certificate: dict[str, Any] | None = Field(description="certificate summary of the new gains")
    error: str | None = Field(description="infeasible, unverified, bad_parameters, solver_failed, ...")
    reason: str | None = Field(description="why the design failed, was superseded or interrupted, in words")
    superseded_by: str | None
    resumes: str | None = Field(None, description="the job, interrupted by a restart, whose design this one resumes")


class ProfileInfo(BaseModel):
    name: str
    state: Literal["running", "failed"] = Field(
        "running",
        description="'failed': the stored profile could not be loaded at start-up and does not run (see error); "
        "a valid PUT /profiles/{name} replaces it",
    )
    error: str | None = Field(None, description="why a failed profile could not be loaded (null when running)")
    spec: ProfileSpec | None = Field(description="the profile (null when it failed to load)")
    active_version: str | None
    gain_versions: list[str] = Field(description="every stored gain version, oldest first")
    vehicles: int
    pending_job: str | None = Field(description="id of a queued or running synthesis job")


class ProfileChange(BaseModel):
    """Answer of PUT /profiles/{name}: the profile, and the job if gains must be designed."""

    model_config = ConfigDict(
        json_schema_extra={"examples": [{"profile": "van", "job": "job-8d2f00c1a9e3", "applied": False}]}
    )

    profile: str
    job: str | None = Field(description="the synthesis job to poll at GET /jobs/{id}; null if applied at once")
    applied: bool = Field(description="true when only thresholds or limits changed and they apply already")


class GainsInfo(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "format": "agv-fe-gains/1",
                    "profile": "default",
                    "version": "3f9a1c0b7d2e",
                    "params": {"mass_kg": 1481.0},
                    "bounds": {"vx_min_mps": 5.0, "vx_max_mps": 30.0},
                    "options": {"design": "paper", "fault_order": 3},
                    "certificate": {"verified": True, "decay_rate": 0.9412, "spectral_radius_max": 0.9397},
                    "matrices": None,
                }
            ]
        }
    )

    format: str = Field(
        description="gains document format; with ?matrices=true the answer loads with "
        "synth.gains.ObserverGains.from_dict"
    )
    profile: str
    version: str
    params: dict[str, Any]
    bounds: dict[str, Any]
    options: dict[str, Any]
    certificate: dict[str, Any] = Field(
        description="certificate: decay rate, spectral radius, solver, timings (per-LMI lists with ?matrices=true)"
    )
    matrices: dict[str, Any] | None = Field(description="N, L, M, E, P, R, T when ?matrices=true")


class Acknowledgement(BaseModel):
    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [{"by": "operator-ana", "note": "seen"}]})

    by: str | None = Field(None, max_length=100, description="who acknowledges (free text)")
    note: str | None = Field(None, max_length=500)


class RecordingUpload(BaseModel):
    """One recording in the replay CSV format (header t, vx, r, torque, steer; a row every 10 ms)."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field("recording.csv", max_length=200, description="shown in messages")
    csv: str = Field(min_length=1, max_length=16_000_000, description="the CSV text, header first")
    payload_kg: float = Field(
        0.0,
        ge=0.0,
        allow_inf_nan=False,
        description="the load the vehicle carried through this recording [kg], at most the base's mass_kg: the "
        "calibration identifies the vehicle without it (0: recorded as the profile's vehicle drives)",
    )


class CalibrationRequest(BaseModel):
    """The body of ``POST /profiles/{name}/calibration``: healthy recordings and what the data sheet gives."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [
                {
                    "base": {
                        "params": {
                            "mass_kg": 1226.0,
                            "front_axle_distance_m": 0.88,
                            "rear_axle_distance_m": 1.51,
                            "wheel_radius_m": 0.344,
                            "yaw_inertia_kgm2": 1539.0,
                        }
                    },
                    "recordings": [
                        {"name": "drive-1.csv", "csv": "t,vx,r,torque,steer\n0.00,15.02,0.001,120.0,0.002\n"}
                    ],
                    "false_alarms_per_1000_h": 1.0,
                }
            ]
        },
    )

    base: dict[str, JsonValue] | None = Field(
        None,
        description="{'params': {...}, 'design': {...}, 'alarms': {...}}: what is known (params.mass_kg, "
        "front_axle_distance_m, rear_axle_distance_m, wheel_radius_m at least); omitted: the profile's own "
        "parameters, design options and alarm settings",
    )
    recordings: list[RecordingUpload] = Field(min_length=1, max_length=16)
    false_alarms_per_1000_h: float = Field(1.0, gt=0, le=1e6, description="the thresholds' false-alarm rate")
    nominal_torque_nm: float | None = Field(
        None, gt=0, description="the drive torque a 10 % torque fault is measured against [N m]"
    )
    gust_n: float = Field(
        GUST_N,
        ge=0,
        le=1e5,
        description="the lateral wind gust [N], held 2 s, the vehicle rides through without a steering alarm "
        "(0: no gust floor on the thresholds)",
    )
    effectiveness: bool = Field(
        False,
        description="enable the loss-of-effectiveness stage in the proposed profile and set the fault thresholds "
        "from its total faults on the recordings",
    )


class CalibrationProposal(BaseModel):
    """A calibrated profile, not applied: ``PUT /profiles/{name}`` with ``profile`` applies it."""

    profile_name: str
    profile: ProfileSpec
    report: dict[str, JsonValue] = Field(
        description="parameters with 95 % intervals, sensor noise, fit residuals, thresholds, warnings"
    )


class HTTPError(BaseModel):
    """An error answered in one sentence."""

    detail: str
