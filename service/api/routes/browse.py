"""Read endpoints for looking around an atlas (the console uses them): the caller, frames by
robot or submap, each robot's activity, and frame thumbnails."""

from __future__ import annotations

from dataclasses import asdict
from typing import Annotated

from fastapi import APIRouter, Query, Request, Response

from service.api.auth import RobotAccess, get_authenticator
from service.api.deps import RowId, ServiceDep
from service.api.routes.frames import frame_out
from service.api.schemas import ErrorOut, FrameOut, RelativePoseOut
from service.api.schemas_browse import (
    CallerOut,
    ClosureMatchesOut,
    KeypointsOut,
    LoopClosureDetailOut,
    MatchedFrameOut,
    RobotOut,
)
from service.ml import thumbnails

router = APIRouter(tags=["browse"])


@router.get("/whoami", response_model=CallerOut, summary="The caller's key: name, role, atlases")
def whoami(request: Request, caller: RobotAccess) -> CallerOut:
    return CallerOut(
        name=caller.name,
        role=caller.role.name,
        atlases=list(caller.atlases),
        auth_enforced=get_authenticator(request).enforced(),
    )


@router.get(
    "/atlases/{atlas}/frames",
    response_model=list[FrameOut],
    responses={404: {"model": ErrorOut}, 422: {"model": ErrorOut}},
    summary="Frames of the atlas in time order (by timestamp, then id)",
)
def list_frames(
    atlas: str,
    service: ServiceDep,
    _: RobotAccess,
    robot: Annotated[str | None, Query(description="Only this robot's frames.")] = None,
    submap: Annotated[str | None, Query(description="Only this submap's frames.")] = None,
    offset: Annotated[int, Query(ge=0, le=10_000_000)] = 0,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
) -> list[FrameOut]:
    records = service.browse.frames(atlas, robot=robot, submap=submap, offset=offset, limit=limit)
    return [frame_out(record) for record in records]


@router.get(
    "/atlases/{atlas}/robots",
    response_model=list[RobotOut],
    responses={404: {"model": ErrorOut}},
    summary="The robots that added frames to the atlas, with counts and last activity",
)
def list_robots(atlas: str, service: ServiceDep, _: RobotAccess) -> list[RobotOut]:
    return [
        RobotOut(
            robot_id=row.robot_id,
            frames=row.frames,
            first_timestamp=row.first_timestamp,
            last_timestamp=row.last_timestamp,
            last_frame_at=row.last_frame_at,
        )
        for row in service.browse.robots(atlas)
    ]


@router.get(
    "/atlases/{atlas}/frames/{frame_id}/keypoints",
    response_model=KeypointsOut,
    responses={404: {"model": ErrorOut}},
    summary="A frame's strongest stored keypoints (to draw them over the frame)",
)
def keypoints(
    atlas: str,
    frame_id: RowId,
    service: ServiceDep,
    _: RobotAccess,
    limit: Annotated[int, Query(ge=1, le=10_000)] = 500,
) -> KeypointsOut:
    found = service.browse.keypoints(atlas, frame_id, limit)
    return KeypointsOut(
        frame_id=found.frame_id,
        width=found.width,
        height=found.height,
        total=found.total,
        keypoints=found.keypoints,
    )


@router.get(
    "/atlases/{atlas}/frames/{frame_id}/thumbnail",
    response_class=Response,
    responses={
        200: {"content": {thumbnails.MEDIA_TYPE: {}}, "description": "A small JPEG"},
        404: {"model": ErrorOut},
    },
    summary="A frame's thumbnail (a placeholder for frames stored without one)",
)
def thumbnail(atlas: str, frame_id: RowId, service: ServiceDep, _: RobotAccess) -> Response:
    return _jpeg(service.browse.frame_thumbnail(atlas, frame_id))


def _jpeg(jpeg: bytes | None) -> Response:
    """A stored thumbnail (ids are never reused, so it never changes), or the placeholder."""
    if jpeg is None:
        return Response(
            thumbnails.placeholder(),
            media_type=thumbnails.MEDIA_TYPE,
            headers={"Cache-Control": "private, max-age=60", "X-Thumbnail": "placeholder"},
        )
    return Response(
        jpeg, media_type=thumbnails.MEDIA_TYPE, headers={"Cache-Control": "private, max-age=86400"}
    )


@router.get(
    "/atlases/{atlas}/loop-closures/{closure_id}",
    response_model=LoopClosureDetailOut,
    responses={404: {"model": ErrorOut}},
    summary="One loop closure: the matched frame, inliers and relative pose",
)
def loop_closure(
    atlas: str, closure_id: RowId, service: ServiceDep, _: RobotAccess
) -> LoopClosureDetailOut:
    found = service.browse.loop_closure(atlas, closure_id)
    row = found.closure
    return LoopClosureDetailOut(
        id=row.id,
        robot_id=row.robot_id,
        matched_robot_id=row.matched_robot_id,
        similarity=row.similarity,
        inliers=row.inliers,
        relative_pose=RelativePoseOut(**row.relative_pose) if row.relative_pose else None,
        model_version=row.model_version,
        source=row.source,
        created_at=row.created_at,
        frame=frame_out(found.frame),
        query_thumbnail=found.query_thumbnail,
        query_frame_id=row.query_frame_id,
    )


@router.get(
    "/atlases/{atlas}/loop-closures/{closure_id}/matches",
    response_model=ClosureMatchesOut,
    responses={
        404: {
            "model": ErrorOut,
            "description": "Unknown closure, or one from a query (only observed frames are kept)",
        },
        409: {"model": ErrorOut, "description": "The atlas was built with other features"},
    },
    summary="A loop closure's verified matches, recomputed from both frames' stored keypoints",
)
def loop_closure_matches(
    atlas: str,
    closure_id: RowId,
    service: ServiceDep,
    _: RobotAccess,
    limit: Annotated[int, Query(ge=1, le=10_000, description="Inlier pairs at most.")] = 1000,
) -> ClosureMatchesOut:
    found = service.closure_matches(atlas, closure_id, limit)
    return ClosureMatchesOut(
        closure_id=found.closure_id,
        query_frame=MatchedFrameOut(**asdict(found.query_frame)),
        frame=MatchedFrameOut(**asdict(found.frame)),
        matcher=found.matcher,
        matches=found.matches,
        inliers=found.inliers,
        model=found.model,
        relative_pose=RelativePoseOut(**asdict(found.relative_pose))
        if found.relative_pose
        else None,
        pairs=found.pairs,
    )


@router.get(
    "/atlases/{atlas}/loop-closures/{closure_id}/query-thumbnail",
    response_class=Response,
    responses={200: {"content": {thumbnails.MEDIA_TYPE: {}}}, 404: {"model": ErrorOut}},
    summary="The thumbnail of the query image that closed the loop (or a placeholder)",
)
def loop_closure_thumbnail(
    atlas: str, closure_id: RowId, service: ServiceDep, _: RobotAccess
) -> Response:
    return _jpeg(service.browse.closure_thumbnail(atlas, closure_id))
