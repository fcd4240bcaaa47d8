"""Whether an observation's loop waits for the robot's next observation to confirm it: a loop
a passed sequence carries while its newest frame's own evidence is weak is answered by the
next frame instead (service.ml.sequences.distinctiveness.CONFIRM_Z), which must know it.

Revision ID: 0010
Revises: 0009
Create Date: 2026-12-07
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0010"
down_revision = "0009"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("frame_proposals") as batch:
        batch.add_column(
            sa.Column("loop_pending", sa.Boolean(), nullable=False, server_default=sa.false())
        )


def downgrade() -> None:
    with op.batch_alter_table("frame_proposals") as batch:
        batch.drop_column("loop_pending")
