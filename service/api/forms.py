"""Form fields shared by the upload routes (frames, observe, queries, precomputed features),
and their parsing into domain objects: one definition per field, one parser per JSON field."""

from __future__ import annotations

from typing import Annotated

from fastapi import Form

from service.api.auth import acting_robot
from service.api.schemas import IntrinsicsIn, PoseIn
from service.api.uploads import parse_json_field
from service.atlas_service import AtlasService
from service.auth import Principal
from service.errors import InvalidInput
from service.geometry import Intrinsics, Pose
from service.query_filters import QueryFilter

# ----- a new frame ---------------------------------------------------------------------------

SubmapName = Annotated[str, Form(description="Name of an existing submap.")]
FrameRobot = Annotated[
    str | None,
    Form(description="The robot that took the frame; a robot key's own robot when left out."),
]
Timestamp = Annotated[float | None, Form(description="Capture time, seconds.")]
PoseField = Annotated[
    str | None,
    Form(description='JSON: {"rotation": [w, x, y, z], "translation": [x, y, z]}'),
]
FrameIntrinsics = Annotated[
    str | None, Form(description='JSON: {"fx": .., "fy": .., "cx": .., "cy": ..}')
]


def frame_robot(caller: Principal, robot_id: str | None) -> str:
    """The robot a new frame belongs to: the one named, or the robot key's own robot."""
    robot = acting_robot(caller, robot_id or None)
    if not robot:
        raise InvalidInput("robot_id is required (only a robot key may leave it out)")
    return robot


def pose_from_form(raw: str | None) -> Pose | None:
    parsed = parse_json_field("pose", raw, PoseIn)
    return Pose.from_lists(parsed.rotation, parsed.translation) if parsed else None


# ----- a query ---------------------------------------------------------------------------------

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
QueryIntrinsics = Annotated[
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
