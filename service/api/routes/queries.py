"""Place-recognition queries."""

from __future__ import annotations

from dataclasses import asdict
from typing import Annotated

from fastapi import APIRouter, File, Form, UploadFile

from service.api.auth import RobotAccess
from service.api.deps import ServiceDep
from service.api.schemas import ErrorOut, QueryOut
from service.api.uploads import read_image_upload
from service.loop_closures import record_if_inter_robot

router = APIRouter(tags=["queries"])


@router.post(
    "/atlases/{atlas}/query",
    response_model=QueryOut,
    responses={
        404: {"model": ErrorOut},
        409: {"model": ErrorOut},
        413: {"model": ErrorOut},
        422: {"model": ErrorOut},
    },
    summary="Find the frames and submap an image revisits",
    description=(
        "Similarity is the cosine of L2-normalised LoopNet embeddings (inner product in FAISS). "
        "`loop_closure` is true when the best similarity reaches the service's threshold."
    ),
)
def query(
    atlas: str,
    service: ServiceDep,
    _: RobotAccess,
    image: Annotated[UploadFile, File(description="JPEG, PNG or WebP image.")],
    k: Annotated[int, Form(ge=1, description="How many candidates to return.")] = 5,
    robot_id: Annotated[
        str | None, Form(description="Only match frames taken by this robot.")
    ] = None,
) -> QueryOut:
    result = service.query(
        atlas_name=atlas,
        image_bytes=read_image_upload(image, service.settings.max_upload_bytes),
        k=k,
        robot_id=robot_id or None,
    )
    record_if_inter_robot(
        service.sessions, robot_id=robot_id or None, result=result, source="query"
    )
    return QueryOut.model_validate(asdict(result))
