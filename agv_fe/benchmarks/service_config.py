"""Capacity by configuration: the same fleet against services that differ in one setting, alternated in one run.

A figure from one service on this shared 2-core machine moves by tens of per cent from run to run
(docs/benchmarks/service_load.md, the reading), so the cost of a feature is measured as a comparison made in
one run: each configuration's service in turn, then again in the same order (ABAB...), each holding the
service-load benchmark's target fleet (1,000 vehicles at 100 Hz, every vehicle at its own phase of the period,
an estimate for every sample taken from the fleet stream, congestion control BLOCK) for a warm-up step and a
30 s hold whose p99 is read per 10 s window, exactly as service_load.py measures it.

The default run compares the estimate history on (the default) with it off. ``python -m
agv_fe.benchmarks.service_config --baseline DIR LABEL`` adds the service of another checkout (for example a
``git worktree`` of an earlier commit) as a configuration, to measure a change of the code the same way.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from agv_fe.benchmarks import report_header
from agv_fe.benchmarks.service_load import (
    STEP_S,
    TARGET_HOLD_S,
    TARGET_P99_MS,
    TARGET_VEHICLES,
    _step,
    _sustained,
    serving,
)

#: How many times each configuration's service runs, alternating with the others.
ROUNDS = 2


@dataclass(frozen=True)
class Configuration:
    """A service configuration: its label, the settings it changes (environment variables of ``agv-fe serve``), and
    the checkout whose code it runs (None: this one)."""

    label: str
    env: dict[str, str] = field(default_factory=dict)
    source: Path | None = None


#: The configurations of the default run: the estimate history on (the default) and off.
HISTORY = (
    Configuration("history on (default)"),
    Configuration("history off", {"AGV_FE_HISTORY__ENABLED": "false"}),
)


def measure_one(
    config: Configuration, vehicles: int = TARGET_VEHICLES, hold_s: float = TARGET_HOLD_S
) -> dict[str, Any]:
    """One service of ``config``: a STEP_S step of ``vehicles`` (registers them, warms up), then the hold."""
    env = {"AGV_FE_INGEST__ESTIMATE_EVERY_N": "1", **config.env}
    with serving(env, cwd=config.source) as (endpoint, http, proc, _):
        warm = _step(endpoint, http, proc.pid, vehicles, 1, stream="fleet", arrival="spread")
        hold = _step(endpoint, http, proc.pid, vehicles, 1, hold_s, stream="fleet", arrival="spread")
        # the setting took effect: the history's series exist on /metrics only while it runs
        history = "agv_fe_history_rows_written_total" in http.get("/metrics").text
    return {"configuration": config.label, "warm": warm, "hold": hold, "history": history}


def measure(
    configs: tuple[Configuration, ...],
    rounds: int = ROUNDS,
    vehicles: int = TARGET_VEHICLES,
    hold_s: float = TARGET_HOLD_S,
) -> list[dict[str, Any]]:
    """Every configuration once per round, in order, ``rounds`` times; the runs in the order they were made."""
    runs = []
    for r in range(rounds):
        for config in configs:
            run = measure_one(config, vehicles, hold_s)
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
        "taken from the fleet stream, congestion control BLOCK; generator, receiver and service share the machine's "
        f"two cores. Each configuration's service ran {len(runs) // max(1, len(configs))} times, alternating with "
        f"the others (one round runs each once, in the order below): a {STEP_S:.0f} s step that registers the "
        f"fleet, then a {TARGET_HOLD_S:.0f} s hold whose p99 latency is taken per {STEP_S:.0f} s window "
        "(agv_fe/benchmarks/service_config.py, the steps of service_load.py).\n",
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
        "| round | configuration | estimate history running | warm-up step p99 [ms] | hold: zero loss | hold p50 [ms] "
        "| hold p99 per window [ms] | service CPU [cores] |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in runs:
        h = r["hold"]
        lines.append(
            f"| {r['round']} | {r['configuration']} | {'yes' if r['history'] else 'no'} | {r['warm']['p99_ms']:.2f} "
            f"| {'yes' if h['zero_loss'] else 'no'} "
            f"| {h['p50_ms']:.2f} | {', '.join(f'{x:.2f}' for x in h['p99_windows_ms'])} | {h['service_cpu']:.2f} |"
        )
    lines += ["", "```json", json.dumps(runs, indent=1), "```", ""]
    return "\n".join(lines)


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
    path.write_text(head + EARLIER_RUNS + "\n```json" + data)
    return path


def main(argv: list[str] | None = None) -> int:
    """``--baseline DIR LABEL``: compare this checkout's service with the one of DIR, both with the same ``--env``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--baseline", nargs=2, metavar=("DIR", "LABEL"), required=True)
    parser.add_argument("--label", default="this checkout", help="the label of this checkout's service")
    parser.add_argument("--out", type=Path, required=True, help="the report to write")
    parser.add_argument("--rounds", type=int, default=ROUNDS)
    parser.add_argument(
        "--env", action="append", default=[], metavar="NAME=VALUE", help="a setting for both services (repeatable)"
    )
    args = parser.parse_args(argv)
    source, label = Path(args.baseline[0]).resolve(), args.baseline[1]
    if not (source / "agv_fe").is_dir():
        parser.error(f"{source} is not a checkout of this project (no agv_fe/ in it)")
    bad = [e for e in args.env if "=" not in e or not e.startswith("AGV_FE_")]
    if bad:
        parser.error(f"--env takes AGV_FE_NAME=VALUE, got {', '.join(bad)}")
    env = dict(e.split("=", 1) for e in args.env)
    configs = (Configuration(label, env, source), Configuration(args.label, env))
    runs = measure(configs, args.rounds)
    settings = "".join(f" --env {e}" for e in args.env)
    command = f"python -m agv_fe.benchmarks.service_config --baseline DIR '{label}'{settings} --out {args.out}"
    text = render(f"Service capacity: {label} against {args.label}", configs, runs, TARGET_VEHICLES, command)
    text = text.replace("`make bench` runs every benchmark; ", "").replace(
        "(either rewrites this file)", "(rewrites this file; DIR is a checkout of the baseline, e.g. a `git worktree`)"
    )
    args.out.write_text(text)
    print(f"written {args.out}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
