# mypy: disable-error-code="no-untyped-call"
"""One replica's capacity with PostgreSQL as its storage, next to SQLite's.

The same steps as the service-load benchmark (service_load.py: a generator process publishes N vehicles at
100 Hz, BLOCK, each at its own phase of the period; a receiver takes every estimate from the replica's fleet
stream; 10 s per step), run twice: `agv-fe serve` with its embedded SQLite file, then with
`--database-url` on a throwaway PostgreSQL server (agv_fe/pg_cluster.py; the replica then serves the 16
buckets by leases, alone). Each larger step adds new vehicles, whose registrations are written through the
storage, and between steps the whole fleet goes STALE and comes back (an alarm raised, then cleared, per
vehicle). One run of each, on a machine shared with other work and with the database server on the same two
cores: each figure is one sample.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from agv_fe.benchmarks import report_header
from agv_fe.benchmarks.service_load import _step, _sustained, _verdict, serving
from agv_fe.pg_cluster import PostgresServer

SIZES = (250, 500, 1000)


def _storage_sweep(env: dict[str, str], sizes: tuple[int, ...]) -> list[dict[str, Any]]:
    rows = []
    with serving(env) as (endpoint, http, proc, _):
        for n in sizes:
            row = _step(endpoint, http, proc.pid, n, 1, stream="fleet", arrival="spread")
            rows.append(row)
            print(f"  {n} vehicles: zero loss {row['zero_loss']}, p99 {row['p99_ms']:.2f} ms", flush=True)
            if not _sustained(row):
                break
    return rows


def run(out_dir: Path, sizes: tuple[int, ...] = SIZES) -> Path:
    print(" SQLite", flush=True)
    results = {"sqlite": _storage_sweep({}, sizes)}
    server = PostgresServer().init()
    try:
        print(" PostgreSQL", flush=True)
        results["postgresql"] = _storage_sweep({"AGV_FE_DATABASE__URL": server.database()}, sizes)
    finally:
        server.close()
    return _write(out_dir, results)


def _write(out_dir: Path, results: dict[str, list[dict[str, Any]]]) -> Path:
    lines = [
        report_header("Capacity of one replica: PostgreSQL against SQLite", "storage_capacity").rstrip("\n") + "\n",
        (__doc__ or "").split("\n\n", 1)[1].replace("\n", " ").strip() + "\n",
        "| storage | vehicles | estimates/s | zero loss | latency p50 / p99 [ms] | service CPU | verdict |",
        "|---|---|---|---|---|---|---|",
    ]
    for storage, rows in results.items():
        for r in rows:
            lines.append(
                f"| {storage} | {r['vehicles']:,} | {r['rate_msg_s']:,.0f} | {'yes' if r['zero_loss'] else 'no'} | "
                f"{r['p50_ms']:.2f} / {r['p99_ms']:.2f} | {r['service_cpu']:.2f} | {_verdict(r)} |"
            )
    path = out_dir / "storage_capacity.md"
    path.write_text("\n".join(lines) + "\n")
    (out_dir / "storage_capacity.json").write_text(json.dumps(results, indent=1, default=str) + "\n")
    return path
