"""Capacity by configuration: the same fleet against services that differ in one setting, alternated in one run.

A figure from one service on this shared 2-core machine moves by tens of per cent from run to run
(docs/benchmarks/service_load.md, the reading), so the cost of a feature is measured as a comparison made in
one run: each configuration's service in turn, then again in the reverse order (ABBA...), each holding the
service-load benchmark's target fleet (1,000 vehicles at 100 Hz, every vehicle at its own phase of the period,
an estimate for every sample taken from the fleet stream, congestion control BLOCK) for a warm-up step and a
30 s hold whose p99 is read per 10 s window, exactly as service_load.py measures it.

The default run compares the estimate history on (the default) with it off. ``python -m
agv_fe.benchmarks.service_config --baseline DIR LABEL`` adds the service of another checkout (for example a
``git worktree`` of an earlier commit) as a configuration, to measure a change of the code the same way.

``--configs NAME,...`` runs named configurations (:data:`CONFIGURATIONS`), among them the service with
everything on: the Zenoh link over TLS with mutual TLS, passwords and the access-control list of the bench fleet
(secure_link.py), the estimate history on, and bucket leases on a real PostgreSQL server this benchmark starts
(one replica, no ``--shard``: it holds all 16 buckets by lease). ``--vehicles N`` sets the fleet.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import statistics
import sys
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx

from agv_fe.benchmarks import report_header
from agv_fe.benchmarks.harness import wait_for
from agv_fe.benchmarks.secure_link import (
    FLEET_IDENTITY,
    SecureLink,
    issue_certificates,
    plain_tcp_refused,
    secure_link,
)
from agv_fe.benchmarks.service_load import (
    STEP_S,
    TARGET_HOLD_S,
    TARGET_P99_MS,
    TARGET_VEHICLES,
    THREAD_GROUPS,
    _metric,
    _step,
    _sustained,
    serving,
)
from agv_fe.pg_cluster import PostgresServer
from agv_protocol.wire import N_BUCKETS
from service.affinity import format_cpu_list, parse_cpu_list, set_process_affinity, thread_cpu_lists

#: How many times each configuration's service runs, alternating with the others (ABBA: :func:`measure`).
ROUNDS = 2
#: How long a service with bucket leases may take to hold every bucket [s].
LEASES_S = 60.0


@dataclass(frozen=True)
class Configuration:
    """A service configuration: its label, the settings it changes (environment variables of ``agv-fe serve``), the
    checkout whose code it runs (None: this one), whether its Zenoh link is TLS (secure_link.py; with the ACL of
    the fleet unless ``acl`` is False), and whether it stores on PostgreSQL with bucket leases."""

    label: str
    env: dict[str, str] = field(default_factory=dict)
    source: Path | None = None
    tls: bool = False
    acl: bool = True
    leases: bool = False
    #: what the receiver takes: the fleet stream, or every vehicle's own binary key ("vehicle-bin") or JSON key
    stream: str = "fleet"
    #: the service's CPUs (setting ``cpus``; None: all), the generator and the receiver then on the others
    cpus: str | None = None


_HISTORY_OFF = {"AGV_FE_HISTORY__ENABLED": "false"}
_HISTORY_PROCESS = {"AGV_FE_HISTORY__WRITER": "process"}
_TICK_2MS = {"AGV_FE_INGEST__TICK_INTERVAL_S": "0.002"}  # the default since 2026-11-27
_TICK_1MS = {"AGV_FE_INGEST__TICK_INTERVAL_S": "0.001"}  # the default before
#: The CPU a service of the 'own core' configurations runs on; the generator and the receiver run on the others.
OWN_CORE = "0"
#: The configurations of the default run: the estimate history on (the default) and off.
HISTORY = (
    Configuration("history on (default)"),
    Configuration("history off", _HISTORY_OFF),
)
#: The configurations ``--configs`` names.
CONFIGURATIONS = {
    "plain": Configuration("plain TCP, history on (default)"),
    "history-off": Configuration("plain TCP, history off", _HISTORY_OFF),
    "tls": Configuration("TLS + ACL, history off", _HISTORY_OFF, tls=True),
    "tls-history": Configuration("TLS + ACL, history on", tls=True),
    "tls-history-process": Configuration("TLS + ACL, history in its own process", _HISTORY_PROCESS, tls=True),
    "plain-history-process": Configuration("plain TCP, history in its own process", _HISTORY_PROCESS),
    "plain-tick-2ms": Configuration("plain TCP, history on, a tick at most every 2 ms", _TICK_2MS),
    "tls-history-tick-2ms": Configuration("TLS + ACL, history on, a tick at most every 2 ms", _TICK_2MS, tls=True),
    "plain-tick-1ms": Configuration("plain TCP, history on, a tick at most every 1 ms", _TICK_1MS),
    "tls-history-tick-1ms": Configuration("TLS + ACL, history on, a tick at most every 1 ms", _TICK_1MS, tls=True),
    "tls-history-noacl": Configuration("TLS without ACL, history on", tls=True, acl=False),
    "tls-history-leases": Configuration("TLS + ACL, history on, PostgreSQL leases", tls=True, leases=True),
    "vehicle-bin-thread": Configuration("every vehicle's binary key, put by a thread (default)", stream="vehicle-bin"),
    "vehicle-bin-process": Configuration(
        "every vehicle's binary key, put by a process",
        {"AGV_FE_ZENOH__VEHICLE_PUBLISHER": "process"},
        stream="vehicle-bin",
    ),
    "vehicle-bin-thread-history-off": Configuration(
        "every vehicle's binary key, put by a thread, history off", _HISTORY_OFF, stream="vehicle-bin"
    ),
    "vehicle-bin-history-process": Configuration(
        "every vehicle's binary key, put by a thread, history in its own process",
        _HISTORY_PROCESS,
        stream="vehicle-bin",
    ),
    "vehicle-bin-zenoh-2": Configuration(
        "every vehicle's binary key, put by a thread, Zenoh on two threads",
        {"AGV_FE_ZENOH__RUNTIME_THREADS": "2"},
        stream="vehicle-bin",
    ),
    "vehicle-bin-zenoh-own": Configuration(
        "every vehicle's binary key, put by a thread, Zenoh's own runtimes",
        {"AGV_FE_ZENOH__RUNTIME_THREADS": "0"},
        stream="vehicle-bin",
    ),
    "vehicle-bin-own-core": Configuration(
        f"every vehicle's binary key, the service on CPU {OWN_CORE}", stream="vehicle-bin", cpus=OWN_CORE
    ),
    "vehicle-bin-own-core-history-off": Configuration(
        f"every vehicle's binary key, history off, the service on CPU {OWN_CORE}",
        _HISTORY_OFF,
        stream="vehicle-bin",
        cpus=OWN_CORE,
    ),
    "vehicle-bin-own-core-history-process": Configuration(
        f"every vehicle's binary key, history in its own process, the service on CPU {OWN_CORE}",
        _HISTORY_PROCESS,
        stream="vehicle-bin",
        cpus=OWN_CORE,
    ),
    "plain-own-core": Configuration(f"plain TCP, history on, the service on CPU {OWN_CORE}", cpus=OWN_CORE),
    "tls-history-own-core": Configuration(
        f"TLS + ACL, history on, the service on CPU {OWN_CORE}", tls=True, cpus=OWN_CORE
    ),
    "tls-history-process-own-core": Configuration(
        f"TLS + ACL, history in its own process, the service on CPU {OWN_CORE}",
        _HISTORY_PROCESS,
        tls=True,
        cpus=OWN_CORE,
    ),
    "tls-history-own-core-tick-4ms": Configuration(
        f"TLS + ACL, history on, the service on CPU {OWN_CORE}, a tick at most every 4 ms",
        {"AGV_FE_INGEST__TICK_INTERVAL_S": "0.004"},
        tls=True,
        cpus=OWN_CORE,
    ),
    "vehicle-json-thread": Configuration("every vehicle's JSON key, put by a thread (default)", stream="vehicle"),
    "vehicle-json-process": Configuration(
        "every vehicle's JSON key, put by a process", {"AGV_FE_ZENOH__VEHICLE_PUBLISHER": "process"}, stream="vehicle"
    ),
}
#: Capacity with everything on (issue 28): today's plain service beside TLS, TLS with history, and all three.
EVERYTHING_ON = ("plain", "tls", "tls-history", "tls-history-leases")


@dataclass(frozen=True)
class Shared:
    """What the runs of one measurement share: a scratch directory, the certificates of the TLS runs, and the
    PostgreSQL server of the lease runs (each run gets a fresh database on it)."""

    workdir: Path
    certs: Path | None = None
    postgres: PostgresServer | None = None


@contextlib.contextmanager
def shared_resources(configs: tuple[Configuration, ...]) -> Iterator[Shared]:
    """Certificates if a configuration runs TLS, a PostgreSQL server if one runs leases; removed on the way out."""
    with tempfile.TemporaryDirectory(prefix="agv-fe-bench-") as tmp:
        workdir = Path(tmp)
        certs = issue_certificates(workdir / "certs") if any(c.tls for c in configs) else None
        postgres = PostgresServer().init() if any(c.leases for c in configs) else None
        try:
            yield Shared(workdir, certs, postgres)
        finally:
            if postgres is not None:
                postgres.close()


def _service_env(config: Configuration, vehicles: int, shared: Shared) -> tuple[dict[str, str], SecureLink | None]:
    """The settings of one run of ``config`` (a new TLS endpoint and database each run), and its TLS link."""
    env = {"AGV_FE_INGEST__ESTIMATE_EVERY_N": "1", **config.env}
    if config.cpus is not None:
        env["AGV_FE_CPUS"] = config.cpus
    link = None
    if config.tls:
        if shared.certs is None:
            raise ValueError(f"configuration {config.label!r} runs TLS but no certificates were issued")
        link = secure_link(shared.certs, Path(tempfile.mkdtemp(dir=shared.workdir)), vehicles, acl=config.acl)
        env.update(link.env)
    if config.leases:
        if shared.postgres is None:
            raise ValueError(f"configuration {config.label!r} runs leases but no PostgreSQL server was started")
        env.update({"AGV_FE_DATABASE__URL": shared.postgres.database(), "AGV_FE_SHARD__MODE": "leases"})
    return env, link


@contextlib.contextmanager
def harness_beside(service_cpus: str | None) -> Iterator[None]:
    """With the service on ``service_cpus`` (None: nothing to do), this process and the generator and receiver it
    starts run on the other CPUs (all of them when none is left); its own CPUs come back on the way out. Enter it
    after the service started: the service would otherwise inherit the harness's CPUs."""
    if service_cpus is None:
        yield
        return
    before = frozenset(os.sched_getaffinity(0))
    set_process_affinity((before - parse_cpu_list(service_cpus)) or before)
    try:
        yield
    finally:
        set_process_affinity(before)


def _buckets(http: httpx.Client) -> int:
    return len(http.get("/health").json()["buckets"])


def measure_one(
    config: Configuration, vehicles: int = TARGET_VEHICLES, hold_s: float = TARGET_HOLD_S, shared: Shared | None = None
) -> dict[str, Any]:
    """One service of ``config``: a STEP_S step of ``vehicles`` (registers them, warms up), then the hold.
    ``shared``: from :func:`shared_resources` (default: made for this run alone)."""
    with contextlib.ExitStack() as stack:
        if shared is None:
            shared = stack.enter_context(shared_resources((config,)))
        env, link = _service_env(config, vehicles, shared)
        with serving(env, cwd=config.source) as (endpoint, http, proc, _), harness_beside(config.cpus):
            if config.leases:  # one replica takes every bucket at its first lease rounds
                wait_for(
                    lambda: _buckets(http) == N_BUCKETS, LEASES_S, what=f"the service to lease {N_BUCKETS} buckets"
                )
            clients = link.clients if link is not None else None
            warm = _step(endpoint, http, proc.pid, vehicles, 1, stream=config.stream, arrival="spread", clients=clients)
            hold = _step(endpoint, http, proc.pid, vehicles, 1, hold_s, config.stream, "spread", clients)
            cpus = {"service": thread_cpu_lists(proc.pid), "harness": format_cpu_list(os.sched_getaffinity(0))}
            metrics = http.get("/metrics").text
            buckets = _buckets(http)
            # the link is TLS only: a plain TCP client gets no session (after the steps, which it cannot disturb)
            refused = plain_tcp_refused(endpoint) if link is not None else False
    return {
        "configuration": config.label,
        "warm": warm,
        "hold": hold,
        # the settings took effect: the history's series exist on /metrics only while it runs, the lease
        # gauge only with leases
        "history": "agv_fe_history_rows_written_total" in metrics,
        "endpoint": endpoint,
        "plain_tcp_refused": refused,
        "acl_rules": link.acl_rules if link is not None else 0,
        "leases": _metric(metrics, "agv_fe_lease_connected") == 1,
        "buckets": buckets,
        # the CPU lists the service's threads and this process ran on, read after the hold
        "cpus": cpus,
    }


def measure(
    configs: tuple[Configuration, ...],
    rounds: int = ROUNDS,
    vehicles: int = TARGET_VEHICLES,
    hold_s: float = TARGET_HOLD_S,
) -> list[dict[str, Any]]:
    """Every configuration once per round, ``rounds`` times, in order in the first round and reversed in every
    second one (ABBA), so that coming first or second in a round favours no configuration; the runs in the order
    they were made."""
    with shared_resources(configs) as shared:
        return _alternate(configs, rounds, vehicles, hold_s, shared)


def _alternate(
    configs: tuple[Configuration, ...], rounds: int, vehicles: int, hold_s: float, shared: Shared
) -> list[dict[str, Any]]:
    runs = []
    for r in range(rounds):
        for config in configs if r % 2 == 0 else configs[::-1]:
            run = measure_one(config, vehicles, hold_s, shared)
            run["round"] = r + 1
            hold = run["hold"]
            print(
                f"  round {r + 1}, {config.label}: zero loss {hold['zero_loss']}, p50 {hold['p50_ms']:.2f} ms, "
                f"p99 per window {', '.join(f'{x:.2f}' for x in hold['p99_windows_ms'])} ms, "
                f"service CPU {hold['service_cpu']:.2f}",
                flush=True,
            )
            runs.append(run)
    return runs


def _summary(label: str, runs: list[dict[str, Any]]) -> dict[str, Any]:
    mine = [r for r in runs if r["configuration"] == label]
    windows = [x for r in mine for x in r["hold"]["p99_windows_ms"]]
    return {
        "label": label,
        "runs": len(mine),
        "clean": all(r["hold"]["zero_loss"] and r["hold"]["paced"] and _sustained(r["hold"]) for r in mine),
        "p99_median_ms": statistics.median(windows) if windows else float("nan"),
        "p99_worst_ms": max(windows, default=float("nan")),
        "windows_under_target": sum(1 for x in windows if x < TARGET_P99_MS),
        "windows": len(windows),
        "cpu": statistics.mean(r["hold"]["service_cpu"] for r in mine) if mine else float("nan"),
    }


def render(
    title: str, configs: tuple[Configuration, ...], runs: list[dict[str, Any]], vehicles: int, command: str
) -> str:
    """The report: a summary per configuration with its ratio to the first, then every run in order, then the data."""
    summaries = [_summary(c.label, runs) for c in configs]
    first = summaries[0]
    lines = [
        report_header(title, "service_config").replace(
            "`agv-fe bench --only service_config` this one", f"`{command}` this one"
        ),
        f"{vehicles:,} vehicles at 100 Hz, each at its own phase of the 10 ms period, an estimate for every sample "
        f"taken from {_streams(configs)}, congestion control BLOCK; generator, receiver and service (with the "
        "process that puts the vehicles' estimates, where a configuration has one: its CPU is counted in the "
        "service's) share the machine's two cores. "
        f"Each configuration's service ran {_times(len(runs) // max(1, len(configs)))}, alternating with "
        "the others (one round runs each once, in the order below, reversed in every second round): a "
        f"{STEP_S:.0f} s step that registers the fleet, then a {TARGET_HOLD_S:.0f} s hold whose p99 latency is "
        f"taken per {STEP_S:.0f} s window (agv_fe/benchmarks/service_config.py, the steps of service_load.py).\n",
        *_setup(configs, runs),
        "| configuration | runs | zero loss, keeping up | p99 per window: median / worst [ms] "
        f"| ratio of median p99 to '{first['label']}' | windows under {TARGET_P99_MS:.0f} ms | service CPU [cores] "
        f"| CPU ratio to '{first['label']}' |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for s in summaries:
        lines.append(
            f"| {s['label']} | {s['runs']} | {'yes' if s['clean'] else '**no**'} "
            f"| {s['p99_median_ms']:.2f} / {s['p99_worst_ms']:.2f} | {s['p99_median_ms'] / first['p99_median_ms']:.2f} "
            f"| {s['windows_under_target']} of {s['windows']} | {s['cpu']:.2f} | {s['cpu'] / first['cpu']:.2f} |"
        )
    lines += [
        "",
        "Every run, in the order made:",
        "",
        "| round | configuration | Zenoh link | storage | estimate history running | warm-up step p99 [ms] "
        "| hold: zero loss | hold p50 [ms] | hold p99 per window [ms] | hold: over 10 ms at the tick / at the "
        "vehicle-key puts (the service's histograms) | service CPU [cores] | of which the event loop / Zenoh's "
        "threads [cores] | hold: waiting for a core, service / generator / receiver [s per s] |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in runs:
        h = r["hold"]
        lines.append(
            f"| {r['round']} | {r['configuration']} | {_link(r)} | {_storage(r)} | {'yes' if r['history'] else 'no'} "
            f"| {r['warm']['p99_ms']:.2f} | {'yes' if h['zero_loss'] else 'no'} "
            f"| {h['p50_ms']:.2f} | {', '.join(f'{x:.2f}' for x in h['p99_windows_ms'])} "
            f"| {_share(h.get('over_target_at_tick'))} / {_share(h.get('over_target_on_vehicle_keys'))} "
            f"| {h['service_cpu']:.2f} | {_threads(h)} | {_waits(h)} |"
        )
    lines += ["", "```json", json.dumps(runs, indent=1), "```", ""]
    return "\n".join(lines)


def _streams(configs: tuple[Configuration, ...]) -> str:
    """What the receiver took, in words."""
    names = {
        "fleet": "the fleet stream",
        "vehicle-bin": "every vehicle's own binary key (`.../estimate.bin`, one subscription to all of them)",
        "vehicle": "every vehicle's own JSON key (`.../estimate`, one subscription to all of them)",
    }
    return " or ".join(dict.fromkeys(names[c.stream] for c in configs))


def _share(value: float | None) -> str:
    """A share as a percentage; '-' where nothing was counted (no estimate on a vehicle key, or an older run)."""
    return "-" if value is None else f"{100 * value:.2f} %"


def _threads(step: dict[str, Any]) -> str:
    """The service's event loop and Zenoh's threads, cores ('-': an older run, or a service without the series)."""
    return " / ".join("-" if not step.get(f"{g}_cpu") else f"{step[f'{g}_cpu']:.2f}" for g in THREAD_GROUPS)


def _waits(step: dict[str, Any]) -> str:
    """The time the service, the generator and the receiver waited for a core in a step, per second of it ('-':
    not counted by this kernel, or an older run)."""
    return " / ".join(
        "-" if step.get(f"{who}_waited") is None else f"{step[f'{who}_waited']:.2f}"
        for who in ("service", "generator", "receiver")
    )


def _times(n: int) -> str:
    return "once" if n == 1 else f"{n} times"


def _link(run: dict[str, Any]) -> str:
    """The run's Zenoh link as checked: TCP, or TLS that refused a plain TCP client, with or without the ACL."""
    if not run.get("endpoint", "tcp/").startswith("tls/"):
        return "TCP"
    refused = "plain TCP refused" if run["plain_tcp_refused"] else "**plain TCP let in**"
    acl = f"ACL of {run['acl_rules']:,} rules" if run["acl_rules"] else "no ACL"
    return f"TLS ({refused}), {acl}"


def _storage(run: dict[str, Any]) -> str:
    return f"PostgreSQL, leases, {run['buckets']} buckets" if run.get("leases") else "SQLite"


def _setup(configs: tuple[Configuration, ...], runs: list[dict[str, Any]]) -> list[str]:
    """How the TLS and the lease configurations ran, when the run has any."""
    lines = []
    if any(c.tls for c in configs):
        rules = max((r.get("acl_rules", 0) for r in runs), default=0)
        lines.append(
            "TLS: the service is the Zenoh router, listening on `tls/127.0.0.1:PORT` only, with the router certificate "
            "of `make certs` (a fresh CA in a temporary directory), mutual TLS, user/password and, unless marked "
            f"otherwise, the access-control list `agv-fe zenoh-acl` generates for the fleet ({rules:,} rules): one "
            f"simulator identity, `{FLEET_IDENTITY}`, listed for every vehicle. The generator connects as that "
            "identity, the receiver as the read-only `agv-dashboard`, both with deploy/zenoh/secure/client.json5 "
            "(agv_fe/benchmarks/secure_link.py). Each run checks that a plain TCP client gets no session there.\n"
        )
    pinned = sorted({c.cpus for c in configs if c.cpus is not None})
    if pinned:
        lines.append(
            f"A core of its own: the configurations marked 'the service on CPU N' run the service with setting "
            f"`cpus` = {', '.join(pinned)} (every thread of `agv-fe serve` and the processes it starts on that CPU, "
            "service/affinity.py), and the generator, the receiver and the benchmark itself on the other CPUs for "
            "the run's steps; the other configurations leave every process on every CPU.\n"
        )
    if any(c.leases for c in configs):
        lines.append(
            "Leases: a PostgreSQL server started by the benchmark on the same machine (agv_fe/pg_cluster.py), a fresh "
            "database for each run, `AGV_FE_SHARD__MODE=leases` and no `--shard`: the one replica takes all "
            f"{N_BUCKETS} buckets by lease before the fleet starts, and its lease round (the live replicas counted "
            "in the database) runs every 0.5 s meanwhile.\n"
        )
    return lines


#: The comparison with everything on (issue 28), how to run it, kept in service_config.md until it is measured.
EVERYTHING_ON_SECTION = """## Capacity with everything on: TLS, estimate history, bucket leases

**Measured 2026-11-26 22:34 UTC, commit 7d3daff** ([service_config_everything_on.md](service_config_everything_on.md),
the machine otherwise idle): at 1,500 vehicles, zero loss in every configuration, and **TLS with the fleet's
ACL costs nothing measurable** (history off: p99 median 5.43 ms, worst 8.42, 6 of 6 windows under 10 ms, 0.86
of a core, the same CPU as plain TCP). **The estimate history is what misses the target at 1,500**: with it on,
p99 median 22.6 ms (plain TCP) and 55.9 ms (TLS), worst 210 and 256 ms, 1 and 0 of 6 windows under 10 ms;
with PostgreSQL leases too, 63.0 / 345 ms. At 1,000 vehicles the history's cost was 6.0 against 4.0 ms
(table above). The target (issue 28): 1,500 vehicles on the fleet stream with TLS and the estimate history
on, zero loss and p99 < 10 ms in every 10 s window of the hold: **not met**, nor since (latest, 2026-11-28 on
an Intel Xeon: zero loss, p99 per window median 127.9 ms with every process spread over both cores, 12.6 ms
with the service on a core of its own and windows of 11.1-96.8 ms,
[service_config_own_core_tls_1500.md](service_config_own_core_tls_1500.md)). The comparison alternates today's
plain service with three secured ones, two rounds each, in one run (about 10 minutes; run it with nothing
else on the machine):

```sh
.venv/bin/python -m agv_fe.benchmarks.service_config \\
    --configs plain,tls,tls-history,tls-history-leases --vehicles 1500 \\
    --out docs/benchmarks/service_config_everything_on.md
```

| name | configuration |
|---|---|
| `plain` | today's service: TCP, estimate history on (the default), SQLite |
| `tls` | the Zenoh link over TLS: mutual TLS, user/password, the fleet's access-control list; history off |
| `tls-history` | the same with the history on: the target's configuration |
| `tls-history-leases` | the same on a PostgreSQL server the benchmark starts, bucket leases on (one replica) |

`history-off` (TCP, history off) and `tls-history-noacl` (TLS, history on, no ACL: the ACL's own cost) can be
added to the list; `--rounds N` and `--env AGV_FE_NAME=VALUE` (a setting of every service) work as with
`--baseline`. The target is met when the summary's row `TLS + ACL, history on` reads zero loss and keeping up
"yes" and every window under 10 ms (the lease row: the same with leases on).

With TLS the service is the Zenoh router on `tls/127.0.0.1:PORT` with the router certificate of `make certs`
(issued into a temporary directory); the generator publishes for the whole fleet as one simulator identity
(`bench-fleet-sim`, listed for every vehicle, as `agv-fleet-sim` is in the compose fleet) and the receiver reads
the fleet stream as `agv-dashboard`, both with deploy/zenoh/secure/client.json5
(agv_fe/benchmarks/secure_link.py). The ACL is on: the router's configuration for 1,500 vehicles holds 4,513
rules, and a router opened with it in under a second (a probe while building this; not a capacity figure).
Each TLS run checks that a plain TCP client gets no session at the service's endpoint; the report's run table
says so. `tests/agv_fe/test_bench_service_config.py` runs `tls`, `tls-history` and `tls-history-leases` with
10 vehicles for a few seconds each (every estimate received over TLS; no timing asserted).

"""

#: Earlier runs of the default comparison, kept below the current figures (docs/benchmarks/service_config.md).
EARLIER_RUNS = """## Earlier runs

The history writer's cost was found and cut with this benchmark (2026-11-26, the same machine and fleet; p99
per 10 s window of the holds, two rounds each, history on / off):

* At 7c6f80d, the writer keeping a chunk's batches as Python objects until it wrote the chunk (60 s): on
  6.65, 7.00, **204.70**, 4.53, 4.17, 5.36 ms; off 4.42, 4.21, 4.18, 4.35, 4.56, 4.97 ms; the steps that
  registered the fleet reached p99 515 and 125 ms with the history on, 43 and 3.7 ms off. A minute of
  1,000 vehicles' batches is 60,000 objects holding lists; a full garbage collection visiting them held
  the GIL for about 200 ms (measured alone: a 1 ms ticker thread 189 ms late with the collector on, 5 ms
  with it off).
* At 59c101e, the batches converted into Arrow tables every second, each conversion a numpy call or two
  per batch (30 ms of GIL a second): on 16.58, 12.10, 9.58, 5.06, 7.17, 10.34 ms; off 3.90, 3.91, 4.26,
  3.65, 3.73, 4.18 ms. No stall, but a p99 twice as high.
* Since 5a2410c (batch_table by groups of like batches, one conversion per column, every 0.25 s):
  the table above.
"""


def run(out_dir: Path) -> Path:
    """The default comparison, estimate history on against off; writes service_config.md."""
    runs = measure(HISTORY)
    path = out_dir / "service_config.md"
    text = render(
        "Service capacity by configuration: the estimate history", HISTORY, runs, TARGET_VEHICLES,
        "agv-fe bench --only service_config",
    )  # fmt: skip
    head, data = text.split("```json", 1)
    path.write_text(head + EVERYTHING_ON_SECTION + EARLIER_RUNS + "\n```json" + data)
    return path


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    which = parser.add_mutually_exclusive_group(required=True)
    which.add_argument(
        "--configs",
        metavar="NAME,...",
        help=f"comma-separated configurations, in the order they alternate: {', '.join(CONFIGURATIONS)} "
        f"(everything on, issue 28: {','.join(EVERYTHING_ON)})",
    )
    which.add_argument("--baseline", nargs=2, metavar=("DIR", "LABEL"), help="this checkout against DIR's service")
    parser.add_argument("--label", default="this checkout", help="with --baseline: this checkout's label")
    parser.add_argument(
        "--stream",
        choices=("fleet", "vehicle-bin", "vehicle"),
        default="fleet",
        help="with --baseline: what the receiver takes, the fleet stream or every vehicle's binary or JSON key",
    )
    parser.add_argument(
        "--tls",
        action="store_true",
        help="with --baseline: both services behind the TLS + ACL link of the 'tls' configurations",
    )
    parser.add_argument(
        "--cpus", metavar="LIST", help="with --baseline: both services on these CPUs (setting cpus), the harness beside"
    )
    parser.add_argument("--out", type=Path, required=True, help="the report to write")
    parser.add_argument("--rounds", type=int, default=ROUNDS)
    parser.add_argument("--vehicles", type=int, default=TARGET_VEHICLES, help="the fleet (default %(default)s)")
    parser.add_argument(
        "--env", action="append", default=[], metavar="NAME=VALUE", help="a setting for every service (repeatable)"
    )
    return parser


def _chosen(
    parser: argparse.ArgumentParser, args: argparse.Namespace, env: dict[str, str]
) -> tuple[tuple[Configuration, ...], str, str]:
    """The configurations the command line names, the report's title, and the option that names them."""
    if args.configs is not None:
        names = [n.strip() for n in args.configs.split(",") if n.strip()]
        if not names or any(n not in CONFIGURATIONS for n in names):
            parser.error(f"--configs takes names of {', '.join(CONFIGURATIONS)}, got {args.configs!r}")
        configs = tuple(dataclasses.replace(CONFIGURATIONS[n], env={**CONFIGURATIONS[n].env, **env}) for n in names)
        return (
            configs,
            f"Service capacity by configuration: {'; '.join(c.label for c in configs)}",
            (f"--configs {','.join(names)}"),
        )
    source, label = Path(args.baseline[0]).resolve(), args.baseline[1]
    if not (source / "agv_fe").is_dir():
        parser.error(f"{source} is not a checkout of this project (no agv_fe/ in it)")
    configs = (
        Configuration(label, env, source, stream=args.stream, tls=args.tls, cpus=args.cpus),
        Configuration(args.label, env, stream=args.stream, tls=args.tls, cpus=args.cpus),
    )
    stream = "" if args.stream == "fleet" else f" --stream {args.stream}"
    cpus = "" if args.cpus is None else f" --cpus {args.cpus}"
    options = f"{stream}{' --tls' if args.tls else ''}{cpus} --label '{args.label}'"
    return configs, f"Service capacity: {label} against {args.label}", f"--baseline DIR '{label}'{options}"


def _command(args: argparse.Namespace, which: str) -> str:
    """The command line that makes the report again: what it compares, and every option not at its default."""
    fleet = "" if args.vehicles == TARGET_VEHICLES else f" --vehicles {args.vehicles}"
    rounds = "" if args.rounds == ROUNDS else f" --rounds {args.rounds}"
    settings = "".join(f" --env {e}" for e in args.env)
    return f"python -m agv_fe.benchmarks.service_config {which}{fleet}{rounds}{settings} --out {args.out}"


def main(argv: list[str] | None = None) -> int:
    """``--configs NAME,...``: the named configurations, alternated; ``--baseline DIR LABEL``: this checkout's
    service against the one of DIR. Both with the same ``--env`` settings on top, ``--vehicles`` in the fleet."""
    parser = _parser()
    args = parser.parse_args(argv)
    bad = [e for e in args.env if "=" not in e or not e.startswith("AGV_FE_")]
    if bad:
        parser.error(f"--env takes AGV_FE_NAME=VALUE, got {', '.join(bad)}")
    if args.vehicles < 1 or args.rounds < 1:
        parser.error("--vehicles and --rounds take a positive number")
    env = dict(e.split("=", 1) for e in args.env)
    configs, title, which = _chosen(parser, args, env)
    command = _command(args, which)
    runs = measure(configs, args.rounds, args.vehicles)
    text = render(title, configs, runs, args.vehicles, command)
    note = "(rewrites this file; DIR is a checkout of the baseline, e.g. a `git worktree`)" if args.baseline else ""
    text = text.replace("`make bench` runs every benchmark; ", "").replace(
        "(either rewrites this file)", note or "(rewrites this file)"
    )
    args.out.write_text(text)
    print(f"written {args.out}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
