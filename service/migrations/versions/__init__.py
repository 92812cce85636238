"""Alembic revisions of the PostgreSQL schema, in order: each names the one it follows (down_revision)."""
