"""The first schema: profiles, gain versions, vehicles, alarms with their events, synthesis jobs.

The same tables as SQLite's schema version 1 (service/storage.py), with PostgreSQL's types: time stamps in
nanoseconds are BIGINT, the alarm event sequence an identity column. Documents stay JSON text, as in SQLite.

Revision ID: 0001
Revises: none
"""

from __future__ import annotations

from alembic import op

revision = "0001"
down_revision: str | None = None
branch_labels: str | None = None
depends_on: str | None = None

_TABLES = (
    """CREATE TABLE profiles (
        name TEXT PRIMARY KEY,
        spec TEXT NOT NULL,
        active_version TEXT,
        created_t_ns BIGINT NOT NULL,
        updated_t_ns BIGINT NOT NULL
    )""",
    """CREATE TABLE gain_versions (
        profile TEXT NOT NULL,
        version TEXT NOT NULL,
        created_t_ns BIGINT NOT NULL,
        gains TEXT NOT NULL,
        PRIMARY KEY (profile, version)
    )""",
    """CREATE TABLE vehicles (
        id TEXT PRIMARY KEY,
        profile TEXT NOT NULL,
        registered_t_ns BIGINT NOT NULL
    )""",
    """CREATE TABLE alarms (
        id TEXT PRIMARY KEY,
        vehicle TEXT NOT NULL,
        kind TEXT NOT NULL,
        latched INTEGER NOT NULL,
        updated_t_ns BIGINT NOT NULL,
        record TEXT NOT NULL
    )""",
    "CREATE INDEX alarms_latched ON alarms (latched, vehicle)",
    """CREATE TABLE alarm_events (
        seq BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
        alarm_id TEXT NOT NULL,
        t_ns BIGINT NOT NULL,
        event TEXT NOT NULL
    )""",
    "CREATE INDEX alarm_events_by_alarm ON alarm_events (alarm_id, seq)",
    """CREATE TABLE jobs (
        id TEXT PRIMARY KEY,
        profile TEXT NOT NULL,
        created_t_ns BIGINT NOT NULL,
        record TEXT NOT NULL
    )""",
)


def upgrade() -> None:
    for statement in _TABLES:
        op.execute(statement)


def downgrade() -> None:
    for table in ("jobs", "alarm_events", "alarms", "vehicles", "gain_versions", "profiles"):
        op.execute(f"DROP TABLE {table}")
