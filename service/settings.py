"""The service's configuration: one :class:`Settings`, built at start-up and passed down.

Every field can be set by an environment variable with the prefix
``AGV_FE_``; nested sections use ``__``, for example ``AGV_FE_HTTP__PORT=9000``
or ``AGV_FE_ZENOH__MODE=client``. The ``agv-fe serve`` flags override them.
docs/service.md ("Settings") lists every setting with its default.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from agv_protocol.wire import DEFAULT_PREFIX, N_BUCKETS, check_vehicle_id
from service.affinity import parse_cpu_list

_ENDPOINT = re.compile(r"^(tcp|udp|quic|tls)/[^:/\s]+:\d{1,5}$")


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class HttpSettings(_Section):
    host: str = Field("127.0.0.1", description="address uvicorn binds to")
    port: Annotated[int, Field(ge=0, le=65535)] = Field(8080, description="HTTP port (0 picks a free one)")
    max_body_bytes: Annotated[int, Field(ge=1024)] = Field(
        1_048_576,
        description="largest request body; a larger one is answered 413 before it is read (by its Content-Length) "
        "or as soon as the bytes read pass it (a chunked body) [bytes]",
    )
    max_calibration_body_bytes: Annotated[int, Field(ge=1024)] = Field(
        67_108_864,
        description="largest body of POST /profiles/{name}/calibration, which carries CSV recordings [bytes]",
    )


class AuthSettings(_Section):
    token: SecretStr | None = Field(
        None,
        description="bearer token required by mutating endpoints; when unset, a random token is created in "
        "DATA_DIR/api-token (mode 0600) and reused",
    )
    open_reads: bool = Field(True, description="GET endpoints answer without a token")


class ZenohSettings(_Section):
    mode: Literal["router", "client"] = Field(
        "router", description="'router': the service is the Zenoh router (listens); 'client': it connects to one"
    )
    endpoint: str = Field(
        "tcp/127.0.0.1:7447", description="where the in-process router listens, or the router a client connects to"
    )
    prefix: str = Field(DEFAULT_PREFIX, description="first chunk of every key expression")
    config_file: Path | None = Field(
        None,
        description="Zenoh JSON5 configuration the session starts from: TLS and mutual TLS, user/password "
        "authentication, a router's access-control list (deploy/zenoh/secure/, docs/deployment.md). Mode and "
        "endpoint stay these settings (a file that sets them too must agree); scouting off and the connect "
        "timeout apply where the file leaves Zenoh's default. Unset: Zenoh's defaults, plain TCP",
    )
    credentials_file: Path | None = Field(
        None,
        description="file whose first line is USER:PASSWORD, Zenoh's user/password authentication "
        "(transport.auth.usrpwd; make certs writes one per identity), kept out of the config file",
    )
    connect_timeout_ms: int = Field(
        10_000, ge=-1, description="client mode: how long open() waits for the router (-1: forever)"
    )
    channel_capacity: Annotated[int, Field(ge=16)] = Field(
        65_536, description="measurements buffered between the Zenoh receive thread and the ingest loop"
    )
    estimate_congestion: Literal["drop", "block"] = Field(
        "drop",
        description="congestion control of estimate puts: 'drop' never lets a slow estimate subscriber stall "
        "ingest; alarms always use 'block'",
    )
    vehicle_estimates: Literal["always", "subscribed"] = Field(
        "subscribed",
        description="'subscribed': a vehicle's estimate goes to its key while a subscriber matches that key (a "
        "matching listener per key, its changes applied before every tick's publication), so that the service "
        "neither encodes nor sends estimates nobody reads; 'always': every estimate goes to its vehicle's key",
    )
    runtime_threads: Annotated[int, Field(ge=0, le=64)] = Field(
        1,
        description="Zenoh's worker threads in `agv-fe serve`: N runs Zenoh's receiving, sending and accepting work on "
        "the N threads of its application runtime (ZENOH_RUNTIME handover); 0 keeps Zenoh's own threads (two "
        "receiving, one each for sending, accepting and the application). One thread measured 0.18 against 0.25-0.29 "
        "cores of Zenoh's threads at 1,000 vehicles (docs/capacity.md). A ZENOH_RUNTIME environment variable of the "
        "operator's own wins; it takes effect before the process opens its first Zenoh session",
    )
    vehicle_publisher: Literal["thread", "process"] = Field(
        "thread",
        description="who puts each vehicle's estimates on its own keys: 'thread', a thread of the service; "
        "'process', a process of its own fed by the replica's fleet stream (service/vehicle_fanout.py): one more "
        "hop, but the puts no longer share the service's interpreter lock with the ingest loop (one more core)",
    )

    @field_validator("endpoint")
    @classmethod
    def _endpoint_form(cls, value: str) -> str:
        if not _ENDPOINT.fullmatch(value):
            raise ValueError(f"expected PROTOCOL/HOST:PORT such as tcp/127.0.0.1:7447, got {value!r}")
        return value


class IngestSettings(_Section):
    unknown_vehicles: Literal["register", "reject"] = Field(
        "register",
        description="a measurement from an unregistered vehicle registers it (default profile) or is rejected",
    )
    default_profile: str = Field("default", description="profile of auto-registered vehicles")
    long_gap_s: Annotated[float, Field(gt=0)] = Field(
        0.5, description="a sequence gap longer than this re-initialises the vehicle's observer [s]"
    )
    seq_jump_slack: Annotated[int, Field(ge=1, le=1_000_000)] = Field(
        100,
        description="a sequence jump is believed when it is at most this many samples beyond twice what the time "
        "stamps allow at the profile's sample period; a larger one is rejected as implausible_seq [samples]",
    )
    estimate_every_n: Annotated[int, Field(ge=1)] = Field(
        1,
        description="publish every Nth estimate of a vehicle (1: every sample); all samples are still observed; "
        "vehicles are spread over the N phases so that each sample tick publishes about 1/N of the fleet",
    )
    history_samples: Annotated[int, Field(ge=1, le=100_000)] = Field(
        500, description="estimates kept per vehicle for GET /vehicles/{id}/estimates"
    )
    tick_interval_s: Annotated[float, Field(gt=0, le=0.1)] = Field(
        0.002,
        description="the ingest loop starts a tick at most this often [s]: what arrived in between is stepped as one "
        "batch. Vehicles with independent clocks send all through the period; without a floor the loop would run a "
        "tick for every few samples and spend its time on per-tick work. 2 ms took 9-13 % less CPU than 1 ms at "
        "1,000 vehicles for 0.5-1.1 ms of median latency (docs/capacity.md)",
    )
    max_batch: Annotated[int, Field(ge=1)] = Field(20_000, description="measurements processed per tick at most")
    housekeeping_interval_s: Annotated[float, Field(gt=0)] = Field(
        0.25, description="period of the stale-vehicle and reject-burst checks [s]"
    )
    gc_freeze: bool = Field(
        True,
        description="once started, move every live object to the garbage collector's permanent generation "
        "(gc.freeze): a full collection then no longer walks the libraries' objects, which stalled ingest "
        "for tens of milliseconds (docs/benchmarks/service_load.md)",
    )


class StorageSettings(_Section):
    busy_timeout_s: Annotated[float, Field(ge=0, le=60)] = Field(
        1.0,
        description="how long one write waits for another process's lock on the database before it counts as "
        "failed and is retried [s]; writes run on the storage writer's thread, never on the event loop",
    )
    retry_initial_s: Annotated[float, Field(gt=0, le=60)] = Field(
        0.05, description="first wait before a failed write is retried; doubled at each failure in a row [s]"
    )
    retry_max_s: Annotated[float, Field(gt=0, le=600)] = Field(2.0, description="longest wait between retries [s]")
    max_pending_writes: Annotated[int, Field(ge=1, le=10_000_000)] = Field(
        100_000,
        description="writes (vehicle registrations, alarm changes, job records...) held in memory while the "
        "database fails; a write beyond it is lost, counted and logged",
    )
    api_write_timeout_s: Annotated[float, Field(gt=0, le=600)] = Field(
        5.0,
        description="how long a mutating request waits for its change to be stored before it answers 503 (the "
        "change then stays applied and queued, stored once the database recovers) [s]",
    )
    shutdown_flush_s: Annotated[float, Field(ge=0, le=600)] = Field(
        3.0, description="how long a shutdown keeps retrying the pending writes before it gives them up [s]"
    )


class DatabaseSettings(_Section):
    url: SecretStr | None = Field(
        None,
        description="PostgreSQL database shared by the replicas, postgresql://USER[:PASSWORD]@HOST[:PORT]/DATABASE "
        "(libpq's URI; its schema is migrated at start). Unset: the embedded SQLite file DATA_DIR/service.sqlite3",
    )

    @field_validator("url")
    @classmethod
    def _postgresql_url(cls, value: SecretStr | None) -> SecretStr | None:
        if value is not None and not value.get_secret_value().startswith(("postgresql://", "postgres://")):
            raise ValueError("expected a PostgreSQL URL, postgresql://USER@HOST:PORT/DATABASE")
        return value


class HealthSettings(_Section):
    heartbeat_timeout_s: Annotated[float, Field(gt=0, le=600)] = Field(
        5.0, description="/ready answers 503 when the ingest loop has not completed an iteration for this long [s]"
    )
    task_restarts: Annotated[int, Field(ge=0, le=100)] = Field(
        3,
        description="a background task (ingest, housekeeping) that raises is restarted up to this many times in a "
        "row (the count resets after a minute without failure); one more failure is fatal",
    )
    fatal_exit_grace_s: Annotated[float, Field(ge=0, le=600)] = Field(
        5.0,
        description="after a fatal background-task failure, /ready answers 503 for this long, then the process "
        "stops and `agv-fe serve` exits with status 4 so that an orchestrator restarts it [s]",
    )


class ShardSettings(_Section):
    replicas: Annotated[int, Field(ge=1, le=N_BUCKETS)] = Field(1, description="number of replicas sharing the fleet")
    index: Annotated[int, Field(ge=0)] = Field(0, description="this replica's index, 0..replicas-1")
    replica_id: str | None = Field(
        None, description="name in the liveliness key (default: replica-INDEX; with bucket leases, HOST-PID)"
    )
    mode: Literal["auto", "static", "leases"] = Field(
        "auto",
        description="'static': this replica serves shard INDEX of REPLICAS; 'leases': the replicas sharing a "
        "PostgreSQL database share the buckets through advisory locks, balanced among the live ones, and take over "
        "a dead replica's; 'auto': leases with a database URL and REPLICAS = 1, static otherwise",
    )
    lease_interval_s: Annotated[float, Field(gt=0, le=60)] = Field(
        0.5,
        description="with bucket leases: how often a replica looks at the live replicas and takes or gives buckets; "
        "a dead replica's buckets are taken within about one interval of its database session ending. With a "
        "shared database in either mode: how often it reads which buckets have no owner [s]",
    )
    unserved_after_s: Annotated[float, Field(gt=0, le=3600)] = Field(
        2.0,
        description="with a shared database: a bucket no replica has held for this long raises an 'unserved' alarm "
        "(level STALE) for each of its vehicles, cleared when the bucket has an owner again; shorter gaps (a "
        "hand-over or a takeover by leases) show only in GET /vehicles and /metrics [s]",
    )

    @model_validator(mode="after")
    def _index_in_range(self) -> ShardSettings:
        if self.index >= self.replicas:
            raise ValueError(f"shard index {self.index} must be below replicas = {self.replicas}")
        if self.replica_id is not None:
            check_vehicle_id(self.replica_id)
        return self

    @property
    def name(self) -> str:
        return self.replica_id or f"replica-{self.index}"


class DashboardSettings(_Section):
    enabled: bool = Field(True, description="serve the web dashboard at / (static files, /ui/stream)")
    fleet_hz: Annotated[float, Field(gt=0, le=10)] = Field(
        2.0, description="fleet view updates per second (changed rows only)"
    )
    push_hz: Annotated[float, Field(gt=0, le=50)] = Field(
        10.0, description="how often new plot points and alarm changes are pushed to browsers"
    )
    plot_hz: Annotated[float, Field(gt=0, le=100)] = Field(
        20.0, description="samples per second kept for the vehicle plots (estimates are decimated to this)"
    )
    history_s: Annotated[float, Field(ge=5, le=600)] = Field(60.0, description="time span of the vehicle plots [s]")
    follow_max: Annotated[int, Field(ge=1, le=10_000)] = Field(
        64,
        description="vehicles whose plot history is kept: those being viewed, then those with latched alarms, "
        "then the most recently viewed",
    )
    ground_truth: bool = Field(
        True,
        description="subscribe to the 'truth' key of the followed vehicles (simulators publish it) and overlay it "
        "on the plots; never used for estimation",
    )


class HistorySettings(_Section):
    enabled: bool = Field(
        True,
        description="keep every published estimate on disk (Parquet, service/history.py) for GET "
        "/vehicles/{id}/estimates?start=&end=",
    )
    retention_h: Annotated[float, Field(gt=0, le=24 * 366)] = Field(
        24.0, description="how long estimates are kept; older files are deleted [h]"
    )
    chunk_s: Annotated[float, Field(ge=1, le=3600)] = Field(
        60.0, description="one file per this much service time: what a crash can lose, and the write period [s]"
    )
    precision: Literal["float64", "float32"] = Field(
        "float64",
        description="the float channels on disk: float64 keeps the published values exactly (12 MB per "
        "vehicle-hour), float32 halves the disk (5.6 MB) at 7 significant digits",
    )
    directory: Path | None = Field(None, description="where the files go (default: DATA_DIR/history)")
    writer: Literal["thread", "process"] = Field(
        "thread",
        description="who keeps the history: 'thread', a thread of the service; 'process', a process of its own "
        "fed by the replica's fleet stream (service/history_process.py): its conversions, its garbage and its "
        "once-a-chunk sort and write leave the service's interpreter",
    )


class Settings(BaseSettings):
    """Everything `agv-fe serve` can be told."""

    model_config = SettingsConfigDict(env_prefix="AGV_FE_", env_nested_delimiter="__", extra="forbid", frozen=True)

    data_dir: Path = Field(
        Path("data"), description="the generated API token and, without a database URL, the SQLite database live here"
    )
    profiles_file: Path | None = Field(
        None, description="JSON or YAML file of initial profiles, used when the database has none"
    )
    synthesis_workers: Annotated[int, Field(ge=1, le=8)] = Field(1, description="processes running LMI designs")
    cpus: str | None = Field(
        None,
        description="the CPUs `agv-fe serve` runs on, a Linux CPU list ('0', '0-1', '0,2'; unset: all it may use): "
        "the ingest loop, Zenoh's threads and the service's own threads on cores of their own, the LMI design "
        "workers and a history process on the others (service/affinity.py). At 1,000 vehicles on their own keys "
        "on a 2-core machine shared with their simulation, one core of its own took the p99 per window from "
        "270-924 ms (falling behind) to 14-39 ms (docs/capacity.md)",
    )
    max_profiles: Annotated[int, Field(ge=1, le=10_000)] = Field(
        64, description="profiles the service runs at most: a PUT of one more is refused (409), not a new bank"
    )
    jobs_kept: Annotated[int, Field(ge=10, le=1_000_000)] = Field(
        500, description="finished design jobs kept (memory and database); the oldest beyond go"
    )
    http: HttpSettings = HttpSettings()
    auth: AuthSettings = AuthSettings()
    zenoh: ZenohSettings = ZenohSettings()
    ingest: IngestSettings = IngestSettings()
    storage: StorageSettings = StorageSettings()
    database: DatabaseSettings = DatabaseSettings()
    health: HealthSettings = HealthSettings()
    shard: ShardSettings = ShardSettings()
    dashboard: DashboardSettings = DashboardSettings()
    history: HistorySettings = HistorySettings()

    @field_validator("cpus")
    @classmethod
    def _cpu_list(cls, value: str | None) -> str | None:
        if value is not None:
            parse_cpu_list(value)  # the form only: which CPUs exist is known where the service starts
        return value

    @property
    def cpu_set(self) -> frozenset[int] | None:
        """The CPUs of ``cpus`` (None: unset)."""
        return None if self.cpus is None else parse_cpu_list(self.cpus)

    @property
    def database_path(self) -> Path:
        """The SQLite file, used when no database URL is set."""
        return self.data_dir / "service.sqlite3"

    @property
    def history_directory(self) -> Path:
        return self.history.directory or self.data_dir / "history"

    @model_validator(mode="after")
    def _leases_need_postgresql(self) -> Settings:
        if self.shard.mode == "leases" and self.database.url is None:
            raise ValueError("shard.mode 'leases' needs a PostgreSQL database (database.url, --database-url)")
        if self.shard.mode == "leases" and self.shard.replicas != 1:
            raise ValueError("shard.mode 'leases' shares every bucket among the live replicas: leave replicas at 1")
        return self

    @property
    def bucket_leases(self) -> bool:
        """Whether this replica's buckets come from leases in the shared database rather than a static shard."""
        mode = self.shard.mode
        return mode == "leases" or (mode == "auto" and self.database.url is not None and self.shard.replicas == 1)

    @property
    def database_url(self) -> str | None:
        return None if self.database.url is None else self.database.url.get_secret_value()
