"""The atlas schema. Alembic migrations in ``migrations/`` create it; never ``create_all``."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    String,
    TypeDecorator,
    UniqueConstraint,
    false,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship

from service.domain.statuses import JobStatus as JobStatus


def utcnow() -> datetime:
    return datetime.now(UTC)


class UTCDateTime(TypeDecorator[datetime]):
    """Timezone-aware UTC datetimes on every backend (SQLite stores them naive)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: datetime | None, _dialect: object) -> datetime | None:
        if value is not None and value.tzinfo is not None:
            value = value.astimezone(UTC)
        return value

    def process_result_value(self, value: datetime | None, _dialect: object) -> datetime | None:
        if value is not None and value.tzinfo is None:
            value = value.replace(tzinfo=UTC)
        return value


class Base(DeclarativeBase):
    type_annotation_map = {dict[str, Any]: JSON}


class Atlas(Base):
    """A shared map: submaps of frames, embedded with one feature signature."""

    __tablename__ = "atlases"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(64), unique=True)
    description: Mapped[str] = mapped_column(String(1000), default="")
    feature_signature: Mapped[dict[str, Any]]
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    # Bumped by every transaction that adds or removes frames, as its last statement: the row
    # lock orders those transactions by commit, so API processes catch up without missing any
    # (see service/change_feed.py).
    revision: Mapped[int] = mapped_column(BigInteger, default=0, server_default="0")

    submaps: Mapped[list[Submap]] = relationship(
        back_populates="atlas", cascade="all, delete-orphan", passive_deletes=True
    )


class Submap(Base):
    """A short sequence of frames of one place (the paper's S_i)."""

    __tablename__ = "submaps"
    __table_args__ = (UniqueConstraint("atlas_id", "name", name="uq_submaps_atlas_name"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    atlas_id: Mapped[int] = mapped_column(ForeignKey("atlases.id", ondelete="CASCADE"), index=True)
    name: Mapped[str] = mapped_column(String(128))
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)

    atlas: Mapped[Atlas] = relationship(back_populates="submaps")


class Frame(Base):
    """One camera frame; its id is also its id in the atlas's FAISS index."""

    __tablename__ = "frames"
    # AUTOINCREMENT on SQLite: a deleted frame's id is never reused, so a stale index file can
    # never attach an old vector to a new frame.
    __table_args__ = (
        Index("ix_frames_atlas_robot", "atlas_id", "robot_id"),
        {"sqlite_autoincrement": True},
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    atlas_id: Mapped[int] = mapped_column(ForeignKey("atlases.id", ondelete="CASCADE"), index=True)
    submap_id: Mapped[int] = mapped_column(ForeignKey("submaps.id", ondelete="CASCADE"), index=True)
    robot_id: Mapped[str] = mapped_column(String(128))
    timestamp: Mapped[float | None] = mapped_column(Float)
    # Pose (camera-to-world): unit quaternion (w, x, y, z) and translation in metres.
    qw: Mapped[float | None] = mapped_column(Float)
    qx: Mapped[float | None] = mapped_column(Float)
    qy: Mapped[float | None] = mapped_column(Float)
    qz: Mapped[float | None] = mapped_column(Float)
    tx: Mapped[float | None] = mapped_column(Float)
    ty: Mapped[float | None] = mapped_column(Float)
    tz: Mapped[float | None] = mapped_column(Float)
    # Pinhole intrinsics in pixels of the uploaded image.
    fx: Mapped[float | None] = mapped_column(Float)
    fy: Mapped[float | None] = mapped_column(Float)
    cx: Mapped[float | None] = mapped_column(Float)
    cy: Mapped[float | None] = mapped_column(Float)
    width: Mapped[int] = mapped_column(Integer)
    height: Mapped[int] = mapped_column(Integer)
    keypoint_count: Mapped[int] = mapped_column(Integer)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)

    submap: Mapped[Submap] = relationship()
    features: Mapped[FrameFeatureRow] = relationship(
        cascade="all, delete-orphan", passive_deletes=True, uselist=False
    )


class FrameFeatureRow(Base):
    """The CNN outputs of a frame, stored once so retraining never reruns the CNNs.

    Arrays are raw little-endian bytes: keypoints float32 (N x 2), descriptors float16
    (N x descriptor_dim), scores float32 (N), local_vector float32 (descriptor_dim),
    global_vector float16 (global_dim; float32 in rows written before the layout pooling).
    """

    __tablename__ = "frame_features"

    frame_id: Mapped[int] = mapped_column(
        ForeignKey("frames.id", ondelete="CASCADE"), primary_key=True
    )
    descriptor_dim: Mapped[int] = mapped_column(Integer)
    global_dim: Mapped[int] = mapped_column(Integer)
    keypoints: Mapped[bytes] = mapped_column(LargeBinary)
    descriptors: Mapped[bytes] = mapped_column(LargeBinary)
    scores: Mapped[bytes] = mapped_column(LargeBinary)
    local_vector: Mapped[bytes] = mapped_column(LargeBinary)
    global_vector: Mapped[bytes] = mapped_column(LargeBinary)


class ModelVersion(Base):
    """A version of an atlas's heads; exactly one per atlas is active."""

    __tablename__ = "model_versions"
    __table_args__ = (UniqueConstraint("atlas_id", "version", name="uq_model_versions_atlas"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    atlas_id: Mapped[int] = mapped_column(ForeignKey("atlases.id", ondelete="CASCADE"), index=True)
    version: Mapped[int] = mapped_column(Integer)
    config: Mapped[dict[str, Any]]
    metrics: Mapped[dict[str, Any]]
    # None: the untrained initial heads, rebuilt exactly from ``config``.
    weights_path: Mapped[str | None] = mapped_column(String(1024))
    is_active: Mapped[bool] = mapped_column(Boolean, default=False)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)


class Job(Base):
    """A queued piece of work (retraining) as the API reports it; the queue holds only its id."""

    __tablename__ = "jobs"
    __table_args__ = (Index("ix_jobs_atlas_status", "atlas_id", "status"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    atlas_id: Mapped[int] = mapped_column(ForeignKey("atlases.id", ondelete="CASCADE"))
    kind: Mapped[str] = mapped_column(String(32))
    # queued -> running -> succeeded | failed | cancelled (or queued -> cancelled)
    status: Mapped[str] = mapped_column(String(16), default=JobStatus.QUEUED.value)
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    message: Mapped[str] = mapped_column(String(500), default="")
    params: Mapped[dict[str, Any]]
    metrics: Mapped[dict[str, Any]]
    error: Mapped[str | None] = mapped_column(String(4000))
    cancel_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    model_version: Mapped[int | None] = mapped_column(Integer)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime())
    updated_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)


class AtlasChange(Base):
    """One frame added to or removed from an atlas, or a model version activated, at the atlas
    revision that did it."""

    __tablename__ = "atlas_changes"
    __table_args__ = (Index("ix_atlas_changes_atlas_revision", "atlas_id", "revision"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    atlas_id: Mapped[int] = mapped_column(ForeignKey("atlases.id", ondelete="CASCADE"))
    revision: Mapped[int] = mapped_column(BigInteger)
    # "add" | "remove" | "activate"; no foreign keys: a removed frame's row is gone
    op: Mapped[str] = mapped_column(String(8))
    frame_id: Mapped[int | None] = mapped_column(Integer)  # add, remove
    model_version: Mapped[int | None] = mapped_column(Integer)  # activate
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)


class ApiKey(Base):
    """An API key: only the SHA-256 of the token is stored; the token is shown once."""

    __tablename__ = "api_keys"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    name: Mapped[str] = mapped_column(String(128))
    role: Mapped[str] = mapped_column(String(16))  # robot | operator | admin
    # Atlas names the key may touch; an empty list means every atlas.
    atlases: Mapped[list[str]] = mapped_column(JSON)
    prefix: Mapped[str] = mapped_column(String(16))  # the token's first characters, for humans
    key_hash: Mapped[str] = mapped_column(String(64), unique=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    revoked_at: Mapped[datetime | None] = mapped_column(UTCDateTime())


class LoopClosure(Base):
    """A loop closure between robots: a query by one robot matched a frame another one took."""

    __tablename__ = "loop_closures"
    __table_args__ = (Index("ix_loop_closures_atlas_created", "atlas_id", "created_at"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    atlas_id: Mapped[int] = mapped_column(ForeignKey("atlases.id", ondelete="CASCADE"))
    robot_id: Mapped[str] = mapped_column(String(128))  # the robot that asked
    frame_id: Mapped[int] = mapped_column(ForeignKey("frames.id", ondelete="CASCADE"), index=True)
    matched_robot_id: Mapped[str] = mapped_column(String(128))
    submap_id: Mapped[int] = mapped_column(ForeignKey("submaps.id", ondelete="CASCADE"))
    similarity: Mapped[float] = mapped_column(Float)
    model_version: Mapped[int] = mapped_column(Integer)
    source: Mapped[str] = mapped_column(String(16))  # query | observe
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
    # what verification found (None when not verified): RANSAC inliers and the relative pose
    # {"rotation": [w, x, y, z], "translation": [x, y, z]} of the query camera to the frame's
    inliers: Mapped[int | None] = mapped_column(Integer)
    relative_pose: Mapped[dict[str, Any] | None] = mapped_column(JSON)
    # the observing robot's frame stored by the same ``observe`` call (None for a ``query``,
    # which keeps no frame, or once that frame is deleted): matches are redrawn from its keypoints
    query_frame_id: Mapped[int | None] = mapped_column(
        ForeignKey("frames.id", ondelete="SET NULL"), index=True
    )


class FrameThumbnail(Base):
    """A small JPEG of a frame (see service/ml/thumbnails.py): the only image data kept."""

    __tablename__ = "frame_thumbnails"

    frame_id: Mapped[int] = mapped_column(
        ForeignKey("frames.id", ondelete="CASCADE"), primary_key=True
    )
    jpeg: Mapped[bytes] = mapped_column(LargeBinary)


class FrameProposals(Base):
    """The frames an observed frame's own search returned (best first, int32 little-endian
    ids, the filter of its request applied): the places it proposes when it is one of its
    robot's recent frames in a later request's sequence. Derived data: a frame without a row
    (stored by ``POST /frames``, or restored from a snapshot) is searched again instead.
    ``loop_frame_id``: the frame its observation closed a loop with (None: no loop), which the
    robot's next observation may continue (loop tracking); a plain id, the frame may have been
    deleted since. ``loop_pending``: that loop was not answered yet, it waits for a later
    observation answered at once to confirm it (service.ml.sequences.distinctiveness.CONFIRM_Z)."""

    __tablename__ = "frame_proposals"

    frame_id: Mapped[int] = mapped_column(
        ForeignKey("frames.id", ondelete="CASCADE"), primary_key=True
    )
    frame_ids: Mapped[bytes] = mapped_column(LargeBinary)
    loop_frame_id: Mapped[int | None] = mapped_column(Integer, nullable=True)
    loop_pending: Mapped[bool] = mapped_column(Boolean, default=False, server_default=false())


class LoopClosureThumbnail(Base):
    """The thumbnail of the query image that closed a loop (a query keeps no frame)."""

    __tablename__ = "loop_closure_thumbnails"

    loop_closure_id: Mapped[int] = mapped_column(
        ForeignKey("loop_closures.id", ondelete="CASCADE"), primary_key=True
    )
    jpeg: Mapped[bytes] = mapped_column(LargeBinary)


class RevisitPair(Base):
    """Two stored frames of one place, a training pair for adaptation (service/jobs/adaptation):
    a closure ``observe`` verified (its new frame and the frame it matched, inliers at or above
    the atlas's minimum), or a pair an operator labelled. Deleting either frame deletes it."""

    __tablename__ = "revisit_pairs"
    __table_args__ = (
        UniqueConstraint("frame_id", "other_frame_id", name="uq_revisit_pairs_frames"),
        Index("ix_revisit_pairs_atlas_created", "atlas_id", "created_at"),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    atlas_id: Mapped[int] = mapped_column(ForeignKey("atlases.id", ondelete="CASCADE"))
    # the frame that revisits (an observation's new frame) and the one it matched
    frame_id: Mapped[int] = mapped_column(ForeignKey("frames.id", ondelete="CASCADE"), index=True)
    other_frame_id: Mapped[int] = mapped_column(
        ForeignKey("frames.id", ondelete="CASCADE"), index=True
    )
    source: Mapped[str] = mapped_column(String(16))  # observe | sequence | operator
    # None: labelled by an operator, or a sequence's loop frame that was not verified
    inliers: Mapped[int | None] = mapped_column(Integer)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime(), default=utcnow)
