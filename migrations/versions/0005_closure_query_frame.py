"""Loop closures recorded by ``observe`` name the frame the observation stored, so the console
can redraw the verified matches from both frames' stored keypoints.

Revision ID: 0005
Revises: 0004
Create Date: 2026-12-01
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0005"
down_revision = "0004"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("loop_closures") as batch:
        batch.add_column(sa.Column("query_frame_id", sa.Integer()))
        batch.create_foreign_key(
            "fk_loop_closures_query_frame_id_frames",
            "frames",
            ["query_frame_id"],
            ["id"],
            ondelete="SET NULL",
        )
        batch.create_index("ix_loop_closures_query_frame_id", ["query_frame_id"])


def downgrade() -> None:
    with op.batch_alter_table("loop_closures") as batch:
        batch.drop_index("ix_loop_closures_query_frame_id")
        batch.drop_constraint("fk_loop_closures_query_frame_id_frames", type_="foreignkey")
        batch.drop_column("query_frame_id")
