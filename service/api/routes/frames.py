"""Adding and reading frames."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, File, Response, UploadFile, status

from service.api.auth import OperatorAccess, RobotAccess
from service.api.deps import RowId, ServiceDep
from service.api.forms import (
    FrameIntrinsics,
    FrameRobot,
    PoseField,
    SubmapName,
    Timestamp,
    frame_fields,
)
from service.api.schemas import ErrorOut, FrameOut, IntrinsicsIn, PoseIn
from service.api.uploads import read_image_upload
from service.app import reads

router = APIRouter(tags=["frames"])
ERRORS: dict[int | str, dict[str, Any]] = {
    404: {"model": ErrorOut, "description": "Unknown atlas or submap"},
    409: {"model": ErrorOut, "description": "The atlas was built with other features"},
    413: {"model": ErrorOut, "description": "Image over the byte or pixel limit"},
    422: {"model": ErrorOut, "description": "Not a decodable image, or a bad field"},
}


@router.post(
    "/atlases/{atlas}/frames",
    response_model=FrameOut,
    status_code=status.HTTP_201_CREATED,
    responses=ERRORS,
    summary="Add a camera frame to a submap",
)
def add_frame(
    atlas: str,
    service: ServiceDep,
    caller: RobotAccess,
    image: Annotated[UploadFile, File(description="JPEG, PNG or WebP image.")],
    submap: SubmapName,
    robot_id: FrameRobot = None,
    timestamp: Timestamp = None,
    pose: PoseField = None,
    intrinsics: FrameIntrinsics = None,
) -> FrameOut:
    frame = service.ingest_frame(
        atlas_name=atlas,
        fields=frame_fields(caller, submap, robot_id, timestamp, pose, intrinsics),
        image_bytes=read_image_upload(image, service.settings.max_upload_bytes),
    )
    return frame_out(reads.FrameRecord(atlas, submap, frame))  # no read-back: names are exact


@router.get(
    "/atlases/{atlas}/frames/{frame_id}",
    response_model=FrameOut,
    responses={404: {"model": ErrorOut}},
    summary="A frame's metadata",
)
def get_frame(atlas: str, frame_id: RowId, service: ServiceDep, _: RobotAccess) -> FrameOut:
    return frame_out(service.reads.frame_record(atlas, frame_id))


def frame_out(record: reads.FrameRecord) -> FrameOut:
    frame = record.frame
    pose = None
    if frame.qw is not None:
        pose = PoseIn(
            rotation=[frame.qw, frame.qx, frame.qy, frame.qz],
            translation=[frame.tx, frame.ty, frame.tz],
        )
    intrinsics = None
    if frame.fx is not None:
        intrinsics = IntrinsicsIn(fx=frame.fx, fy=frame.fy, cx=frame.cx, cy=frame.cy)
    return FrameOut(
        frame_id=frame.id,
        atlas=record.atlas,
        submap=record.submap,
        robot_id=frame.robot_id,
        timestamp=frame.timestamp,
        pose=pose,
        intrinsics=intrinsics,
        width=frame.width,
        height=frame.height,
        keypoints=frame.keypoint_count,
        created_at=frame.created_at,
    )


@router.delete(
    "/atlases/{atlas}/frames/{frame_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    responses={404: {"model": ErrorOut}},
    summary="Delete a frame and its stored features",
    description="Every API process drops it from its index within LOOPNET_SYNC_SECONDS.",
)
def delete_frame(atlas: str, frame_id: RowId, service: ServiceDep, _: OperatorAccess) -> Response:
    service.delete_frame(atlas, frame_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
