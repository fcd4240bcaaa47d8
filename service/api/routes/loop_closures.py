"""Inter-robot loop closures found by queries (and observations)."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Annotated

from fastapi import APIRouter, Query

from service.api.auth import RobotAccess
from service.api.deps import ServiceDep
from service.api.schemas import ErrorOut, LoopClosureOut
from service.app.names import validate_name

router = APIRouter(tags=["loop closures"])


@router.get(
    "/atlases/{atlas}/loop-closures",
    response_model=list[LoopClosureOut],
    responses={404: {"model": ErrorOut}, 422: {"model": ErrorOut}},
    summary="Loop closures between robots, newest first",
    description=(
        "Recorded when a query sent with `robot_id` is a loop closure onto a frame another "
        "robot took."
    ),
)
def loop_closures(
    atlas: str,
    service: ServiceDep,
    _: RobotAccess,
    robot: Annotated[
        str | None, Query(description="Only closures this robot took part in.")
    ] = None,
    since: Annotated[datetime | None, Query(description="Only closures found at or after.")] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
) -> list[LoopClosureOut]:
    if robot is not None:
        validate_name("robot", robot)
    if since is not None and since.tzinfo is None:
        since = since.replace(tzinfo=UTC)
    rows = service.reads.loop_closures(atlas, robot=robot, since=since, limit=limit)
    return [
        LoopClosureOut(
            id=row.id,
            robot_id=row.robot_id,
            frame_id=row.frame_id,
            matched_robot_id=row.matched_robot_id,
            submap=submap,
            similarity=row.similarity,
            model_version=row.model_version,
            source=row.source,
            created_at=row.created_at,
        )
        for row, submap in rows
    ]
