"""The process's CPU by thread group (service/thread_cpu.py): real threads read from /proc, the grouping rules, and
series that never decrease when threads end or their ids are reused."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from service.thread_cpu import ThreadCpu, thread_group

linux_only = pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs /proc/self/task (Linux)")


def burn(cpu_s: float) -> None:
    """Keep this thread on a core for ``cpu_s`` of its own CPU time."""
    started = time.thread_time()
    while time.thread_time() - started < cpu_s:
        pass


def test_threads_are_grouped_by_what_they_do():
    loop = 100
    assert thread_group(100, loop, "MainThread", "python") == "event_loop"
    assert thread_group(99, loop, "MainThread", "python") == "python_other"
    assert thread_group(101, loop, "storage-writer", "python") == "storage-writer"
    assert thread_group(102, loop, "estimate-history", "python") == "estimate-history"
    assert thread_group(103, loop, "asyncio_0", "python") == "executor"
    assert thread_group(105, loop, "bucket-locks", "python") == "bucket-locks"
    assert thread_group(106, loop, "worker-12", "python") == "worker"  # a pool's numbered threads: one series
    assert thread_group(104, loop, "Thread-3 (worker)", "python") == "python_other"
    for comm in ("rx-0", "rx-1", "tx-0", "acc-0", "net-2", "app-0", "Watchdog Confir"):
        assert thread_group(110, loop, None, comm) == "zenoh", comm
    assert thread_group(120, loop, None, "openblas") == "native_other"
    assert thread_group(121, loop, None, "rx-") == "native_other"


@contextlib.contextmanager
def burning_thread(name: str, cpu_s: float) -> Iterator[Callable[[], None]]:
    """A thread called ``name`` that burns ``cpu_s`` of CPU, then waits; yields a function that ends it (called on
    the way out too)."""
    done = threading.Event()
    worker = threading.Thread(target=lambda: (burn(cpu_s), done.wait(10)), name=name)

    def end() -> None:
        done.set()
        worker.join(10)

    worker.start()
    try:
        yield end
    finally:
        end()


@linux_only
def test_a_named_thread_and_the_main_thread_are_counted_in_their_groups():
    cpu = ThreadCpu()
    with burning_thread("storage-writer", 0.3):
        burn(0.2)
        time.sleep(0.4)  # the worker has burnt its share by now, and waits
        seconds = cpu.sample()
    assert seconds["storage-writer"] >= 0.2
    assert seconds["event_loop"] >= 0.15
    # the groups are the process's threads: their sum is at most the process's CPU time
    assert sum(seconds.values()) <= time.process_time() + 0.05


@linux_only
def test_a_thread_that_ended_keeps_its_time_in_its_group():
    cpu = ThreadCpu()
    with burning_thread("vehicle-estimates", 0.2) as end:
        time.sleep(0.3)
        before = cpu.sample()["vehicle-estimates"]
        end()
        after = cpu.sample()
    assert before >= 0.1
    assert after["vehicle-estimates"] == before
    assert cpu.sample()["vehicle-estimates"] == before


def write_task(task_dir: Path, tid: int, comm: str, utime: int, stime: int) -> None:
    """A /proc/PID/task/TID/stat line: pid (comm) state, then fields 4.. with utime and stime at 14 and 15."""
    fields = ["S", *["0"] * 10, str(utime), str(stime), *["0"] * 30]
    (task_dir / str(tid)).mkdir(exist_ok=True)
    (task_dir / str(tid) / "stat").write_text(f"{tid} ({comm}) {' '.join(fields)}\n")


def test_an_id_reused_by_a_new_thread_does_not_make_a_series_decrease(tmp_path: Path):
    cpu = ThreadCpu(tmp_path)
    ticks = cpu._ticks_per_s
    write_task(tmp_path, 7001, "rx-0", 3 * ticks, ticks)
    write_task(tmp_path, 7002, "a thread (with) parens", ticks, 0)
    first = cpu.sample()
    assert first == {"zenoh": 4.0, "native_other": 1.0}
    # 7001 ended and its id now names a new Zenoh thread with less time: the old one's 4 s stay
    write_task(tmp_path, 7001, "rx-1", ticks // 2, 0)
    second = cpu.sample()
    assert second["zenoh"] == pytest.approx(4.5)
    # 7002 ended
    (tmp_path / "7002" / "stat").unlink()
    (tmp_path / "7002").rmdir()
    assert cpu.sample() == {"zenoh": pytest.approx(4.5), "native_other": 1.0}


def test_without_a_task_list_there_is_nothing_to_report(tmp_path: Path):
    assert ThreadCpu(tmp_path / "absent").sample() == {}
