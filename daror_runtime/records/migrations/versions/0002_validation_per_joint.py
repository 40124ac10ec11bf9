"""A model's validation RMSE per joint (the elbow's rises first as a pilot's stiffness outgrows his model).

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-29

Frozen: a migration never imports the schema module (it describes the schema as it was then).
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("models") as batch:
        batch.add_column(sa.Column("validation_rmse_per_joint_nm", sa.JSON(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("models") as batch:
        batch.drop_column("validation_rmse_per_joint_nm")
