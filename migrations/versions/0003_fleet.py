"""Fleet: atlas revisions and their change log, API keys, inter-robot loop closures.

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-24
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("atlases") as batch:
        batch.add_column(sa.Column("revision", sa.BigInteger(), nullable=False, server_default="0"))
    op.create_table(
        "atlas_changes",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column(
            "atlas_id",
            sa.Integer(),
            sa.ForeignKey("atlases.id", ondelete="CASCADE"),
            nullable=False,
        ),
        sa.Column("revision", sa.BigInteger(), nullable=False),
        sa.Column("op", sa.String(8), nullable=False),
        sa.Column("frame_id", sa.Integer(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
    )
    op.create_index("ix_atlas_changes_atlas_revision", "atlas_changes", ["atlas_id", "revision"])
    op.create_table(
        "api_keys",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column("name", sa.String(128), nullable=False),
        sa.Column("role", sa.String(16), nullable=False),
        sa.Column("atlases", sa.JSON(), nullable=False),
        sa.Column("prefix", sa.String(16), nullable=False),
        sa.Column("key_hash", sa.String(64), nullable=False, unique=True),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("revoked_at", sa.DateTime(timezone=True)),
    )
    op.create_table(
        "loop_closures",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column(
            "atlas_id",
            sa.Integer(),
            sa.ForeignKey("atlases.id", ondelete="CASCADE"),
            nullable=False,
        ),
        sa.Column("robot_id", sa.String(128), nullable=False),
        sa.Column(
            "frame_id",
            sa.Integer(),
            sa.ForeignKey("frames.id", ondelete="CASCADE"),
            nullable=False,
        ),
        sa.Column("matched_robot_id", sa.String(128), nullable=False),
        sa.Column(
            "submap_id",
            sa.Integer(),
            sa.ForeignKey("submaps.id", ondelete="CASCADE"),
            nullable=False,
        ),
        sa.Column("similarity", sa.Float(), nullable=False),
        sa.Column("model_version", sa.Integer(), nullable=False),
        sa.Column("source", sa.String(16), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
    )
    op.create_index("ix_loop_closures_atlas_created", "loop_closures", ["atlas_id", "created_at"])
    op.create_index("ix_loop_closures_frame_id", "loop_closures", ["frame_id"])


def downgrade() -> None:
    op.drop_table("loop_closures")
    op.drop_table("api_keys")
    op.drop_table("atlas_changes")
    with op.batch_alter_table("atlases") as batch:
        batch.drop_column("revision")
