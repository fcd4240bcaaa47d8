"""The rows of a snapshot archive (one JSON object a line per member), as validated models.

Each model checks a row with the rules the API applies to what it stores: names and robot ids,
finite numbers, unit-quaternion poses, positive focal lengths, the retraining bounds of a heads
configuration. :mod:`service.fleet.snapshot_rows` reads the members into them.
"""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from service.app.names import NAME_PATTERN
from service.errors import InvalidInput
from service.fleet.snapshot_features import MAX_DIM
from service.ml.geometry import Intrinsics, Pose

NAME = NAME_PATTERN.pattern  # the API's pattern for atlases, submaps, robots

Name = Annotated[str, Field(pattern=NAME)]
Finite = Annotated[float, Field(allow_inf_nan=False)]
RowId = Annotated[int, Field(ge=1, le=2**62)]


class _Row(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)


class AtlasRow(_Row):
    name: str = Field(max_length=64)
    description: str = Field(max_length=1000)
    feature_signature: dict[str, Any]
    created_at: datetime


class SubmapRow(_Row):
    id: RowId
    name: Name
    created_at: datetime


class FrameRow(_Row):
    id: RowId
    submap_id: RowId
    robot_id: Name
    timestamp: Finite | None
    qw: Finite | None
    qx: Finite | None
    qy: Finite | None
    qz: Finite | None
    tx: Finite | None
    ty: Finite | None
    tz: Finite | None
    fx: Finite | None
    fy: Finite | None
    cx: Finite | None
    cy: Finite | None
    width: int = Field(ge=1, le=1_000_000)
    height: int = Field(ge=1, le=1_000_000)
    keypoint_count: int = Field(ge=0, le=1_000_000)
    created_at: datetime

    def check_geometry(self) -> None:
        pose = (self.qw, self.qx, self.qy, self.qz, self.tx, self.ty, self.tz)
        if any(v is not None for v in pose):
            if any(v is None for v in pose):
                raise InvalidInput("a pose needs all of qw, qx, qy, qz, tx, ty, tz")
            Pose.from_lists(list(pose[:4]), list(pose[4:]))  # type: ignore[arg-type]
        intrinsics = (self.fx, self.fy, self.cx, self.cy)
        if any(v is not None for v in intrinsics):
            if any(v is None for v in intrinsics):
                raise InvalidInput("intrinsics need all of fx, fy, cx, cy")
            Intrinsics(*intrinsics)  # type: ignore[arg-type]


class HeadsRow(_Row):
    local_dim: int = Field(ge=1, le=MAX_DIM)
    global_dim: int = Field(ge=1, le=MAX_DIM)
    alpha: Finite = Field(ge=0.0, le=1.0)
    hidden_dim: int = Field(ge=1, le=MAX_DIM)
    embed_dim: int | None = Field(ge=2, le=MAX_DIM)


class CalibrationRow(BaseModel):
    """A calibrated version's ``config.calibration`` (its ``path`` is rewritten at restore)."""

    model_config = ConfigDict(extra="forbid", strict=True)

    path: str = Field(max_length=1000)
    version: int = Field(ge=1, le=999_999_999)
    frames_at_fit: int = Field(ge=0)
    min_inliers: dict[str, Any] | None = None


class VersionConfigRow(BaseModel):
    model_config = ConfigDict(extra="allow", strict=True)  # training records its parameters

    heads: HeadsRow
    trained: bool
    calibration: CalibrationRow | None = None  # absent: the uncalibrated blend


class ModelVersionRow(_Row):
    version: int = Field(ge=1, le=999_999_999)
    config: VersionConfigRow
    metrics: dict[str, Any]
    is_active: bool
    created_at: datetime
    weights: str | None  # required key: null for untrained heads rebuilt from the config
    calibration_file: str | None = None  # a calibrated version's member (absent: none)


class RelativePoseRow(_Row):
    """A verified closure's relative pose (see :class:`service.ml.verification.RelativePose`)."""

    rotation: tuple[Finite, Finite, Finite, Finite]
    translation: tuple[Finite, Finite, Finite]


class LoopClosureRow(_Row):
    robot_id: Name
    frame_id: RowId
    matched_robot_id: Name
    submap_id: RowId
    similarity: Finite
    model_version: int = Field(ge=1)
    source: Literal["query", "observe"]
    created_at: datetime
    inliers: int | None = Field(None, ge=0)  # absent from archives written before them
    relative_pose: RelativePoseRow | None = None
    query_frame_id: RowId | None = None  # the observing frame (absent: a query, or older)
