"""The frame each observation closed a loop with, kept beside its proposals: the robot's next
observation may continue that loop along the trajectory from a lower sequence margin (loop
tracking, service.ml.sequences.distinctiveness).

Revision ID: 0009
Revises: 0008
Create Date: 2026-12-06
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0009"
down_revision = "0008"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("frame_proposals") as batch:
        batch.add_column(sa.Column("loop_frame_id", sa.Integer(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("frame_proposals") as batch:
        batch.drop_column("loop_frame_id")
