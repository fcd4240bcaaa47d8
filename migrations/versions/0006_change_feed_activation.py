"""The change feed also carries model-version activations: a row with op "activate" names the
version (``model_version``) and no frame, so ``frame_id`` may be null.

Revision ID: 0006
Revises: 0005
Create Date: 2026-12-01
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0006"
down_revision = "0005"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("atlas_changes") as batch:
        batch.alter_column("frame_id", existing_type=sa.Integer(), nullable=True)
        batch.add_column(sa.Column("model_version", sa.Integer()))


def downgrade() -> None:
    op.execute("DELETE FROM atlas_changes WHERE frame_id IS NULL")
    with op.batch_alter_table("atlas_changes") as batch:
        batch.drop_column("model_version")
        batch.alter_column("frame_id", existing_type=sa.Integer(), nullable=False)
