"""Which database a replica stores in: the embedded SQLite file, or a PostgreSQL server shared by replicas.

Its own module so that service/storage.py (the interface and SQLite) and service/storage_postgres.py (which
imports psycopg and Alembic, loaded only when a URL asks for them) import in one direction only.
"""

from __future__ import annotations

from pathlib import Path

from service.storage import SqliteStorage, Storage


def open_storage(database_url: str | None, path: Path, busy_timeout_s: float = 5.0) -> Storage:
    """PostgreSQL when a URL is given (migrated to the newest schema), else the SQLite file at ``path``."""
    if database_url is None:
        return SqliteStorage(path, busy_timeout_s)
    from service.storage_postgres import PostgresStorage  # psycopg and Alembic are loaded only when used

    return PostgresStorage(database_url, busy_timeout_s)
