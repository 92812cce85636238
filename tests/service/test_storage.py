"""The storage interface, the same tests on both implementations: SQLite (a real file) and PostgreSQL (a real
server, agv_fe/pg_cluster.py). Then what only PostgreSQL has: Alembic migrations applied at start, a database of a
newer version refused, and a connection lost and found again."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import psycopg
import pytest

from agv_fe.pg_cluster import PostgresServer
from service.databases import open_storage
from service.storage import SqliteStorage, Storage, StorageError, StorageUnavailable
from service.storage_postgres import PostgresStorage, migrate, redacted

Open = Callable[[], Storage]


@pytest.fixture(params=["sqlite", "postgresql"])
def open_db(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Open]:
    """Opens connections to one database of the implementation under test, and closes them after the test."""
    if request.param == "sqlite":
        path = tmp_path / "service.sqlite3"

        def opener() -> Storage:
            return open_storage(None, path)
    else:
        url = request.getfixturevalue("postgres_url")

        def opener() -> Storage:
            return open_storage(url, tmp_path / "unused.sqlite3")

    opened: list[Storage] = []

    def tracked() -> Storage:
        opened.append(opener())
        return opened[-1]

    yield tracked
    for db in opened:
        db.close()


def alarm(alarm_id: str, vehicle: str, t_ns: int, state: str = "raised", acknowledged: bool = False) -> dict[str, Any]:
    return {
        "id": alarm_id,
        "vehicle": vehicle,
        "kind": "stale",
        "state": state,
        "acknowledged": acknowledged,
        "updated_t_ns": t_ns,
    }


def test_what_is_stored_is_read_back_by_another_connection(open_db: Open) -> None:
    db = open_db()
    db.put_profile("van", {"design": {"fault_order": 1}}, 1)
    db.activate_gains("van", {"design": {"fault_order": 1}}, {"version": "abc", "certificate": {}}, 2)
    db.put_vehicles([("v1", "van", 3), ("v2", "van", 3)])
    db.record_alarm_changes([(alarm("al-1", "v1", 4), {"t_ns": 4, "state": "raised"})])
    again = open_db()
    (profile,) = again.profiles()
    assert (profile.name, profile.active_version, profile.spec) == ("van", "abc", {"design": {"fault_order": 1}})
    assert (profile.created_t_ns, profile.updated_t_ns, profile.problem) == (1, 2, None)
    assert again.gains("van", "abc") == {"version": "abc", "certificate": {}}
    assert again.gains("van", "nope") is None and again.gains("truck", "abc") is None
    assert again.vehicles() == [("v1", "van", 3), ("v2", "van", 3)]
    assert [a["id"] for a in again.latched_alarms()] == ["al-1"]
    acked = alarm("al-1", "v1", 5, state="cleared", acknowledged=True)
    again.record_alarm_changes([(acked, {"t_ns": 5, "state": "acknowledged"})])
    assert db.latched_alarms() == [] and [e["t_ns"] for e in db.alarm_events("al-1")] == [4, 5]
    assert db.alarm("al-1") == acked and db.alarm("al-2") is None


def test_a_payload_is_stored_per_vehicle_and_replaced_by_the_next(open_db: Open) -> None:
    db = open_db()
    assert db.payloads() == {}
    db.put_payload("v1", 120.5, 1)
    db.put_payload("v2", 0.0, 2)
    db.put_payload("v1", 80.25, 3)
    assert open_db().payloads() == {"v1": 80.25, "v2": 0.0}


def test_nanosecond_time_stamps_keep_every_digit(open_db: Open) -> None:
    t_ns = 1_764_000_000_123_456_789  # 2025 in nanoseconds: beyond 32 bits, within 64
    db = open_db()
    db.put_vehicles([("v1", "van", t_ns)])
    assert open_db().vehicles() == [("v1", "van", t_ns)]


def test_a_profile_update_keeps_its_active_version_unless_given_one(open_db: Open) -> None:
    db = open_db()
    db.activate_gains("van", {"a": 1}, {"version": "g1"}, 10)
    db.put_profile("van", {"a": 2}, 20)
    (profile,) = db.profiles()
    assert (profile.spec, profile.active_version, profile.created_t_ns, profile.updated_t_ns) == (
        {"a": 2},
        "g1",
        10,
        20,
    )
    db.put_profile("van", {"a": 3}, 30, active_version="g2")
    assert db.profiles()[0].active_version == "g2"


def test_a_gain_version_is_stored_once_and_listed_in_order(open_db: Open) -> None:
    db = open_db()
    db.activate_gains("van", {}, {"version": "g1", "n": 1}, 1)
    db.activate_gains("van", {}, {"version": "g2"}, 2)
    db.activate_gains("van", {}, {"version": "g1", "n": 2}, 3)  # activated again: the stored document stays
    assert db.gain_versions("van") == [("g1", 1), ("g2", 2)]
    assert db.gains("van", "g1") == {"version": "g1", "n": 1}
    assert db.profiles()[0].active_version == "g1"


def test_a_registration_moves_a_vehicle_to_its_new_profile_keeping_the_first_time(open_db: Open) -> None:
    db = open_db()
    db.put_vehicles([("v1", "van", 1)])
    db.put_vehicles([("v1", "truck", 2), ("v0", "van", 2)])
    assert db.vehicles() == [("v0", "van", 2), ("v1", "truck", 1)]
    db.put_vehicles([])  # nothing to store is no error
    assert len(db.vehicles()) == 2


def test_alarms_newest_first_filtered_and_limited(open_db: Open) -> None:
    db = open_db()
    changes = [(alarm(f"al-{i}", f"v{i % 2}", i), {"t_ns": i}) for i in range(6)]
    db.record_alarm_changes(changes)
    assert [a["id"] for a in db.alarms()] == ["al-5", "al-4", "al-3", "al-2", "al-1", "al-0"]
    assert [a["id"] for a in db.alarms("v0", limit=2)] == ["al-4", "al-2"]
    assert [a["id"] for a in db.latched_alarms()] == [f"al-{i}" for i in range(6)]


def test_jobs_upserted_listed_newest_first_and_pruned(open_db: Open) -> None:
    db = open_db()
    for i in range(5):
        db.put_job({"id": f"j{i}", "profile": "van", "created_t_ns": i, "status": "queued"})
    db.put_job({"id": "j1", "profile": "van", "created_t_ns": 1, "status": "done"})
    assert db.job("j1") == {"id": "j1", "profile": "van", "created_t_ns": 1, "status": "done"}
    assert [j["id"] for j in db.jobs(limit=3)] == ["j4", "j3", "j2"]
    db.prune_jobs(keep=2)
    assert [j["id"] for j in db.jobs()] == ["j4", "j3"] and db.job("j1") is None


def test_a_failed_transaction_leaves_nothing_behind_and_the_next_one_works(open_db: Open) -> None:
    db = open_db()
    half = [(alarm("al-1", "v1", 1), {"t_ns": 1}), ({"id": "al-2", "state": "raised"}, {"t_ns": 2})]
    with pytest.raises(KeyError):  # the second record has no acknowledged flag: the first is rolled back
        db.record_alarm_changes(half)
    assert db.alarms() == [] and db.alarm_events("al-1") == []
    db.put_vehicles([("v2", "van", 2)])
    assert open_db().vehicles() == [("v2", "van", 2)]


def test_stored_documents_that_are_not_json_are_reported_not_raised_as_decoder_errors(open_db: Open) -> None:
    db = open_db()
    db.put_profile("good", {"design": {"fault_order": 1}}, 1)
    db.activate_gains("bad", {}, {"version": "abc", "certificate": {}}, 2)
    db.put_profile("list", {}, 3)
    with open_db().transaction() as raw:
        raw.execute("UPDATE profiles SET spec = ? WHERE name = ?", ("{not json", "bad"))
        raw.execute("UPDATE profiles SET spec = ? WHERE name = ?", ("[1]", "list"))
        raw.execute("UPDATE gain_versions SET gains = ? WHERE version = ?", ("[1, 2", "abc"))
    bad, good, listed = db.profiles()
    assert good.problem is None and good.spec == {"design": {"fault_order": 1}}
    assert bad.name == "bad" and bad.spec == {} and "not JSON" in str(bad.problem)
    assert listed.spec == {} and "JSON list, not an object" in str(listed.problem)
    with pytest.raises(StorageError, match="gains abc of profile bad are not JSON"):
        db.gains("bad", "abc")


def test_two_writers_at_once_lose_nothing(open_db: Open) -> None:
    """Two connections (two threads, or two replicas) registering vehicles at the same time: all are stored."""
    writers = [open_db(), open_db()]
    errors: list[BaseException] = []

    def register(db: Storage, name: str) -> None:
        try:
            for i in range(50):
                db.put_vehicles([(f"{name}-{i}", "van", i)])
        except BaseException as exc:  # reported below: a thread's exception would otherwise vanish
            errors.append(exc)

    threads = [threading.Thread(target=register, args=(db, f"w{n}")) for n, db in enumerate(writers)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(60)
    assert errors == [] and not any(t.is_alive() for t in threads)
    assert len(open_db().vehicles()) == 100


# ---------------------------------------------------------------------- PostgreSQL only


def test_the_schema_is_migrated_at_start_once_and_versioned(postgres_url: str) -> None:
    PostgresStorage(postgres_url).close()
    with psycopg.connect(postgres_url) as conn:
        (revision,) = conn.execute("SELECT version_num FROM alembic_version").fetchone() or ("",)
        tables = {r[0] for r in conn.execute("SELECT tablename FROM pg_tables WHERE schemaname = 'public'")}
    assert revision == migrate(postgres_url)  # at the newest revision; migrating again changes nothing
    assert {"profiles", "gain_versions", "vehicles", "alarms", "alarm_events", "jobs"} <= tables


def test_replicas_starting_together_migrate_the_schema_once(postgres_url: str) -> None:
    results: list[object] = []

    def start() -> None:
        try:
            results.append(migrate(postgres_url))
        except BaseException as exc:  # reported below
            results.append(exc)

    threads = [threading.Thread(target=start) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(120)
    assert len(set(map(str, results))) == 1 and len(results) == 4, results
    assert all(isinstance(r, str) for r in results), results


def test_a_database_migrated_by_a_newer_version_is_refused_naming_its_revision(postgres_url: str) -> None:
    PostgresStorage(postgres_url).close()
    with psycopg.connect(postgres_url) as conn:
        conn.execute("UPDATE alembic_version SET version_num = '9999'")
    with pytest.raises(StorageError, match="revision '9999', which this version does not know"):
        PostgresStorage(postgres_url)


def test_a_database_that_cannot_be_reached_is_a_storage_error_naming_it_without_the_password() -> None:
    from tests.service.helpers import free_port

    url = f"postgresql://agv:s3cret@127.0.0.1:{free_port()}/nothing"
    with pytest.raises(StorageError, match="cannot open the database") as failed:
        PostgresStorage(url)
    assert "s3cret" not in str(failed.value) and "agv:***@127.0.0.1" in str(failed.value)
    assert redacted("postgresql://agv@h/db") == "postgresql://agv@h/db"
    with pytest.raises(StorageError, match="expected postgresql://"):
        PostgresStorage("mysql://agv@h/db")


def test_a_lost_connection_fails_reads_as_unavailable_and_is_opened_again(postgres_server: PostgresServer) -> None:
    """The server stops (as if it crashed) and comes back: reads say the database is unavailable (the API's 503),
    writes raise an error the storage writer retries, and both work again once the server is back."""
    url = postgres_server.database()
    db = PostgresStorage(url)
    db.put_vehicles([("v1", "van", 1)])
    postgres_server.stop("immediate")
    try:
        with pytest.raises(StorageUnavailable, match=r"127\.0\.0\.1"):
            db.vehicles()
        with pytest.raises(db.transient_errors):
            db.put_vehicles([("v2", "van", 2)])
    finally:
        postgres_server.start()

    def back() -> bool:
        try:
            db.put_vehicles([("v2", "van", 2)])
        except db.transient_errors:
            return False
        return True

    from tests.service.helpers import wait_for

    wait_for(back, what="the storage to reach the restarted server")
    assert db.vehicles() == [("v1", "van", 1), ("v2", "van", 2)]
    db.close()


def test_sqlite_is_the_default_and_a_url_selects_postgresql(tmp_path: Path, postgres_url: str) -> None:
    embedded = open_storage(None, tmp_path / "service.sqlite3")
    shared = open_storage(postgres_url, tmp_path / "unused.sqlite3")
    try:
        assert isinstance(embedded, SqliteStorage) and isinstance(shared, PostgresStorage)
        assert not (tmp_path / "unused.sqlite3").exists()
    finally:
        embedded.close()
        shared.close()
