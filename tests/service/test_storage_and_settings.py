"""SQLite's own storage behaviour (a real file) and the settings (environment variables, nested with __); the
storage interface is tested on SQLite and PostgreSQL alike in test_storage.py."""

from __future__ import annotations

import sqlite3

import pytest
from pydantic import ValidationError

from service.fleet import ProfileBank
from service.profiles import (
    MAX_RULE_DURATION_S,
    ProfileFileError,
    ProfileSpec,
    load_profiles_file,
    valid_profile_name,
)
from service.settings import Settings
from service.storage import SqliteStorage, StorageError


def test_sqlite_storage_journals_in_wal_mode(tmp_path):
    """SQLite's own settings; what is stored and read back is tested on both databases in test_storage.py."""
    path = tmp_path / "db.sqlite3"
    db = SqliteStorage(path)
    db.put_vehicles([("v1", "van", 3)])
    db.close()
    assert sqlite3.connect(path).execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert sqlite3.connect(path).execute("SELECT id FROM vehicles").fetchall() == [("v1",)]


def test_profile_spec_keeps_only_what_was_set_so_defaults_propagate():
    spec = ProfileSpec.model_validate({"design": {"fault_order": 2}, "alarms": {"torque_warn_nm": 40}})
    assert spec.stored() == {"design": {"fault_order": 2}, "alarms": {"torque_warn_nm": 40.0}}
    assert ProfileSpec.model_validate(spec.stored()).design.design == ProfileSpec().design.design


def test_profile_spec_names_the_bad_field():
    with pytest.raises(ValidationError, match="torque_warn_nm must be below torque_fault_nm"):
        ProfileSpec.model_validate({"alarms": {"torque_warn_nm": 300}})


def test_profiles_file_errors_name_the_profile_and_field(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text("profiles:\n  van:\n    params:\n      mass_kg: -1\n")
    with pytest.raises(ProfileFileError, match=r"profiles\.van\.params\.mass_kg"):
        load_profiles_file(path)
    path.write_text("profiles:\n  van:\n    design:\n      fault_order: 1\n")
    assert load_profiles_file(path)["van"].design.fault_order == 1


def test_settings_from_nested_environment_variables(monkeypatch, tmp_path):
    monkeypatch.setenv("AGV_FE_HTTP__PORT", "9123")
    monkeypatch.setenv("AGV_FE_ZENOH__MODE", "client")
    monkeypatch.setenv("AGV_FE_ZENOH__ENDPOINT", "tcp/127.0.0.1:7999")
    monkeypatch.setenv("AGV_FE_INGEST__ESTIMATE_EVERY_N", "5")
    monkeypatch.setenv("AGV_FE_AUTH__TOKEN", "s3cret")
    monkeypatch.setenv("AGV_FE_DATA_DIR", str(tmp_path))
    s = Settings()
    assert (s.http.port, s.zenoh.mode, s.zenoh.endpoint, s.ingest.estimate_every_n) == (
        9123,
        "client",
        "tcp/127.0.0.1:7999",
        5,
    )
    assert s.auth.token is not None and s.auth.token.get_secret_value() == "s3cret" and "s3cret" not in repr(s)
    monkeypatch.setenv("AGV_FE_ZENOH__ENDPOINT", "127.0.0.1:7447")
    with pytest.raises(ValidationError, match="endpoint"):
        Settings()


def test_serve_flags_override_the_environment(monkeypatch, tmp_path):
    from agv_fe.cli import build_parser
    from agv_fe.commands.serve import build_settings

    monkeypatch.setenv("AGV_FE_HTTP__PORT", "9123")
    monkeypatch.setenv("AGV_FE_AUTH__TOKEN", "s3cret")
    args = build_parser().parse_args(
        [
            "serve",
            "--http-port",
            "8111",
            "--zenoh-endpoint",
            "tcp/127.0.0.1:7555",
            "--data-dir",
            str(tmp_path),
            "--shard",
            "1/2",
        ]
    )
    s = build_settings(args)
    assert (s.http.port, s.zenoh.endpoint, s.data_dir, s.shard.index, s.shard.replicas) == (
        8111,
        "tcp/127.0.0.1:7555",
        tmp_path,
        1,
        2,
    )
    assert s.auth.token.get_secret_value() == "s3cret"


@pytest.mark.parametrize(
    "alarms",
    [
        {"clear_after_s": 1e300},
        {"raise_after_s": 1e300},
        {"warmup_s": 1e12},
        {"out_of_domain_after_s": 86_401.0},
        {"stale_after_s": 1e300},
        {"reject_burst_window_s": 1e300},
        {"reject_burst_count": 10**12},
        {"sequence_reject_count": 10**12},
        {"torque_warn_nm": 1e300, "torque_fault_nm": 2e300},
    ],
)
def test_a_profile_is_refused_unless_every_rule_is_finite_and_bounded(alarms):
    """Durations end up as integer nanoseconds of sample time: a profile is valid only if every one converts."""
    with pytest.raises(ValidationError, match=next(iter(alarms))):
        ProfileSpec.model_validate({"alarms": alarms})
    with pytest.raises(ValidationError, match="vx_max_mps"):
        ProfileSpec.model_validate({"limits": {"vx_max_mps": 1e300}})
    longest = {k: MAX_RULE_DURATION_S for k in ("raise_after_s", "clear_after_s", "warmup_s", "stale_after_s")}
    ProfileBank("p", ProfileSpec.model_validate({"alarms": longest}), 10)  # the bounds themselves convert


@pytest.mark.parametrize("name", ["van", "van-2.b_c", "...", "x" * 64])
def test_profile_names_that_are_accepted(name):
    assert valid_profile_name(name)


@pytest.mark.parametrize("name", [".", "..", "van\n", "", "x" * 65, "van/2", "v an"])
def test_profile_names_that_are_refused(name):
    assert not valid_profile_name(name)


def test_an_empty_database_file_is_refused_not_taken_for_a_new_database(tmp_path):
    """A 0-byte file (a truncated copy, a failed restore) would open as a new, empty database: the service would
    start with none of its profiles, gains, vehicles or alarms. A database the service creates is never empty."""
    path = tmp_path / "service.sqlite3"
    path.touch()
    with pytest.raises(StorageError, match="empty"):
        SqliteStorage(path)
    assert path.stat().st_size == 0  # left as it was found
    fresh = tmp_path / "new" / "service.sqlite3"
    SqliteStorage(fresh).close()  # a file that does not exist yet is created
    SqliteStorage(fresh).close()  # and opens again
    assert fresh.stat().st_size > 0


def test_a_foreign_schema_version_is_a_storage_error_naming_it(tmp_path):
    path = tmp_path / "db.sqlite3"
    SqliteStorage(path).close()
    for stored in ("abc", "", "2"):  # not even a number: once a ValueError with a traceback
        with sqlite3.connect(path) as db:
            db.execute("UPDATE meta SET value = ? WHERE key = 'schema_version'", (stored,))
        with pytest.raises(StorageError, match=f"schema version '{stored}', this service reads 1"):
            SqliteStorage(path)


def test_a_zenoh_endpoint_is_the_whole_setting_not_a_prefix_before_a_newline():
    with pytest.raises(ValidationError, match="PROTOCOL/HOST:PORT"):
        Settings.model_validate({"zenoh": {"endpoint": "tcp/127.0.0.1:7447\n"}})
    assert Settings.model_validate({"zenoh": {"endpoint": "tcp/127.0.0.1:7447"}}).zenoh.endpoint.endswith(":7447")


def test_the_database_url_from_the_environment_or_the_flag_and_never_shown(monkeypatch, tmp_path):
    from agv_fe.cli import build_parser
    from agv_fe.commands.serve import build_settings

    assert Settings().database_url is None  # the embedded SQLite file by default
    monkeypatch.setenv("AGV_FE_DATABASE__URL", "postgresql://agv:s3cret@db:5432/fleet")
    from_env = build_settings(build_parser().parse_args(["serve"]))
    assert from_env.database_url == "postgresql://agv:s3cret@db:5432/fleet" and "s3cret" not in repr(from_env)
    flagged = build_settings(build_parser().parse_args(["serve", "--database-url", "postgresql://agv@other/fleet"]))
    assert flagged.database_url == "postgresql://agv@other/fleet"
    monkeypatch.setenv("AGV_FE_DATABASE__URL", "mysql://agv@db/fleet")
    with pytest.raises(ValidationError, match="expected a PostgreSQL URL"):
        Settings()
