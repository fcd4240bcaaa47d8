"""Typed, keyword-only queries on the atlas schema; domain errors instead of ``None``."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from service.errors import Conflict, NotFound
from service.ml.features import FrameFeatures
from service.ml.geometry import Intrinsics, Pose
from service.storage.feature_store import to_row
from service.storage.models import (
    Atlas,
    Frame,
    FrameProposals,
    FrameThumbnail,
    ModelVersion,
    Submap,
)


def create_atlas(
    session: Session, *, name: str, description: str, feature_signature: dict[str, Any]
) -> Atlas:
    if session.scalar(select(Atlas.id).where(Atlas.name == name)) is not None:
        raise Conflict(f"atlas '{name}' already exists")
    atlas = Atlas(name=name, description=description, feature_signature=feature_signature)
    session.add(atlas)
    try:
        session.flush()
    except IntegrityError as exc:  # a concurrent create won the race
        raise Conflict(f"atlas '{name}' already exists") from exc
    return atlas


def get_atlas(session: Session, *, name: str) -> Atlas:
    atlas = session.scalar(select(Atlas).where(Atlas.name == name))
    if atlas is None:
        raise NotFound(f"atlas '{name}' does not exist")
    return atlas


def list_atlases(session: Session) -> list[Atlas]:
    """Every atlas but those a snapshot restore is still writing (named with a leading '.',
    which atlas names cannot start with)."""
    query = select(Atlas).where(~Atlas.name.startswith(".")).order_by(Atlas.name)
    return list(session.scalars(query))


def count_frames(session: Session, *, atlas_id: int, submap_id: int | None = None) -> int:
    query = select(func.count(Frame.id)).where(Frame.atlas_id == atlas_id)
    if submap_id is not None:
        query = query.where(Frame.submap_id == submap_id)
    return int(session.scalar(query) or 0)


def count_submaps(session: Session, *, atlas_id: int) -> int:
    return int(
        session.scalar(select(func.count(Submap.id)).where(Submap.atlas_id == atlas_id)) or 0
    )


def count_populated_submaps(session: Session, *, atlas_id: int) -> int:
    """Submaps of the atlas that hold at least one frame."""
    query = select(func.count(func.distinct(Frame.submap_id))).where(Frame.atlas_id == atlas_id)
    return int(session.scalar(query) or 0)


def create_submap(session: Session, *, atlas: Atlas, name: str) -> Submap:
    exists = select(Submap.id).where(Submap.atlas_id == atlas.id, Submap.name == name)
    if session.scalar(exists) is not None:
        raise Conflict(f"submap '{name}' already exists in atlas '{atlas.name}'")
    submap = Submap(atlas_id=atlas.id, name=name)
    session.add(submap)
    try:
        session.flush()
    except IntegrityError as exc:
        raise Conflict(f"submap '{name}' already exists in atlas '{atlas.name}'") from exc
    return submap


def get_submap(session: Session, *, atlas: Atlas, name: str) -> Submap:
    submap = session.scalar(select(Submap).where(Submap.atlas_id == atlas.id, Submap.name == name))
    if submap is None:
        raise NotFound(f"submap '{name}' does not exist in atlas '{atlas.name}'")
    return submap


def list_submaps_with_counts(session: Session, *, atlas: Atlas) -> list[tuple[Submap, int]]:
    query = (
        select(Submap, func.count(Frame.id))
        .outerjoin(Frame, Frame.submap_id == Submap.id)
        .where(Submap.atlas_id == atlas.id)
        .group_by(Submap.id)
        .order_by(Submap.id)
    )
    return [(submap, int(n)) for submap, n in session.execute(query)]


def submap_names(session: Session, *, atlas_id: int) -> dict[int, str]:
    rows = session.execute(select(Submap.id, Submap.name).where(Submap.atlas_id == atlas_id))
    return {int(i): name for i, name in rows}


def add_frame(
    session: Session,
    *,
    atlas: Atlas,
    submap: Submap,
    robot_id: str,
    timestamp: float | None,
    pose: Pose | None,
    intrinsics: Intrinsics | None,
    features: FrameFeatures,
    proposals: Sequence[int] | None = None,
    loop_frame_id: int | None = None,
    loop_pending: bool = False,
) -> Frame:
    """Insert a frame and its features in the caller's transaction; returns it with its id.

    ``proposals``: the frames the frame's own search returned, best first (an observation's),
    kept for sequence scoring (:class:`~service.storage.models.FrameProposals`), with the frame
    its observation closed a loop with (``loop_frame_id``; ``loop_pending``: a loop left to a
    later frame to confirm)."""
    width, height = features.image_size
    frame = Frame(
        atlas_id=atlas.id,
        submap_id=submap.id,
        robot_id=robot_id,
        timestamp=timestamp,
        width=width,
        height=height,
        keypoint_count=features.local.count,
    )
    if pose is not None:
        frame.qw, frame.qx, frame.qy, frame.qz = pose.rotation
        frame.tx, frame.ty, frame.tz = pose.translation
    if intrinsics is not None:
        frame.fx, frame.fy = intrinsics.fx, intrinsics.fy
        frame.cx, frame.cy = intrinsics.cx, intrinsics.cy
    session.add(frame)
    session.flush()
    session.add(to_row(frame.id, features))
    if features.thumbnail is not None:
        session.add(FrameThumbnail(frame_id=frame.id, jpeg=features.thumbnail))
    if proposals is not None:
        ids = np.asarray(proposals, dtype="<i4")
        session.add(
            FrameProposals(
                frame_id=frame.id,
                frame_ids=ids.tobytes(),
                loop_frame_id=loop_frame_id,
                loop_pending=loop_pending,
            )
        )
    session.flush()
    return frame


class Kept(NamedTuple):
    """What an observed frame's observation kept: its search's proposals (int64 frame ids,
    best first), the frame it closed a loop with (None: no loop) and whether that loop waits
    for a later frame to confirm it."""

    proposals: np.ndarray
    loop_frame_id: int | None
    loop_pending: bool = False


def frame_proposals(session: Session, *, frame_ids: Sequence[int]) -> dict[int, Kept]:
    """What the observations of those of ``frame_ids`` that have a row kept, in one read."""
    if not frame_ids:
        return {}
    rows = session.execute(
        select(
            FrameProposals.frame_id,
            FrameProposals.frame_ids,
            FrameProposals.loop_frame_id,
            FrameProposals.loop_pending,
        ).where(FrameProposals.frame_id.in_(list(frame_ids)))
    )
    return {
        int(i): Kept(np.frombuffer(blob, dtype="<i4").astype(np.int64), loop, bool(pending))
        for i, blob, loop, pending in rows
    }


def get_frame(session: Session, *, atlas: Atlas, frame_id: int) -> Frame:
    frame = session.get(Frame, frame_id)
    if frame is None or frame.atlas_id != atlas.id:
        raise NotFound(f"frame {frame_id} does not exist in atlas '{atlas.name}'")
    return frame


def frames_by_id(session: Session, *, frame_ids: list[int]) -> dict[int, Frame]:
    if not frame_ids:
        return {}
    return {f.id: f for f in session.scalars(select(Frame).where(Frame.id.in_(frame_ids)))}


def frame_ids_and_robots(session: Session, *, atlas_id: int) -> dict[int, str]:
    rows = session.execute(select(Frame.id, Frame.robot_id).where(Frame.atlas_id == atlas_id))
    return {int(i): robot for i, robot in rows}


def frame_times(
    session: Session, *, atlas_id: int, frame_ids: list[int] | None = None
) -> list[tuple[int, str, float | None]]:
    """``(id, robot, timestamp)`` of an atlas's frames (or of ``frame_ids``), in id order."""
    query = select(Frame.id, Frame.robot_id, Frame.timestamp).where(Frame.atlas_id == atlas_id)
    if frame_ids is not None:
        query = query.where(Frame.id.in_(frame_ids))
    return [(int(i), r, t) for i, r, t in session.execute(query.order_by(Frame.id))]


def recent_robot_frames(
    session: Session, *, atlas_id: int, robot_id: str, limit: int
) -> list[tuple[int, float | None]]:
    """``(id, timestamp)`` of a robot's last ``limit`` frames in arrival order, oldest first."""
    rows = session.execute(
        select(Frame.id, Frame.timestamp)
        .where(Frame.atlas_id == atlas_id, Frame.robot_id == robot_id)
        .order_by(Frame.id.desc())
        .limit(limit)
    )
    return [(int(i), t) for i, t in rows][::-1]


def robot_frames_newest_first(
    session: Session, *, atlas_id: int, robot_id: str, offset: int, limit: int
) -> np.ndarray:
    """A robot's frame ids newest first (ids grow with arrival), ``limit`` from ``offset``."""
    query = (
        select(Frame.id)
        .where(Frame.atlas_id == atlas_id, Frame.robot_id == robot_id)
        .order_by(Frame.id.desc())
        .offset(offset)
        .limit(limit)
    )
    return np.fromiter(session.scalars(query), np.int64)


def frame_ids_of_submap(session: Session, *, submap_id: int) -> list[int]:
    return [int(i) for i in session.scalars(select(Frame.id).where(Frame.submap_id == submap_id))]


def create_model_version(
    session: Session,
    *,
    atlas_id: int,
    config: dict[str, Any],
    metrics: dict[str, Any],
    weights_path: str | None,
    activate: bool,
) -> ModelVersion:
    latest = session.scalar(
        select(func.max(ModelVersion.version)).where(ModelVersion.atlas_id == atlas_id)
    )
    version = ModelVersion(
        atlas_id=atlas_id,
        version=int(latest or 0) + 1,
        config=config,
        metrics=metrics,
        weights_path=weights_path,
        is_active=False,
    )
    session.add(version)
    session.flush()
    if activate:
        activate_model_version(session, atlas_id=atlas_id, version=version.version)
    return version


def activate_model_version(session: Session, *, atlas_id: int, version: int) -> ModelVersion:
    versions = list(session.scalars(select(ModelVersion).where(ModelVersion.atlas_id == atlas_id)))
    chosen = next((v for v in versions if v.version == version), None)
    if chosen is None:
        raise NotFound(f"model version {version} does not exist for this atlas")
    for v in versions:
        v.is_active = v.version == version
    session.flush()
    return chosen


def active_model_version(session: Session, *, atlas_id: int) -> ModelVersion:
    version = session.scalar(
        select(ModelVersion).where(ModelVersion.atlas_id == atlas_id, ModelVersion.is_active)
    )
    if version is None:
        raise NotFound(f"atlas {atlas_id} has no active model version")
    return version


def list_model_versions(session: Session, *, atlas_id: int) -> list[ModelVersion]:
    query = select(ModelVersion).where(ModelVersion.atlas_id == atlas_id)
    return list(session.scalars(query.order_by(ModelVersion.version)))
