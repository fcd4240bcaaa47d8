"""Revisit pairs: the training pairs of adaptation jobs (verified closures ``observe`` recorded,
and pairs operators label or delete)."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Annotated

from fastapi import APIRouter, Query, Response, status

from service.api.auth import OperatorAccess
from service.api.deps import RowId, ServiceDep
from service.api.schemas import ErrorOut
from service.api.schemas_admin import PairIn, PairOut
from service.app import revisit_pairs
from service.app.names import validate_name

router = APIRouter(tags=["revisit pairs"])
ERRORS: dict[int | str, dict[str, object]] = {
    404: {"model": ErrorOut, "description": "Unknown atlas, frame or pair"},
    422: {"model": ErrorOut},
}


def pair_out(row: revisit_pairs.PairRow) -> PairOut:
    pair = row.pair
    return PairOut(
        id=pair.id,
        frame_id=pair.frame_id,
        other_frame_id=pair.other_frame_id,
        robot_id=row.robot_id,
        other_robot_id=row.other_robot_id,
        submap=row.submap,
        other_submap=row.other_submap,
        source=pair.source,
        inliers=pair.inliers,
        created_at=pair.created_at,
    )


def _utc(moment: datetime | None) -> datetime | None:
    if moment is not None and moment.tzinfo is None:
        return moment.replace(tzinfo=UTC)
    return moment


@router.get(
    "/atlases/{atlas}/pairs",
    response_model=list[PairOut],
    responses=ERRORS,
    summary="Revisit pairs, newest first",
    description="Verified closures recorded by observe and pairs labelled by operators: what "
    "an adapt job learns from.",
)
def list_pairs(
    atlas: str,
    service: ServiceDep,
    _: OperatorAccess,
    robot: Annotated[str | None, Query(description="Only pairs with a frame of it.")] = None,
    submap: Annotated[str | None, Query(description="Only pairs with a frame in it.")] = None,
    since: Annotated[datetime | None, Query(description="Only pairs recorded from then.")] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
) -> list[PairOut]:
    if robot is not None:
        validate_name("robot", robot)
    if submap is not None:
        validate_name("submap", submap)
    where = revisit_pairs.PairFilter(
        robots=(robot,) if robot else (), submaps=(submap,) if submap else (), since=_utc(since)
    )
    rows = service.pairs.list(atlas, where, limit)
    return [pair_out(row) for row in rows]


@router.post(
    "/atlases/{atlas}/pairs",
    response_model=PairOut,
    status_code=status.HTTP_201_CREATED,
    responses={**ERRORS, 409: {"model": ErrorOut, "description": "The pair exists"}},
    summary="Label two frames of the atlas as one place",
)
def create_pair(atlas: str, body: PairIn, service: ServiceDep, _: OperatorAccess) -> PairOut:
    return pair_out(service.pairs.label(atlas, body.frame_id, body.other_frame_id))


@router.delete(
    "/atlases/{atlas}/pairs/{pair_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    responses=ERRORS,
    summary="Delete a wrong revisit pair",
)
def delete_pair(atlas: str, pair_id: RowId, service: ServiceDep, _: OperatorAccess) -> Response:
    service.pairs.delete(atlas, pair_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
