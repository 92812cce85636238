"""Each vehicle's last reported payload (PUT /vehicles/{id}/payload): the table SQLite's schema gained beside
version 1 (service/storage.py), with PostgreSQL's types.

Revision ID: 0002
Revises: 0001
"""

from __future__ import annotations

from alembic import op

revision = "0002"
down_revision: str | None = "0001"
branch_labels: str | None = None
depends_on: str | None = None


def upgrade() -> None:
    op.execute(
        """CREATE TABLE vehicle_payloads (
            id TEXT PRIMARY KEY,
            payload_kg DOUBLE PRECISION NOT NULL,
            updated_t_ns BIGINT NOT NULL
        )"""
    )


def downgrade() -> None:
    op.execute("DROP TABLE vehicle_payloads")
