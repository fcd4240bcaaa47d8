"""Place-recognition queries, and observations (query then insert) for robots running SLAM."""

from __future__ import annotations

from dataclasses import asdict
from typing import Annotated, Any

from fastapi import APIRouter, File, Form, UploadFile

from service.api.auth import RobotAccess, acting_robot
from service.api.deps import ServiceDep
from service.api.schemas import ErrorOut, IntrinsicsIn, ObserveOut, PoseIn, QueryOut
from service.api.uploads import parse_json_field, read_image_upload
from service.atlas_service import AtlasService
from service.geometry import Intrinsics, Pose
from service.loop_closures import record_if_inter_robot
from service.query_filters import QueryFilter

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

RobotId = Annotated[
    str | None,
    Form(
        description="The robot asking: its recent frames are excluded; needed by robots=own|others."
    ),
]
Robots = Annotated[
    str, Form(description="Which frames may match: 'all' (default), 'own' or 'others'.")
]
SubmapFilter = Annotated[str | None, Form(description="Only frames of this submap.")]
Since = Annotated[float | None, Form(description="Only frames with timestamp >= since.")]
Until = Annotated[float | None, Form(description="Only frames with timestamp <= until.")]
ExcludeFrames = Annotated[
    int | None,
    Form(description="Override: the asking robot's last N frames never match (default setting)."),
]
ExcludeSeconds = Annotated[
    float | None,
    Form(description="Override: nor its frames within T seconds of the query (default setting)."),
]
IntrinsicsField = Annotated[
    str | None,
    Form(description='JSON {"fx", "fy", "cx", "cy"} of the query image: gives relative poses.'),
]


def intrinsics_from_form(raw: str | None) -> Intrinsics | None:
    parsed = parse_json_field("intrinsics", raw, IntrinsicsIn)
    return Intrinsics(**parsed.model_dump()) if parsed else None


def filter_from_form(
    service: AtlasService,
    robot_id: str | None,
    robots: str,
    submap: str | None,
    since: float | None,
    until: float | None,
    timestamp: float | None,
    exclude_recent_frames: int | None,
    exclude_recent_seconds: float | None,
) -> QueryFilter:
    return service.query_filter(
        robot_id=robot_id or None,
        robots=robots,
        submap=submap or None,
        since=since,
        until=until,
        timestamp=timestamp,
        exclude_recent_frames=exclude_recent_frames,
        exclude_recent_seconds=exclude_recent_seconds,
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
    k: Annotated[int, Form(ge=1, description="How many candidates to return.")] = 5,
    robot_id: RobotId = None,
    robots: Robots = "all",
    submap: SubmapFilter = None,
    since: Since = None,
    until: Until = None,
    timestamp: Annotated[
        float | None, Form(description="Capture time of the query image, seconds.")
    ] = None,
    intrinsics: IntrinsicsField = None,
    exclude_recent_frames: ExcludeFrames = None,
    exclude_recent_seconds: ExcludeSeconds = None,
) -> QueryOut:
    robot_id = acting_robot(caller, robot_id)
    query_filter = filter_from_form(
        service,
        robot_id,
        robots,
        submap,
        since,
        until,
        timestamp,
        exclude_recent_frames,
        exclude_recent_seconds,
    )
    result = service.query(
        atlas_name=atlas,
        image_bytes=read_image_upload(image, service.settings.max_upload_bytes),
        k=k,
        query_filter=query_filter,
        intrinsics=intrinsics_from_form(intrinsics),
    )
    record_if_inter_robot(
        service.sessions, robot_id=robot_id or None, result=result, source="query"
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
    robot_id: Annotated[str, Form(description="The robot that took the frame.")],
    timestamp: Annotated[float | None, Form(description="Capture time, seconds.")] = None,
    pose: Annotated[
        str | None,
        Form(description='JSON: {"rotation": [w, x, y, z], "translation": [x, y, z]}'),
    ] = None,
    intrinsics: IntrinsicsField = None,
    k: Annotated[int, Form(ge=1, description="How many candidates to return.")] = 5,
    robots: Robots = "all",
    submap_filter: Annotated[
        str | None, Form(description="Only match frames of this submap.")
    ] = None,
    since: Since = None,
    until: Until = None,
    exclude_recent_frames: ExcludeFrames = None,
    exclude_recent_seconds: ExcludeSeconds = None,
) -> ObserveOut:
    robot_id = acting_robot(caller, robot_id) or robot_id
    pose_in = parse_json_field("pose", pose, PoseIn)
    query_filter = filter_from_form(
        service,
        robot_id,
        robots,
        submap_filter,
        since,
        until,
        timestamp,
        exclude_recent_frames,
        exclude_recent_seconds,
    )
    result, frame = service.observe(
        atlas_name=atlas,
        submap_name=submap,
        robot_id=robot_id,
        image_bytes=read_image_upload(image, service.settings.max_upload_bytes),
        timestamp=timestamp,
        pose=Pose.from_lists(pose_in.rotation, pose_in.translation) if pose_in else None,
        intrinsics=intrinsics_from_form(intrinsics),
        k=k,
        query_filter=query_filter,
    )
    record_if_inter_robot(service.sessions, robot_id=robot_id, result=result, source="observe")
    return ObserveOut.model_validate({**asdict(result), "frame_id": frame.id})
