"""Revisit pairs: verified closures and operator-labelled pairs of stored frames, the training
pairs of an adaptation job.

Revision ID: 0008
Revises: 0007
Create Date: 2026-12-03
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0008"
down_revision = "0007"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "revisit_pairs",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column(
            "atlas_id",
            sa.Integer(),
            sa.ForeignKey("atlases.id", ondelete="CASCADE"),
            nullable=False,
        ),
        sa.Column(
            "frame_id", sa.Integer(), sa.ForeignKey("frames.id", ondelete="CASCADE"), nullable=False
        ),
        sa.Column(
            "other_frame_id",
            sa.Integer(),
            sa.ForeignKey("frames.id", ondelete="CASCADE"),
            nullable=False,
        ),
        sa.Column("source", sa.String(16), nullable=False),
        sa.Column("inliers", sa.Integer(), nullable=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.UniqueConstraint("frame_id", "other_frame_id", name="uq_revisit_pairs_frames"),
    )
    op.create_index("ix_revisit_pairs_atlas_created", "revisit_pairs", ["atlas_id", "created_at"])
    op.create_index("ix_revisit_pairs_frame_id", "revisit_pairs", ["frame_id"])
    op.create_index("ix_revisit_pairs_other_frame_id", "revisit_pairs", ["other_frame_id"])


def downgrade() -> None:
    op.drop_table("revisit_pairs")
