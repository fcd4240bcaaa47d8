"""Inter-robot loop closures: a robot recognised a place that another robot mapped.

Each query and each observation whose answer is a loop closure onto a frame
taken by a different robot than the one asking is recorded, so a fleet's map-merging back end
can list the links between the robots' trajectories.
"""

from __future__ import annotations

from dataclasses import asdict
from datetime import datetime

from sqlalchemy import or_, select
from sqlalchemy.orm import Session, sessionmaker

from service.app.results import QueryResult
from service.storage.db import transaction
from service.storage.models import Frame, LoopClosure, LoopClosureThumbnail, Submap

SOURCES = ("query", "observe")


def record_if_inter_robot(
    sessions: sessionmaker[Session],
    *,
    robot_id: str | None,
    result: QueryResult,
    source: str,
    query_frame_id: int | None = None,
) -> int | None:
    """Record ``result`` when it closes a loop onto another robot's frame; returns the row id.

    ``query_frame_id``: the frame an observation stored (its keypoints let the matches be
    redrawn later); a query stores none."""
    assert source in SOURCES, source
    match = result.match
    if robot_id is None or not result.loop_closure or match is None:
        return None
    if match.robot_id == robot_id:
        return None
    with transaction(sessions) as session:
        frame = session.get(Frame, match.frame_id)
        if frame is None:  # deleted since the search
            return None
        row = LoopClosure(
            atlas_id=frame.atlas_id,
            robot_id=robot_id,
            frame_id=frame.id,
            matched_robot_id=frame.robot_id,
            submap_id=frame.submap_id,
            similarity=float(match.similarity),
            model_version=result.model_version,
            source=source,
            inliers=match.inliers,
            relative_pose=asdict(match.relative_pose) if match.relative_pose else None,
            query_frame_id=query_frame_id,
        )
        session.add(row)
        session.flush()
        if result.query_thumbnail is not None:
            session.add(LoopClosureThumbnail(loop_closure_id=row.id, jpeg=result.query_thumbnail))
        return row.id


def list_loop_closures(
    session: Session,
    *,
    atlas_id: int,
    robot: str | None = None,
    since: datetime | None = None,
    limit: int = 100,
) -> list[tuple[LoopClosure, str]]:
    """Newest first, with the matched frame's submap name; ``robot`` matches either side."""
    query = (
        select(LoopClosure, Submap.name)
        .join(Submap, Submap.id == LoopClosure.submap_id)
        .where(LoopClosure.atlas_id == atlas_id)
    )
    if robot is not None:
        query = query.where(
            or_(LoopClosure.robot_id == robot, LoopClosure.matched_robot_id == robot)
        )
    if since is not None:
        query = query.where(LoopClosure.created_at >= since)
    query = query.order_by(LoopClosure.created_at.desc(), LoopClosure.id.desc()).limit(limit)
    return [(row, name) for row, name in session.execute(query)]
