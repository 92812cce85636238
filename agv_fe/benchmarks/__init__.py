"""Benchmarks behind `make bench`: each writes a markdown report under docs/benchmarks/."""

from __future__ import annotations

import os
import platform
import subprocess
from datetime import UTC, datetime
from importlib import metadata

from synth.params import VehicleParams

#: The reference physical car of the benchmarks and the calibration tests: everything calibration identifies
#: switched on (wheel torque, effective mass, drag, rolling resistance, cornering drag, a 40 ms steering lag).
REFERENCE_CAR = VehicleParams(
    mass_kg=1230.0,
    effective_mass_kg=1290.0,
    wheel_radius_m=0.33,
    yaw_inertia_kgm2=1540.0,
    front_axle_distance_m=0.9,
    rear_axle_distance_m=1.5,
    front_cornering_stiffness_npr=80000.0,
    rear_cornering_stiffness_npr=50000.0,
    longitudinal_drag_coeff=0.4,
    rolling_resistance_n=150.0,
    cornering_drag=True,
    steer_time_constant_s=0.04,
)


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
