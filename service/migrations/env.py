"""Alembic's environment: runs the revisions of ``versions/`` on the connection the service hands over.

``service.storage_postgres.migrate`` calls ``alembic.command.upgrade`` with an open connection in
``config.attributes["connection"]`` (holding the migration lock); the ``alembic`` command line, given
``-x url=postgresql://...``, gets a connection of its own.
"""

from __future__ import annotations

from alembic import context
from sqlalchemy import create_engine, pool
from sqlalchemy.engine import Connection


def _run(connection: Connection) -> None:
    context.configure(connection=connection, transaction_per_migration=True)
    with context.begin_transaction():
        context.run_migrations()


def main() -> None:
    connection = context.config.attributes.get("connection")
    if connection is not None:
        _run(connection)
        return
    url = context.get_x_argument(as_dictionary=True).get("url")
    if not url:
        raise SystemExit("alembic: give the database as -x url=postgresql://USER@HOST/DATABASE")
    engine = create_engine(url.replace("postgresql://", "postgresql+psycopg://", 1), poolclass=pool.NullPool)
    with engine.begin() as own:
        _run(own)


main()
