"""Bodies of the browsing endpoints (``routes/browse.py``); no heavy imports, so the client
can use them."""

from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, Field

from service.api.schemas import FrameOut, RelativePoseOut


class CallerOut(BaseModel):
    name: str
    role: str
    atlases: list[str]
    auth_enforced: bool


class LoopClosureDetailOut(BaseModel):
    id: int
    robot_id: str = Field(description="The robot whose query or observation closed the loop.")
    matched_robot_id: str
    similarity: float
    inliers: int | None = Field(description="RANSAC inliers of the match (None: not verified).")
    relative_pose: RelativePoseOut | None
    model_version: int
    source: str
    created_at: datetime
    frame: FrameOut = Field(description="The matched frame.")
    query_thumbnail: bool = Field(description="Whether the query image's thumbnail was kept.")
    query_frame_id: int | None = Field(
        description="The frame an observation stored (None for a query, which stores none); "
        "its matches can be drawn."
    )


class MatchedFrameOut(BaseModel):
    frame_id: int
    width: int = Field(description="Width of the decoded frame, the points' pixel frame.")
    height: int


class ClosureMatchesOut(BaseModel):
    closure_id: int
    query_frame: MatchedFrameOut = Field(description="The frame the observation stored.")
    frame: MatchedFrameOut = Field(description="The matched frame.")
    matcher: str
    matches: int = Field(description="Tentative matches given to RANSAC.")
    inliers: int = Field(
        description="RANSAC inliers, recomputed now from the stored keypoints (they may differ "
        "slightly from those recorded when the loop closed)."
    )
    model: str = Field(description="essential, fundamental or none.")
    relative_pose: RelativePoseOut | None
    pairs: list[list[float]] = Field(
        description="[x_query, y_query, x_frame, y_frame] per inlier (at most `limit`), each in "
        "its frame's decoded-image pixels."
    )


class RobotOut(BaseModel):
    robot_id: str
    frames: int
    first_timestamp: float | None
    last_timestamp: float | None
    last_frame_at: datetime


class KeypointsOut(BaseModel):
    frame_id: int
    width: int = Field(description="Width of the decoded frame, the keypoints' pixel frame.")
    height: int
    total: int = Field(description="Keypoints stored for the frame.")
    keypoints: list[list[float]] = Field(description="[x, y] of the strongest, best first.")
