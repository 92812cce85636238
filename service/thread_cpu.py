"""CPU time of the service's own threads, by what they do: where a replica's core goes, from /proc.

The process's CPU (``process_cpu_seconds_total``) says how busy a replica is, not what limits it. The service's
Python work runs under one interpreter lock: the event loop (the ingest loop, the HTTP API, housekeeping) cannot
use more than one core however many the machine has, while Zenoh's threads (receiving, routing, sending) run
beside it. ``agv_fe_thread_cpu_seconds_total{thread=...}`` splits the process's CPU into

* ``event_loop``: the thread that runs the event loop (the ingest loop, the HTTP API, housekeeping; the main
  thread of ``agv-fe serve``); near one core it is the limit, and the fleet is split across replicas
  (docs/capacity.md);
* the service's named threads (``storage-writer``, ``estimate-history``, ``vehicle-estimates``, ...);
* ``executor``: the event loop's default thread pool (storage calls of the API, synthesis hand-offs);
* ``zenoh``: Zenoh's runtime threads (``rx-N``, ``tx-N``, ``acc-N``, ``net-N``, ``app-N``, its watchdogs);
* ``python_other`` and ``native_other``: any other thread.

Linux only (``/proc/self/task``); elsewhere :meth:`ThreadCpu.sample` returns nothing. A thread's time is read at
each scrape: a thread that ended keeps the time it had at the last scrape in its group (what it used after that is
not counted), so the series never decrease. A sample reads one small file per thread: about 0.3 ms for 15
threads on the project's 2-core machine, once a scrape.
"""

from __future__ import annotations

import os
import re
import threading
from pathlib import Path

#: Zenoh's runtime threads, by the names its runtimes give them (and its shared-memory watchdogs).
_ZENOH_THREAD = re.compile(r"(rx|tx|acc|net|app)-\d+|Watchdog.*")
#: The service's own thread names (lower case, hyphenated); others go to ``python_other``.
_SERVICE_THREAD = re.compile(r"[a-z][a-z0-9]*(-[a-z0-9]+)*")
_EXECUTOR_THREAD = re.compile(r"asyncio_\d+")


def thread_group(tid: int, loop_tid: int, python_name: str | None, comm: str) -> str:
    """The group a thread's CPU counts in: see the module's docstring. ``loop_tid``: the native id of the event
    loop's thread; ``python_name``: the name of the Python thread with native id ``tid`` (None: not a Python
    thread); ``comm``: the kernel's name for it."""
    if tid == loop_tid:
        return "event_loop"
    if python_name is not None:
        if _EXECUTOR_THREAD.fullmatch(python_name):
            return "executor"
        if _SERVICE_THREAD.fullmatch(python_name):
            return re.sub(r"-\d+$", "", python_name)  # one group for a pool's numbered threads
        return "python_other"
    return "zenoh" if _ZENOH_THREAD.fullmatch(comm) else "native_other"


class ThreadCpu:
    """CPU seconds (user + system) by thread group, never decreasing (see the module's docstring)."""

    def __init__(self, task_dir: Path = Path("/proc/self/task")) -> None:
        self.task_dir = task_dir
        self._ticks_per_s = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
        self._last: dict[int, tuple[str, float]] = {}  # tid -> (group, its CPU at the last sample [s])
        self._ended: dict[str, float] = {}  # group -> CPU of its threads that ended [s]

    def sample(self, loop_tid: int | None = None) -> dict[str, float]:
        """CPU seconds by group now, the ended threads included; {} where /proc has no task directory.
        ``loop_tid``: the native id of the event loop's thread (default: the main thread's)."""
        try:
            tids = [int(name) for name in os.listdir(self.task_dir)]
        except (FileNotFoundError, NotADirectoryError, ValueError):
            return {}
        loop_tid = os.getpid() if loop_tid is None else loop_tid  # the main thread's id is the process's
        python_names = {t.native_id: t.name for t in threading.enumerate() if t.native_id is not None}
        now: dict[int, tuple[str, float]] = {}
        for tid in tids:
            read = self._read(tid)
            if read is None:  # ended since the listing
                continue
            comm, seconds = read
            now[tid] = (thread_group(tid, loop_tid, python_names.get(tid), comm), seconds)
        for tid, (group, seconds) in self._last.items():
            later = now.get(tid)
            # ended, or ended and its id reused by a new thread (less time, or another group)
            if later is None or later[1] < seconds or later[0] != group:
                self._ended[group] = self._ended.get(group, 0.0) + seconds
        self._last = now
        totals = dict(self._ended)
        for group, seconds in now.values():
            totals[group] = totals.get(group, 0.0) + seconds
        return totals

    def _read(self, tid: int) -> tuple[str, float] | None:
        """(comm, user + system CPU [s]) of one thread, None if it has ended."""
        try:
            stat = (self.task_dir / str(tid) / "stat").read_text()
        except (FileNotFoundError, ProcessLookupError):
            return None
        # pid (comm) state ...: comm may hold spaces and parentheses, so split at the last ')'
        comm = stat[stat.index("(") + 1 : stat.rindex(")")]
        fields = stat[stat.rindex(")") + 2 :].split()
        return comm, (int(fields[11]) + int(fields[12])) / self._ticks_per_s
