"""Thumbnails for the console: a small JPEG per frame and per loop-closing query; loop
closures keep their verification (inliers, relative pose).

Revision ID: 0004
Revises: 0003
Create Date: 2026-12-01
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "frame_thumbnails",
        sa.Column(
            "frame_id",
            sa.Integer(),
            sa.ForeignKey("frames.id", ondelete="CASCADE"),
            primary_key=True,
        ),
        sa.Column("jpeg", sa.LargeBinary(), nullable=False),
    )
    with op.batch_alter_table("loop_closures") as batch:
        batch.add_column(sa.Column("inliers", sa.Integer()))
        batch.add_column(sa.Column("relative_pose", sa.JSON()))
    op.create_table(
        "loop_closure_thumbnails",
        sa.Column(
            "loop_closure_id",
            sa.Integer(),
            sa.ForeignKey("loop_closures.id", ondelete="CASCADE"),
            primary_key=True,
        ),
        sa.Column("jpeg", sa.LargeBinary(), nullable=False),
    )


def downgrade() -> None:
    op.drop_table("loop_closure_thumbnails")
    with op.batch_alter_table("loop_closures") as batch:
        batch.drop_column("relative_pose")
        batch.drop_column("inliers")
    op.drop_table("frame_thumbnails")
