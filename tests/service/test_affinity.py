"""The CPUs the service runs on (service/affinity.py, setting ``cpus``): the CPU list, the pin of every thread, the
design workers on the CPUs the pin leaves. The pins run in a child process: the test process keeps its CPUs."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from pydantic import ValidationError

from service.affinity import format_cpu_list, parse_cpu_list, pin_process, set_process_affinity
from service.settings import Settings

LINUX = pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs /proc (Linux)")


@pytest.mark.parametrize(
    ("text", "cpus", "canonical"),
    [("0", {0}, "0"), ("0-2,5", {0, 1, 2, 5}, "0-2,5"), (" 3 , 1-2 ", {1, 2, 3}, "1-3"), ("4-4,4", {4}, "4")],
)
def test_a_cpu_list_reads_as_linux_writes_it(text, cpus, canonical):
    assert parse_cpu_list(text) == frozenset(cpus)
    assert format_cpu_list(cpus) == canonical
    assert parse_cpu_list(format_cpu_list(cpus)) == frozenset(cpus)


@pytest.mark.parametrize(
    ("text", "names"),
    [("a", "'a'"), ("3-1", "ends before it starts"), ("", "''"), ("0,,1", "''"), ("-1", "'-1'"), ("0-", "'0-'")],
)
def test_a_bad_cpu_list_is_an_error_that_names_the_part(text, names):
    with pytest.raises(ValueError, match="CPU list") as caught:
        parse_cpu_list(text)
    assert names in str(caught.value)


def test_the_setting_takes_a_cpu_list_and_refuses_anything_else():
    assert Settings(cpus="0-1").cpu_set == frozenset({0, 1})
    assert Settings().cpu_set is None
    with pytest.raises(ValidationError, match="cpus"):
        Settings(cpus="first")


@LINUX
def test_a_cpu_the_process_may_not_use_is_refused_before_anything_moves():
    before = os.sched_getaffinity(0)
    outside = max(before) + 1000
    with pytest.raises(ValueError, match=f"CPUs {outside}: this process may run on CPUs"):
        pin_process(frozenset({outside}))
    with pytest.raises(ValueError, match="none given"):
        pin_process(frozenset())
    assert os.sched_getaffinity(0) == before


_CHILD = """
import asyncio, json, os, sys, threading
from service.affinity import background_cpus, pin_process
from service.jobs import SynthesisJobs

def allowed(tid):
    status = open(f"/proc/self/task/{tid}/status").read()
    return [line.split(":")[1].strip() for line in status.splitlines() if line.startswith("Cpus_allowed_list")][0]

stop = threading.Event()
early = threading.Thread(target=stop.wait, name="early")
early.start()
pin_process(frozenset({int(sys.argv[1])}))
late = threading.Thread(target=stop.wait, name="late")
late.start()
threads = {t.name: allowed(t.native_id) for t in (early, late)}
threads["main"] = allowed(threading.get_native_id())
stop.set()
jobs = SynthesisJobs(1, lambda *a: None, lambda job: None)

async def worker_cpus():
    try:
        return sorted(await jobs.run_in_worker(os.sched_getaffinity, 0))
    finally:
        await jobs.close()

print(json.dumps({"threads": threads, "worker": asyncio.run(worker_cpus()), "background": sorted(background_cpus())}))
"""


@LINUX
def test_a_pinned_process_moves_every_thread_and_leaves_the_rest_to_its_design_workers():
    allowed = sorted(os.sched_getaffinity(0))
    first = allowed[0]
    done = subprocess.run(
        [sys.executable, "-c", _CHILD, str(first)], capture_output=True, text=True, timeout=120, check=False
    )
    assert done.returncode == 0, done.stderr
    seen = json.loads(done.stdout.strip().splitlines()[-1])
    # the thread started before the pin moved too, the one started after inherited it
    assert seen["threads"] == {"early": str(first), "late": str(first), "main": str(first)}
    rest = [cpu for cpu in allowed if cpu != first] or allowed  # a 1-CPU machine: the workers share it
    assert seen["background"] == rest
    assert seen["worker"] == rest


@LINUX
def test_moving_a_process_that_ended_does_nothing():
    done = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    gone = int(done.stdout)  # ended and reaped: no /proc entry (unless the id was reused meanwhile)
    if Path(f"/proc/{gone}").exists():
        pytest.skip("the process id was reused")
    set_process_affinity(frozenset(os.sched_getaffinity(0)), gone)
