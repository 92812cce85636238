"""Bucket leases on a real PostgreSQL server: three `agv-fe serve` replicas (separate processes, Zenoh clients of
one router on loopback) share the 16 buckets of a 60-vehicle fleet, balanced; one replica is killed with SIGKILL
mid-stream; the survivors take its buckets and estimate every one of its vehicles again within 3 s, its latched
alarm is visible through them, nothing it acknowledged is lost, no bucket is ever served by two replicas, and when
it comes back the buckets rebalance."""

from __future__ import annotations

import statistics
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

import psycopg
import pytest

from agv_fe.benchmarks.harness import SteadyFleet
from agv_protocol.wire import N_BUCKETS, bucket_of
from service.bucket_leases import BUCKET_LOCKS
from service.transport import open_session
from tests.faults.helpers import RouterProcess
from tests.service.helpers import (
    FAST_DESIGN,
    WAIT_S,
    ServiceProcess,
    free_port,
    make_settings,
    wait_for,
)

pytestmark = pytest.mark.network

VEHICLES = [f"veh-{k:02d}" for k in range(60)]
PROFILES = {"default": {"design": FAST_DESIGN, "alarms": {"stale_after_s": 1.0}}}
#: how often each replica looks at the lock table and takes free buckets [s]
LEASE_INTERVAL_S = 0.2
#: The issue's bound on a takeover, from the kill to a survivor's first estimate of each of the dead replica's
#: vehicles (measured on the estimate stream). What the configuration guarantees is far below it: a SIGKILLed
#: process's connections are closed by its kernel, so PostgreSQL ends its session and frees its bucket locks at
#: once (no timeout is involved; a machine that vanishes is another matter, deployment.md "Limits"); each survivor
#: starts a lease round within LEASE_INTERVAL_S, sees two members and takes the free buckets up to its share;
#: serving them is a read of their vehicles and one subscription per bucket; the next sample (10 ms) is then
#: estimated at the next tick. One round plus that work is under 0.5 s on an idle machine (docs/benchmarks/
#: failover.md: max 0.51 s with a 0.5 s interval); the rest of the 3 s is headroom for a loaded 2-core machine,
#: where a round or the service's event loop may wait for the CPU. A missed round would still leave 2.6 s.
TAKEOVER_BOUND_S = 3.0


def replica(tmp_path: Path, name: str, router: RouterProcess, url: str) -> ServiceProcess:
    settings = make_settings(
        tmp_path / name,
        PROFILES,
        zenoh={"mode": "client", "endpoint": router.endpoint},
        database={"url": url},
        shard={"replica_id": name, "lease_interval_s": LEASE_INTERVAL_S},
    )
    return ServiceProcess(settings, tmp_path / f"{name}.log")


def served(replicas: dict[str, ServiceProcess]) -> dict[str, set[str]]:
    """The buckets each replica says it serves (GET /health)."""
    return {name: set(srv.get("/health").json()["buckets"]) for name, srv in replicas.items()}


def balanced(replicas: dict[str, ServiceProcess]) -> dict[str, set[str]] | None:
    """Every bucket served by exactly one of ``replicas``, shares within one of each other; else None."""
    shares = served(replicas)
    sizes = sorted(len(s) for s in shares.values())
    union = set().union(*shares.values())
    if sum(sizes) == N_BUCKETS and len(union) == N_BUCKETS and sizes[-1] - sizes[0] <= 1:
        return shares
    return None


def no_bucket_twice(replicas: dict[str, ServiceProcess]) -> None:
    """No bucket served by two replicas at once. The replicas answer one after the other, so a bucket handed over
    between two answers would show in both: an overlap counts only if the replica that answered first still
    serves the bucket when asked again after the others."""
    first, again = served(replicas), served(replicas)
    names = list(first)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            both = first[a] & first[b] & again[a]
            assert not both, f"buckets {sorted(both)} served by {a} and {b} at once"


def bucket_locks(url: str) -> dict[int, list[int]]:
    """The sessions (pids) holding each bucket's advisory lock."""
    holders: dict[int, list[int]] = {}
    with psycopg.connect(url) as conn:
        rows = conn.execute(
            "SELECT objid::bigint, pid FROM pg_locks WHERE locktype = 'advisory' AND classid = %s AND granted",
            (BUCKET_LOCKS,),
        ).fetchall()
    for objid, pid in rows:
        holders.setdefault(int(objid), []).append(int(pid))
    return holders


@contextmanager
def cluster(tmp_path: Path, url: str) -> Iterator[tuple[RouterProcess, dict[str, ServiceProcess]]]:
    with ExitStack() as stack:
        router = RouterProcess(free_port()).start()
        stack.callback(router.stop)
        replicas = {name: replica(tmp_path, name, router, url) for name in ("r0", "r1", "r2")}
        for srv in replicas.values():
            stack.callback(lambda srv=srv: srv.close())
        replicas["r0"].start().wait_ready()  # the first designs the gains; the others read them from the database
        for name in ("r1", "r2"):
            replicas[name].start()
        for srv in replicas.values():
            srv.wait_ready()
        yield router, replicas


def stored_alarm_kinds(url: str, vehicle: str) -> set[str]:
    with psycopg.connect(url) as conn:
        rows = conn.execute("SELECT kind FROM alarms WHERE vehicle = %s AND latched = 1", (vehicle,)).fetchall()
    return {r[0] for r in rows}


def test_a_killed_replicas_buckets_are_taken_over_and_rebalanced_when_it_returns(
    tmp_path: Path, postgres_url: str
) -> None:
    with cluster(tmp_path, postgres_url) as (router, replicas):
        shares = wait_for(lambda: balanced(replicas), what="the 16 buckets shared 6/5/5 by three replicas")
        answer = replicas["r0"].get("/replicas").json()
        assert answer["replicas"] == ["r0", "r1", "r2"] and answer["lease_replicas"] == 3
        assert sorted(len(s) for s in shares.values()) == [5, 5, 6]
        session = open_session("client", router.endpoint)
        fleet = SteadyFleet(session, VEHICLES, max_s=15 * WAIT_S).start()
        try:
            check_the_takeover(fleet, replicas, shares, postgres_url, tmp_path)
        finally:
            fleet.close()
            session.close()


def check_the_takeover(
    fleet: SteadyFleet, replicas: dict[str, ServiceProcess], shares: dict[str, set[str]], url: str, tmp_path: Path
) -> None:
    wait_for(lambda: set(fleet.estimated_since(0.0, {})) == set(VEHICLES), what="estimates of all 60 vehicles")
    victim = "r1"
    its_vehicles = [v for v in VEHICLES if bucket_of(v) in shares[victim]]
    quiet = its_vehicles[0]  # falls silent: the victim latches its STALE alarm before it dies
    fleet.silenced.add(quiet)
    wait_for(lambda: "stale" in stored_alarm_kinds(url, quiet), what=f"the STALE alarm of {quiet} to be stored")
    survivors = {n: s for n, s in replicas.items() if n != victim}
    killed_at = time.monotonic()
    replicas[victim].kill()  # returns once the process is gone
    marks = dict(fleet.seq)  # samples from now on can only be estimated by a survivor
    taken = wait_for(
        lambda: (lambda first: first if set(its_vehicles) - {quiet} <= set(first) else None)(
            fleet.estimated_since(killed_at, marks)
        ),
        what=f"a survivor to estimate every vehicle of {victim} again",
    )
    delays = sorted(taken[v] - killed_at for v in its_vehicles if v != quiet)
    # issue 24's must-show: each vehicle estimated again by a survivor within TAKEOVER_BOUND_S of the kill
    assert delays[-1] <= TAKEOVER_BOUND_S, (
        f"takeover of {len(delays)} vehicles after SIGKILL: p50 {statistics.median(delays):.2f} s, "
        f"max {delays[-1]:.2f} s, beyond {TAKEOVER_BOUND_S} s"
    )
    wait_for(  # the dead replica's liveliness token went with its session
        lambda: survivors["r0"].get("/replicas").json()["replicas"] == ["r0", "r2"],
        what="/replicas without the dead replica",
    )
    after = wait_for(lambda: balanced(survivors), what="the survivors to share the 16 buckets 8/8")
    assert sorted(len(s) for s in after.values()) == [8, 8]
    locks = bucket_locks(url)
    assert sorted(locks) == list(range(N_BUCKETS)) and all(len(pids) == 1 for pids in locks.values())
    # the dead replica's latched alarm, read from the shared database by the survivor that serves its bucket now
    owner = next(n for n, s in after.items() if bucket_of(quiet) in s)
    alarms = survivors[owner].get("/alarms", params={"vehicle": quiet}).json()
    assert [a["kind"] for a in alarms] == ["stale"] and alarms[0]["latched"]
    # nothing the dead replica acknowledged is lost: every vehicle is registered in the database
    with psycopg.connect(url) as conn:
        stored = {r[0] for r in conn.execute("SELECT id FROM vehicles WHERE profile = 'default'")}
    assert set(VEHICLES) <= stored
    for _ in range(10):  # no bucket is served twice while the fleet streams on
        no_bucket_twice(survivors)
        time.sleep(0.1)
    check_the_return(fleet, replicas, victim, tmp_path)


def check_the_return(fleet: SteadyFleet, replicas: dict[str, ServiceProcess], victim: str, tmp_path: Path) -> None:
    back = ServiceProcess(replicas[victim].settings, tmp_path / f"{victim}-again.log")
    replicas[victim] = back
    try:
        back.start().wait_ready()
        deadline = time.monotonic() + WAIT_S
        shares: dict[str, set[str]] | None = None
        while shares is None and time.monotonic() < deadline:  # rebalancing: never a bucket served twice
            no_bucket_twice(replicas)
            shares = balanced(replicas)
            time.sleep(0.05)
        assert shares is not None, f"no rebalance within {WAIT_S} s: {served(replicas)}"
        assert sorted(len(s) for s in shares.values()) == [5, 5, 6] and shares[victim]
        marks, since = dict(fleet.seq), time.monotonic()
        talking = set(VEHICLES) - fleet.silenced
        wait_for(lambda: talking <= set(fleet.estimated_since(since, marks)), what="every vehicle estimated again")
    finally:
        back.close()
