"""Benchmarks behind `make bench`: each writes a markdown report under docs/benchmarks/."""

from __future__ import annotations

import os
import platform
import subprocess
from datetime import UTC, datetime
from importlib import metadata


def machine_description() -> str:
    """One line about where the figures were measured."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as handle:
            for line in handle:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    versions = ", ".join(f"{p} {metadata.version(p)}" for p in ("numpy", "cvxpy", "clarabel"))
    return f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, {versions}"


def report_header(title: str, benchmark: str) -> str:
    """Title, where and when it was measured, and the commands that rewrite the report."""
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=False
        ).stdout.strip()
    except OSError:
        commit = ""
    when = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    return (
        f"# {title}\n\n"
        f"Measured {when} on {machine_description()}"
        f"{f', commit {commit}' if commit else ''}.\n\n"
        f"Command: `make bench` runs every benchmark; `agv-fe bench --only {benchmark}` this one "
        "(either rewrites this file).\n\n"
    )
