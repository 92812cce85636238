"""`agv-fe serve` as a separate process: killed without warning, then restarted; started with a profile that
cannot be designed. (A SIGKILL during a design: tests/faults/test_crash.py.)"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from service.affinity import format_cpu_list, thread_cpu_lists
from tests.service.helpers import (
    FAST_DESIGN,
    constant_measurement,
    job_done,
    make_settings,
    parse_metrics,
    plant_measurements,
    probe,
    running,
    service_process,
    settings_env,
    wait_for,
)

pytestmark = pytest.mark.network

ALARMS = {"torque_warn_nm": 10.0, "torque_fault_nm": 20.0, "raise_after_s": 0.2, "warmup_s": 1.0}
HEAVY = {"mass_kg": 2100.0, "yaw_inertia_kgm2": 2600.0}
HEAVY_ALARMS = {"torque_warn_nm": 60.0, "torque_fault_nm": 120.0}
#: How long synthesis workers may outlive a killed service [s] (they check their parent every 0.5 s).
ORPHAN_EXIT_S = 10.0


def test_a_sigkill_loses_nothing_the_api_acknowledged(tmp_path):
    settings = make_settings(tmp_path, {"default": {"design": FAST_DESIGN, "alarms": ALARMS}})
    with service_process(settings, tmp_path / "service.log") as srv:
        srv.wait_ready()
        auth = srv.auth
        # a new design for a profile (202), a new profile (202), then a change of thresholds only (200)
        changed = srv.http.put(
            "/profiles/default", json={"design": {**FAST_DESIGN, "fault_order": 2}, "alarms": ALARMS}, headers=auth
        )
        created = srv.http.put("/profiles/heavy", json={"params": HEAVY, "design": FAST_DESIGN}, headers=auth)
        assert (changed.status_code, created.status_code) == (202, 202)
        jobs = [wait_for(lambda r=r: job_done(srv, r.json()["job"]), what="job") for r in (changed, created)]
        assert [j["status"] for j in jobs] == ["succeeded", "succeeded"]
        heavy_spec = {"params": HEAVY, "design": FAST_DESIGN, "alarms": HEAVY_ALARMS}
        thresholds = srv.http.put("/profiles/heavy", json=heavy_spec, headers=auth)
        assert thresholds.status_code == 200 and thresholds.json()["applied"]
        registered = srv.http.put("/vehicles/heavy-7", json={"profile": "heavy"}, headers=auth)
        assert registered.status_code == 200
        with probe(settings.zenoh.endpoint) as p:
            for row in plant_measurements(["crash-1"], 900):  # a 30 N m torque bias from 5 s
                p.put(row[0])
            alarm = wait_for(
                lambda: [a for a in srv.get("/alarms").json() if a["kind"] == "torque_fault"], what="torque alarm"
            )[0]
        profiles = {p["name"]: p for p in srv.get("/profiles").json()}
        jobs_before = srv.get("/jobs").json()
        acked = srv.http.post(f"/alarms/{alarm['id']}/ack", headers=auth, json={"by": "night shift"})
        assert acked.status_code == 200 and acked.json()["acknowledged"]
        srv.kill()  # at once: what the API answered must already be on disk
        assert srv.process is not None and srv.process.returncode == -9
        # the synthesis worker notices and ends too: a crash leaves no orphan behind
        wait_for(lambda: not srv.survivors(), timeout=ORPHAN_EXIT_S, what="the synthesis workers to exit")
    with running(settings) as again:  # a new process on the same data directory
        after = {p["name"]: p for p in again.get("/profiles").json()}
        assert set(after) == {"default", "heavy"}
        for name in after:
            for field in ("spec", "active_version", "gain_versions"):
                assert after[name][field] == profiles[name][field], (name, field)
        assert after["default"]["active_version"] == jobs[0]["gain_version"]
        assert after["default"]["spec"]["design"]["fault_order"] == 2
        assert after["heavy"]["active_version"] == jobs[1]["gain_version"]
        heavy = after["heavy"]["spec"]
        assert heavy["alarms"] | HEAVY_ALARMS == heavy["alarms"] and heavy["params"] | HEAVY == heavy["params"]
        assert again.get("/jobs").json() == jobs_before  # nothing was redesigned
        stored = again.get(f"/alarms/{alarm['id']}").json()
        assert stored["acknowledged"] and stored["acknowledged_by"] == "night shift" and stored["latched"]
        assert [e["state"] for e in stored["events"]][-1] == "acknowledged"
        assert again.vehicle("heavy-7")["profile"] == "heavy"
        assert again.vehicle("crash-1")["profile"] == "default"


def test_a_failed_first_design_is_named_by_ready_logged_and_listed_in_jobs(tmp_path):
    impossible = {**FAST_DESIGN, "design": "paper-decoupled"}
    settings = make_settings(tmp_path, {"default": {"design": FAST_DESIGN}, "van": {"design": impossible}})
    profiles_file = str(settings.profiles_file)
    settings = settings.model_copy(update={"profiles_file": None})  # given by the flag instead
    log = tmp_path / "service.log"
    with service_process(settings, log, "--profiles", profiles_file) as srv:
        # one worker: default's design runs first, van's waits for it
        first = srv.get("/ready")
        assert first.status_code == 503
        assert first.json()["missing_gains"]["van"]["state"] == "designing"
        assert "'van' has no active gains: designing" in first.json()["detail"]

        def van_failed() -> dict[str, Any] | None:
            body: dict[str, Any] = srv.get("/ready").json()
            missing = body["missing_gains"]
            return body if set(missing) == {"van"} and missing["van"]["state"] == "failed" else None

        body = wait_for(van_failed, what="van's design to fail and default's to succeed")
        answer = srv.get("/ready")
        # it stays so; the storage's pending writes are whatever the writer has not stored yet at each request
        steady = lambda ready: {k: v for k, v in ready.items() if k != "storage"}  # noqa: E731
        assert answer.status_code == 503 and steady(answer.json()) == steady(body)
        van = body["missing_gains"]["van"]
        assert van["error"] == "infeasible" and "unobservable" in van["reason"]
        assert body["profiles"]["van"] is None and body["profiles"]["default"] is not None
        assert body["detail"] == f"profile 'van' has no active gains: its design failed (infeasible): {van['reason']}"
        failed = [j for j in srv.get("/jobs").json() if j["profile"] == "van"]
        assert [(j["id"], j["status"], j["kind"], j["reason"]) for j in failed] == [
            (van["job"], "failed", "initial", van["reason"])
        ]
        logged = wait_for(
            lambda: [line for line in srv.log().splitlines() if " ERROR " in line and "profile van" in line],
            what="an ERROR log line",
        )
        assert van["job"] in logged[0] and "infeasible" in logged[0] and "unobservable" in logged[0]
        # a feasible design of the profile makes the service ready
        fixed = srv.http.put("/profiles/van", json={"design": FAST_DESIGN}, headers=srv.auth)
        assert fixed.status_code == 202
        assert wait_for(lambda: job_done(srv, fixed.json()["job"]), what="the new job")["status"] == "succeeded"
        ready = srv.get("/ready")
        assert ready.status_code == 200 and ready.json()["missing_gains"] == {} and ready.json()["detail"] is None


def test_the_latest_request_wins_over_a_pending_design(tmp_path):
    """A change of thresholds on the active design, sent while an earlier design of the profile is still
    pending, withdraws that design: its gains are not activated and they cannot overwrite the thresholds."""
    settings = make_settings(tmp_path, {"default": {"design": FAST_DESIGN, "alarms": ALARMS}})
    with running(settings) as srv:
        active = srv.get("/profiles/default").json()
        redesign = srv.http.put(
            "/profiles/default", json={"design": {**FAST_DESIGN, "fault_order": 2}, "alarms": ALARMS}, headers=srv.auth
        )
        assert redesign.status_code == 202
        newer = {"design": FAST_DESIGN, "alarms": {**ALARMS, "torque_warn_nm": 15.0}}
        applied = srv.http.put("/profiles/default", json=newer, headers=srv.auth)
        assert applied.status_code == 200 and applied.json()["applied"]
        job = wait_for(lambda: job_done(srv, redesign.json()["job"]), what="the withdrawn design")
        assert job["status"] == "superseded" and "later request" in job["reason"]
        after = srv.get("/profiles/default").json()
        assert after["active_version"] == active["active_version"]
        assert after["spec"]["alarms"]["torque_warn_nm"] == 15.0
        assert after["spec"]["design"]["fault_order"] == active["spec"]["design"]["fault_order"]


def test_samples_arriving_all_the_time_are_stepped_in_ticks_at_most_one_per_interval(tmp_path):
    """Vehicles with independent clocks send all through the sample period. The ingest loop starts a tick at most
    once per ``tick_interval_s`` and steps what arrived in between as one batch: samples that keep arriving while
    a tick runs do not each start a tick of their own. (A separate process: a service in the test's process would
    share its interpreter lock with the sender.)"""
    interval, spacing_s, rounds = 0.02, 0.00005, 250
    ids = [f"trickle-{i}" for i in range(20)]
    settings = make_settings(tmp_path, ingest={"tick_interval_s": interval})

    def ticks() -> float:
        return parse_metrics(srv.get("/metrics").text).value("agv_fe_tick_batch_measurements_count")

    with service_process(settings, tmp_path / "service.log") as srv, probe(settings.zenoh.endpoint) as p:
        srv.wait_ready()
        before = ticks()
        started = due = time.perf_counter()
        for k in range(rounds):
            for vehicle_id in ids:
                p.put(constant_measurement(vehicle_id, k))
                due += spacing_s
                while time.perf_counter() < due:  # a steady stream, finer than time.sleep can pace
                    pass
        sending_s = time.perf_counter() - started
        wait_for(lambda: all(len(p.estimates_of(v)) >= rounds for v in ids), what="every estimate")
        stepped = ticks() - before
        for vehicle_id in ids:
            assert [e.seq for e in p.estimates_of(vehicle_id)] == list(range(rounds))
    # 5,000 samples 50 us apart (0.25 s at least) in ticks 20 ms apart: at most about 13 ticks (9 in a run here),
    # where the loop that drained whatever waited as soon as a tick ended ran 29
    assert sending_s >= rounds * len(ids) * spacing_s
    assert stepped <= sending_s / interval + 3, (stepped, sending_s)


@contextlib.contextmanager
def estimates_flowing(srv: Any, vehicle: str, samples: int = 20) -> Iterator[int]:
    """Wait until the started service is ready, send ``samples`` measurements of ``vehicle`` and wait for every
    estimate of them; yield the service's process id while the sending session is still connected (Zenoh's
    runtimes start threads of their own when a session goes)."""
    srv.wait_ready()
    with probe(srv.settings.zenoh.endpoint) as p:
        for k in range(samples):
            p.put(constant_measurement(vehicle, k))
        wait_for(lambda: len(p.estimates_of(vehicle)) >= samples, what="estimates")
        assert srv.process is not None
        yield int(srv.process.pid)


def zenoh_threads(pid: int) -> set[str]:
    """The names of the process's threads that Zenoh's runtimes run (rx-N, tx-N, acc-N, app-N, net-N)."""
    names = set()
    for tid in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(FileNotFoundError):
            names.add((tid / "comm").read_text().strip())
    return {n for n in names if n.split("-")[0] in ("rx", "tx", "acc", "app", "net")}


@pytest.mark.parametrize(
    ("threads", "operator", "present", "absent"),
    [
        (1, None, {"app-0"}, {"rx-0", "tx-0", "acc-0"}),  # the default: rx, tx, acc on the app runtime's worker
        (2, None, {"app-0", "app-1"}, {"rx-0", "tx-0", "acc-0"}),
        (0, None, {"rx-0", "rx-1", "tx-0", "acc-0"}, set()),  # Zenoh's own runtimes
        (1, "(rx: (worker_threads: 1))", {"rx-0", "tx-0", "acc-0"}, {"rx-1"}),  # the operator's variable wins
    ],
)
def test_zenoh_runs_on_the_threads_its_setting_gives(tmp_path, monkeypatch, threads, operator, present, absent):
    """`agv-fe serve` sets ZENOH_RUNTIME from zenoh.runtime_threads before it opens Zenoh; the estimates flow
    whatever threads carry them."""
    if not Path("/proc/self/task").is_dir():
        pytest.skip("needs /proc (Linux)")
    monkeypatch.delenv("ZENOH_RUNTIME", raising=False)
    settings = make_settings(tmp_path, zenoh={"runtime_threads": threads})
    env = {} if operator is None else {"ZENOH_RUNTIME": operator}
    with (
        service_process(settings, tmp_path / "service.log", env=env) as srv,
        estimates_flowing(srv, "threads-1") as pid,
    ):
        names = zenoh_threads(pid)
    assert present <= names and not (absent & names), sorted(names)


def test_a_cpu_the_service_may_not_use_stops_it_with_the_setting_named(tmp_path):
    allowed = os.sched_getaffinity(0)
    outside = max(allowed) + 1000
    settings = make_settings(tmp_path, cpus=f"{min(allowed)},{outside}")
    done = subprocess.run(
        [sys.executable, "-m", "agv_fe", "serve"],
        env=settings_env(settings),
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode != 0
    assert f"setting cpus ('{min(allowed)},{outside}'): CPUs {outside}: this process may run on CPUs" in done.stderr


def children(pid: int) -> list[int]:
    """The processes whose parent is ``pid``."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError, ValueError, IndexError):
            if int(stat.read_text().rsplit(")", 1)[1].split()[1]) == pid:
                found.append(int(stat.parent.name))
    return found


@pytest.mark.parametrize("writer", ["thread", "process"])
def test_the_service_runs_on_the_cpus_its_setting_gives_and_its_history_process_on_the_rest(tmp_path, writer):
    """Setting cpus: every thread of `agv-fe serve` (Zenoh's, the event loop's, the vehicle-estimate thread's)
    runs on the one CPU given and the estimates flow; a history in its own process (the child with a Zenoh
    session) runs on the CPUs left over: no estimate waits for its writes."""
    if not Path("/proc/self/task").is_dir():
        pytest.skip("needs /proc (Linux)")
    allowed = os.sched_getaffinity(0)
    cpu = min(allowed)
    settings = make_settings(tmp_path, cpus=str(cpu), history={"writer": writer})
    with service_process(settings, tmp_path / "service.log") as srv:
        with estimates_flowing(srv, "pinned-1") as pid:
            service_lists = thread_cpu_lists(pid)
            names = zenoh_threads(pid)
            history_lists = [thread_cpu_lists(c) for c in children(pid) if zenoh_threads(c)]
        assert "running on CPUs" in srv.log()
        build = [
            dict(labels)
            for name, labels in parse_metrics(srv.get("/metrics").text).samples
            if name == "agv_fe_build_info"
        ]
        assert [b["cpus"] for b in build] == [str(cpu)]  # what an operator sees on /metrics
    assert service_lists == [str(cpu)]
    assert "app-0" in names  # Zenoh's thread was among them
    rest = format_cpu_list(allowed - {cpu} or allowed)
    assert history_lists == ([[rest]] if writer == "process" else [])
