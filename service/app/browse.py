"""What the console reads to look around an atlas: frames by robot or submap, each robot's
activity, a frame's keypoints and thumbnail, and one loop closure with its images."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.orm import Session, selectinload, sessionmaker

from service.app import thumbnails
from service.app.names import validate_name
from service.app.reads import FrameRecord
from service.errors import NotFound
from service.storage import repository as repo
from service.storage.feature_store import load_local_features
from service.storage.models import Atlas, Frame, LoopClosure

Sessions = sessionmaker[Session]


@dataclass(frozen=True)
class RobotActivity:
    robot_id: str
    frames: int
    first_timestamp: float | None
    last_timestamp: float | None
    last_frame_at: datetime


@dataclass(frozen=True)
class FrameKeypoints:
    frame_id: int
    width: int
    height: int
    total: int
    keypoints: list[list[float]]  # [x, y], strongest first


@dataclass(frozen=True)
class ClosureRecord:
    closure: LoopClosure
    frame: FrameRecord  # the matched frame
    query_thumbnail: bool  # whether the query image's thumbnail was kept


def closure_row(session: Session, atlas: Atlas, closure_id: int) -> LoopClosure:
    """A loop closure of the atlas (NotFound when it is another atlas's or absent)."""
    row = session.get(LoopClosure, closure_id)
    if row is None or row.atlas_id != atlas.id:
        raise NotFound(f"loop closure {closure_id} does not exist in atlas '{atlas.name}'")
    return row


def _closure(session: Session, atlas: str, closure_id: int) -> tuple[Atlas, LoopClosure]:
    found = repo.get_atlas(session, name=atlas)
    return found, closure_row(session, found, closure_id)


class Browse:
    """What the console reads to look around an atlas, each read in one session of its own."""

    def __init__(self, sessions: Sessions) -> None:
        self.sessions = sessions

    def frames(
        self,
        atlas: str,
        *,
        robot: str | None = None,
        submap: str | None = None,
        offset: int = 0,
        limit: int = 100,
    ) -> list[FrameRecord]:
        """Frames in time order (by timestamp, frames without one last, then id)."""
        with self.sessions() as session:
            found = repo.get_atlas(session, name=atlas)
            query = (
                select(Frame).where(Frame.atlas_id == found.id).options(selectinload(Frame.submap))
            )
            if robot is not None:
                query = query.where(Frame.robot_id == validate_name("robot", robot))
            if submap is not None:
                query = query.where(
                    Frame.submap_id == repo.get_submap(session, atlas=found, name=submap).id
                )
            query = query.order_by(Frame.timestamp.is_(None), Frame.timestamp, Frame.id)
            rows = session.scalars(query.offset(offset).limit(limit))
            return [FrameRecord(found.name, frame.submap.name, frame) for frame in rows]

    def robots(self, atlas: str) -> list[RobotActivity]:
        """The robots that added frames, with their frame counts and last activity."""
        with self.sessions() as session:
            found = repo.get_atlas(session, name=atlas)
            rows = session.execute(
                select(
                    Frame.robot_id,
                    func.count(Frame.id),
                    func.min(Frame.timestamp),
                    func.max(Frame.timestamp),
                    func.max(Frame.created_at),
                )
                .where(Frame.atlas_id == found.id)
                .group_by(Frame.robot_id)
                .order_by(Frame.robot_id)
            ).all()
        return [RobotActivity(*row) for row in rows]

    def keypoints(self, atlas: str, frame_id: int, limit: int) -> FrameKeypoints:
        """A frame's ``limit`` strongest stored keypoints, in decoded-image pixels."""
        with self.sessions() as session:
            frame = repo.get_frame(
                session, atlas=repo.get_atlas(session, name=atlas), frame_id=frame_id
            )
            local = load_local_features(session, [frame_id]).get(frame_id)
            width, height = frame.width, frame.height
        if local is None:
            raise NotFound(f"frame {frame_id} has no stored features")
        best = np.argsort(-local.scores, kind="stable")[:limit]
        points: list[list[float]] = np.round(local.keypoints[best], 1).tolist()
        return FrameKeypoints(frame_id, width, height, local.count, points)

    def frame_thumbnail(self, atlas: str, frame_id: int) -> bytes | None:
        """The frame's thumbnail (None: stored before thumbnails; NotFound: no such frame)."""
        with self.sessions() as session:
            repo.get_frame(session, atlas=repo.get_atlas(session, name=atlas), frame_id=frame_id)
            return thumbnails.frame_thumbnail(session, frame_id)

    def loop_closure(self, atlas: str, closure_id: int) -> ClosureRecord:
        with self.sessions() as session:
            found, row = _closure(session, atlas, closure_id)
            frame = repo.get_frame(session, atlas=found, frame_id=row.frame_id)
            kept = thumbnails.closure_thumbnail(session, row.id) is not None
            return ClosureRecord(row, FrameRecord(found.name, frame.submap.name, frame), kept)

    def closure_thumbnail(self, atlas: str, closure_id: int) -> bytes | None:
        """The query image's thumbnail of a loop closure (None when not kept)."""
        with self.sessions() as session:
            _closure(session, atlas, closure_id)
            return thumbnails.closure_thumbnail(session, closure_id)
