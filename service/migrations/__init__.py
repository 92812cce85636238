"""Alembic migrations of the PostgreSQL schema (service/storage_postgres.py applies them at start)."""
