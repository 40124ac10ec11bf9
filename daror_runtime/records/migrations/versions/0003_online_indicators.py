"""A session's online indicators per model and its blind comparison's verdict (issue 29).

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-29

Frozen: a migration never imports the schema module (it describes the schema as it was then).
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("sessions") as batch:
        batch.add_column(sa.Column("online", sa.JSON(), nullable=True))
        batch.add_column(sa.Column("comparison", sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("sessions") as batch:
        batch.drop_column("comparison")
        batch.drop_column("online")
