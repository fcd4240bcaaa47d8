"""Initial schema: atlases, submaps, frames, per-frame features, model versions.

Revision ID: 0001
Revises:
Create Date: 2026-11-23
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "atlases",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column("name", sa.String(64), nullable=False, unique=True),
        sa.Column("description", sa.String(1000), nullable=False),
        sa.Column("feature_signature", sa.JSON(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
    )
    op.create_table(
        "submaps",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column(
            "atlas_id",
            sa.Integer(),
            sa.ForeignKey("atlases.id", ondelete="CASCADE"),
            nullable=False,
        ),
        sa.Column("name", sa.String(128), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.UniqueConstraint("atlas_id", "name", name="uq_submaps_atlas_name"),
    )
    op.create_index("ix_submaps_atlas_id", "submaps", ["atlas_id"])
    op.create_table(
        "frames",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column(
            "atlas_id",
            sa.Integer(),
            sa.ForeignKey("atlases.id", ondelete="CASCADE"),
            nullable=False,
        ),
        sa.Column(
            "submap_id",
            sa.Integer(),
            sa.ForeignKey("submaps.id", ondelete="CASCADE"),
            nullable=False,
        ),
        sa.Column("robot_id", sa.String(128), nullable=False),
        sa.Column("timestamp", sa.Float()),
        *(sa.Column(name, sa.Float()) for name in ("qw", "qx", "qy", "qz", "tx", "ty", "tz")),
        *(sa.Column(name, sa.Float()) for name in ("fx", "fy", "cx", "cy")),
        sa.Column("width", sa.Integer(), nullable=False),
        sa.Column("height", sa.Integer(), nullable=False),
        sa.Column("keypoint_count", sa.Integer(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sqlite_autoincrement=True,
    )
    op.create_index("ix_frames_atlas_id", "frames", ["atlas_id"])
    op.create_index("ix_frames_submap_id", "frames", ["submap_id"])
    op.create_index("ix_frames_atlas_robot", "frames", ["atlas_id", "robot_id"])
    op.create_table(
        "frame_features",
        sa.Column(
            "frame_id",
            sa.Integer(),
            sa.ForeignKey("frames.id", ondelete="CASCADE"),
            primary_key=True,
        ),
        sa.Column("descriptor_dim", sa.Integer(), nullable=False),
        sa.Column("global_dim", sa.Integer(), nullable=False),
        sa.Column("keypoints", sa.LargeBinary(), nullable=False),
        sa.Column("descriptors", sa.LargeBinary(), nullable=False),
        sa.Column("scores", sa.LargeBinary(), nullable=False),
        sa.Column("local_vector", sa.LargeBinary(), nullable=False),
        sa.Column("global_vector", sa.LargeBinary(), nullable=False),
    )
    op.create_table(
        "model_versions",
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column(
            "atlas_id",
            sa.Integer(),
            sa.ForeignKey("atlases.id", ondelete="CASCADE"),
            nullable=False,
        ),
        sa.Column("version", sa.Integer(), nullable=False),
        sa.Column("config", sa.JSON(), nullable=False),
        sa.Column("metrics", sa.JSON(), nullable=False),
        sa.Column("weights_path", sa.String(1024)),
        sa.Column("is_active", sa.Boolean(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.UniqueConstraint("atlas_id", "version", name="uq_model_versions_atlas"),
    )
    op.create_index("ix_model_versions_atlas_id", "model_versions", ["atlas_id"])


def downgrade() -> None:
    op.drop_table("model_versions")
    op.drop_table("frame_features")
    op.drop_table("frames")
    op.drop_table("submaps")
    op.drop_table("atlases")
