"""The CPUs the service runs on (setting ``cpus``): its hot path on cores of its own, its designs on the others.

On a machine the service shares (with other services, or with a benchmark's 1,000 simulated vehicles), the
kernel spreads its threads over every core. Each sample then crosses cores between Zenoh's thread, the event loop
and the thread that puts the vehicles' estimates, and each of them waits for whichever core frees first: at
1,000 vehicles on their own keys on the project's 2-core machine the p99 per 10 s window was 270-924 ms (falling
behind) with the service's threads spread and 14-39 ms with them on one core of their own, the generator and
receiver on the other (docs/capacity.md, "A core of its own").

``cpus`` takes a Linux CPU list (``0``, ``0-3``, ``0,2``). At start ``agv-fe serve`` moves every thread it has to
those CPUs (:func:`pin_process`); the threads and processes it starts later inherit them (the vehicle estimates'
process), except its background work, which runs on the CPUs it may use that the setting leaves out
(:func:`background_cpus`; all of them when it leaves none): the LMI design workers (a design takes a core for a
second) and the estimate history's process (its conversions and its once-a-chunk sort and write), neither of
which any estimate waits for. Linux only.
"""

from __future__ import annotations

import contextlib
import os
import re
from collections.abc import Iterable
from pathlib import Path

_RANGE = re.compile(r"(\d+)(?:-(\d+))?")
#: What the process could run on before :func:`pin_process` moved it (None: it was not moved).
_before_pin: frozenset[int] | None = None
_pinned: frozenset[int] | None = None


def parse_cpu_list(text: str) -> frozenset[int]:
    """The CPUs of a Linux CPU list (``0``, ``0-3``, ``0,2-3``); raise ValueError naming the bad part."""
    cpus: set[int] = set()
    for part in text.split(","):
        match = _RANGE.fullmatch(part.strip())
        if match is None:
            raise ValueError(f"CPU list {text!r}: {part.strip()!r} is not a CPU number or a range like 0-3")
        first = int(match.group(1))
        last = first if match.group(2) is None else int(match.group(2))
        if last < first:
            raise ValueError(f"CPU list {text!r}: the range {part.strip()!r} ends before it starts")
        cpus.update(range(first, last + 1))
    return frozenset(cpus)


def format_cpu_list(cpus: Iterable[int]) -> str:
    """The Linux CPU list of ``cpus``, ranges joined: ``{0, 1, 2, 5}`` is ``0-2,5``."""
    parts: list[str] = []
    ordered = sorted(set(cpus))
    start = 0
    for i, cpu in enumerate(ordered):
        if i + 1 == len(ordered) or ordered[i + 1] != cpu + 1:
            first = ordered[start]
            parts.append(str(first) if first == cpu else f"{first}-{cpu}")
            start = i + 1
    return ",".join(parts)


def set_process_affinity(cpus: frozenset[int], pid: int | None = None) -> None:
    """Move every thread of process ``pid`` (None: this one) to ``cpus`` (the kernel's affinity is per thread: a
    process's existing threads, numpy's BLAS pool among them, keep theirs otherwise; the threads they start later
    inherit it); threads that end meanwhile are skipped."""
    if pid is None:
        os.sched_setaffinity(0, cpus)
    try:
        tasks = list(Path(f"/proc/{'self' if pid is None else pid}/task").iterdir())
    except FileNotFoundError:  # the process ended: whoever watches it sees that
        return
    for entry in tasks:
        try:
            os.sched_setaffinity(int(entry.name), cpus)
        except ProcessLookupError:  # the thread ended since the listing
            continue


def pin_process(cpus: frozenset[int]) -> None:
    """Run this process (every thread it has and will start) on ``cpus``; remember what it could run on before,
    for :func:`background_cpus`. Raise ValueError naming the CPUs when one is not among those it may use."""
    global _before_pin, _pinned
    allowed = frozenset(os.sched_getaffinity(0))
    if not cpus or not cpus <= allowed:
        missing = format_cpu_list(cpus - allowed) or "none given"
        raise ValueError(f"CPUs {missing}: this process may run on CPUs {format_cpu_list(allowed)} only")
    set_process_affinity(cpus)
    _before_pin, _pinned = allowed, cpus


def background_cpus() -> frozenset[int] | None:
    """The CPUs for background work (the LMI design workers, a history process): those the process could use
    before :func:`pin_process` that the pin left out, or all of them when it left none; None when it was not
    pinned."""
    if _before_pin is None or _pinned is None:
        return None
    return (_before_pin - _pinned) or _before_pin


def thread_cpu_lists(pid: int) -> list[str]:
    """The CPU lists (Linux's Cpus_allowed_list) the threads of process ``pid`` may run on, each once, sorted."""
    lists = set()
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(FileNotFoundError, ProcessLookupError, StopIteration):
            status = (task / "status").read_text().splitlines()
            lists.add(next(line.split(":")[1].strip() for line in status if line.startswith("Cpus_allowed_list")))
    return sorted(lists)
