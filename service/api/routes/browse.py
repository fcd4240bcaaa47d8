"""Read endpoints for looking around an atlas (the console uses them): the caller, frames by
robot or submap, each robot's activity, and frame thumbnails."""

from __future__ import annotations

from typing import Annotated

import numpy as np
from fastapi import APIRouter, Query, Request, Response
from sqlalchemy import func, select
from sqlalchemy.orm import Session, selectinload

from service import thumbnails
from service.api.auth import RobotAccess, get_authenticator
from service.api.deps import RowId, ServiceDep
from service.api.routes.frames import frame_out
from service.api.schemas import ErrorOut, FrameOut, RelativePoseOut
from service.api.schemas_browse import CallerOut, KeypointsOut, LoopClosureDetailOut, RobotOut
from service.atlas_service import validate_name
from service.errors import NotFound
from service.storage import repository as repo
from service.storage.feature_store import load_local_features
from service.storage.models import Atlas, Frame, LoopClosure, LoopClosureThumbnail

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
    with service.sessions() as session:
        found = repo.get_atlas(session, name=atlas)
        query = select(Frame).where(Frame.atlas_id == found.id).options(selectinload(Frame.submap))
        if robot is not None:
            query = query.where(Frame.robot_id == validate_name("robot", robot))
        if submap is not None:
            query = query.where(
                Frame.submap_id == repo.get_submap(session, atlas=found, name=submap).id
            )
        query = query.order_by(Frame.timestamp.is_(None), Frame.timestamp, Frame.id)
        frames = session.scalars(query.offset(offset).limit(limit))
        return [frame_out(found.name, frame) for frame in frames]


@router.get(
    "/atlases/{atlas}/robots",
    response_model=list[RobotOut],
    responses={404: {"model": ErrorOut}},
    summary="The robots that added frames to the atlas, with counts and last activity",
)
def list_robots(atlas: str, service: ServiceDep, _: RobotAccess) -> list[RobotOut]:
    with service.sessions() as session:
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
    return [
        RobotOut(
            robot_id=robot_id,
            frames=count,
            first_timestamp=first,
            last_timestamp=last,
            last_frame_at=last_at,
        )
        for robot_id, count, first, last, last_at in rows
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
    with service.sessions() as session:
        frame = repo.get_frame(
            session, atlas=repo.get_atlas(session, name=atlas), frame_id=frame_id
        )
        local = load_local_features(session, [frame_id]).get(frame_id)
        width, height = frame.width, frame.height
    if local is None:
        raise NotFound(f"frame {frame_id} has no stored features")
    best = np.argsort(-local.scores, kind="stable")[:limit]
    return KeypointsOut(
        frame_id=frame_id,
        width=width,
        height=height,
        total=local.count,
        keypoints=np.round(local.keypoints[best], 1).tolist(),
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
    with service.sessions() as session:
        found = repo.get_atlas(session, name=atlas)
        repo.get_frame(session, atlas=found, frame_id=frame_id)
        jpeg = thumbnails.get_thumbnail(session, frame_id=frame_id)
    return _jpeg(jpeg)


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


def _closure(session: Session, atlas: str, closure_id: int) -> tuple[Atlas, LoopClosure]:
    found = repo.get_atlas(session, name=atlas)
    row = session.get(LoopClosure, closure_id)
    if row is None or row.atlas_id != found.id:
        raise NotFound(f"loop closure {closure_id} does not exist in atlas '{atlas}'")
    return found, row


@router.get(
    "/atlases/{atlas}/loop-closures/{closure_id}",
    response_model=LoopClosureDetailOut,
    responses={404: {"model": ErrorOut}},
    summary="One loop closure: the matched frame, inliers and relative pose",
)
def loop_closure(
    atlas: str, closure_id: RowId, service: ServiceDep, _: RobotAccess
) -> LoopClosureDetailOut:
    with service.sessions() as session:
        found, row = _closure(session, atlas, closure_id)
        kept = session.get(LoopClosureThumbnail, row.id) is not None
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
            frame=frame_out(
                found.name, repo.get_frame(session, atlas=found, frame_id=row.frame_id)
            ),
            query_thumbnail=kept,
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
    with service.sessions() as session:
        _closure(session, atlas, closure_id)
        kept = session.get(LoopClosureThumbnail, closure_id)
        jpeg = kept.jpeg if kept is not None else None
    return _jpeg(jpeg)
