"""The places each observed frame's own search proposed, kept with the frame: sequence scoring
lets every frame of a robot's recent sequence propose candidates without searching the index
again for each of them at every request.

Revision ID: 0007
Revises: 0006
Create Date: 2026-12-02
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0007"
down_revision = "0006"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "frame_proposals",
        sa.Column(
            "frame_id",
            sa.Integer(),
            sa.ForeignKey("frames.id", ondelete="CASCADE"),
            primary_key=True,
        ),
        sa.Column("frame_ids", sa.LargeBinary(), nullable=False),
    )


def downgrade() -> None:
    op.drop_table("frame_proposals")
