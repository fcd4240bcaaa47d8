"""Form fields shared by the upload routes (frames, observe, queries, precomputed features),
and their parsing into domain objects: one definition per field, one parser per JSON field."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Annotated

from fastapi import Depends, Form

from service.api.auth import acting_robot
from service.api.schemas import IntrinsicsIn, PoseIn
from service.api.uploads import parse_json_field
from service.app.filters import QueryFilter, make_filter
from service.app.ingest import FrameFields
from service.config import Settings
from service.errors import InvalidInput
from service.fleet.keys import Principal
from service.ml.geometry import Intrinsics, Pose

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


def frame_fields(
    caller: Principal,
    submap: str,
    robot_id: str | None,
    timestamp: float | None,
    pose: str | None,
    intrinsics: str | None,
) -> FrameFields:
    """A frame upload's form fields as the one value ingest and observe take."""
    return FrameFields(
        submap,
        frame_robot(caller, robot_id),
        timestamp=timestamp,
        pose=pose_from_form(pose),
        intrinsics=intrinsics_from_form(intrinsics),
    )


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
SequenceLength = Annotated[
    int | None,
    Form(
        ge=0,
        description="Frames of the robot's recent sequence to score (0: off; default: the "
        "service's LOOPNET_SEQUENCE_LENGTH). Needs robot_id.",
    ),
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


@dataclass(frozen=True)
class FilterFields:
    """The filter fields of a query form; the robot asking and the timestamp come from the
    route (they mean more there: who acts, when the frame was taken)."""

    robots: str
    submap: str | None
    since: float | None
    until: float | None
    exclude_recent_frames: int | None
    exclude_recent_seconds: float | None

    def build(
        self, settings: Settings, *, robot_id: str | None, timestamp: float | None
    ) -> QueryFilter:
        """The validated filter (before any CNN runs)."""
        return make_filter(settings, robot_id=robot_id, timestamp=timestamp, **asdict(self))


def filter_fields(
    robots: Robots = "all",
    submap: SubmapFilter = None,
    since: Since = None,
    until: Until = None,
    exclude_recent_frames: ExcludeFrames = None,
    exclude_recent_seconds: ExcludeSeconds = None,
) -> FilterFields:
    return FilterFields(robots, submap, since, until, exclude_recent_frames, exclude_recent_seconds)


def observe_filter_fields(
    robots: Robots = "all",
    submap_filter: Annotated[
        str | None, Form(description="Only match frames of this submap.")
    ] = None,
    since: Since = None,
    until: Until = None,
    exclude_recent_frames: ExcludeFrames = None,
    exclude_recent_seconds: ExcludeSeconds = None,
) -> FilterFields:
    """As :func:`filter_fields`; an observation's own ``submap`` is where its frame goes."""
    return FilterFields(
        robots, submap_filter, since, until, exclude_recent_frames, exclude_recent_seconds
    )


QueryFilterForm = Annotated[FilterFields, Depends(filter_fields)]
ObserveFilterForm = Annotated[FilterFields, Depends(observe_filter_fields)]
