"""Place-recognition queries, and observations (query then insert) for robots running SLAM."""

from __future__ import annotations

from dataclasses import asdict
from typing import Annotated, Any

from fastapi import APIRouter, File, Form, UploadFile

from service.api.auth import RobotAccess, acting_robot
from service.api.deps import ServiceDep
from service.api.forms import (
    FrameRobot,
    ObserveFilterForm,
    PoseField,
    QueryFilterForm,
    QueryIntrinsics,
    RobotId,
    SequenceLength,
    Timestamp,
    frame_fields,
    frame_robot,
    intrinsics_from_form,
)
from service.api.schemas import ErrorOut, ObserveOut, QueryOut
from service.api.uploads import read_image_upload

router = APIRouter(tags=["queries"])
ERRORS: dict[int | str, dict[str, Any]] = {
    404: {"model": ErrorOut, "description": "Unknown atlas or submap"},
    409: {"model": ErrorOut, "description": "The atlas was built with other features"},
    413: {"model": ErrorOut, "description": "Image over the byte or pixel limit"},
    422: {"model": ErrorOut, "description": "Not a decodable image, or a bad field or filter"},
}
DECISION = (
    "Candidates are the frames with the highest cosine similarity of L2-normalised LoopNet "
    "embeddings; the best few are verified (local-feature matches + RANSAC) and re-ranked by "
    "inliers. `loop_closure` is true when the best similarity reaches the threshold and that "
    "candidate is verified. The asking robot's own most recent frames never match."
)


@router.post(
    "/atlases/{atlas}/query",
    response_model=QueryOut,
    responses=ERRORS,
    summary="Find the frames and submap an image revisits",
    description=DECISION,
)
def query(
    atlas: str,
    service: ServiceDep,
    caller: RobotAccess,
    image: Annotated[UploadFile, File(description="JPEG, PNG or WebP image.")],
    filters: QueryFilterForm,
    k: Annotated[int, Form(ge=1, description="How many candidates to return.")] = 5,
    robot_id: RobotId = None,
    timestamp: Annotated[
        float | None, Form(description="Capture time of the query image, seconds.")
    ] = None,
    intrinsics: QueryIntrinsics = None,
    sequence_length: SequenceLength = None,
) -> QueryOut:
    robot_id = acting_robot(caller, robot_id)
    query_filter = filters.build(service.settings, robot_id=robot_id, timestamp=timestamp)
    result = service.query(
        atlas_name=atlas,
        image_bytes=read_image_upload(image, service.settings.max_upload_bytes),
        k=k,
        robot_id=robot_id or None,
        query_filter=query_filter,
        intrinsics=intrinsics_from_form(intrinsics),
        sequence_length=sequence_length,
    )
    return QueryOut.model_validate(asdict(result))


@router.post(
    "/atlases/{atlas}/observe",
    response_model=ObserveOut,
    status_code=201,
    responses=ERRORS,
    summary="A robot's new keyframe: query the atlas, then add the frame",
    description=DECISION
    + " The frame is inserted after the query (it never matches itself); if the insert "
    "fails, nothing is written.",
)
def observe(
    atlas: str,
    service: ServiceDep,
    caller: RobotAccess,
    image: Annotated[UploadFile, File(description="JPEG, PNG or WebP image.")],
    submap: Annotated[str, Form(description="Submap the new frame is added to.")],
    filters: ObserveFilterForm,
    robot_id: FrameRobot = None,
    timestamp: Timestamp = None,
    pose: PoseField = None,
    intrinsics: QueryIntrinsics = None,
    k: Annotated[int, Form(ge=1, description="How many candidates to return.")] = 5,
    sequence_length: SequenceLength = None,
) -> ObserveOut:
    robot_id = frame_robot(caller, robot_id)
    query_filter = filters.build(service.settings, robot_id=robot_id, timestamp=timestamp)
    result, frame = service.observe(
        atlas_name=atlas,
        fields=frame_fields(caller, submap, robot_id, timestamp, pose, intrinsics),
        image_bytes=read_image_upload(image, service.settings.max_upload_bytes),
        k=k,
        query_filter=query_filter,
        sequence_length=sequence_length,
    )
    return ObserveOut.model_validate({**asdict(result), "frame_id": frame.id})
