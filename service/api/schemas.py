"""Request and response bodies of the HTTP API (pydantic), documented in the OpenAPI spec."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from pydantic import BaseModel, Field


class ErrorOut(BaseModel):
    detail: str = Field(description="What is wrong, in words.")
    error: str = Field(description="The error's type, e.g. NotFound, InvalidImage.")


class AtlasIn(BaseModel):
    name: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$", examples=["campus"])
    description: str = Field("", max_length=1000)


class AtlasOut(BaseModel):
    name: str
    description: str
    created_at: datetime
    submaps: int
    frames: int
    active_model_version: int
    classifier_trained: bool = Field(
        description="Whether the active model version has a trained classification head."
    )
    feature_signature: dict[str, Any] = Field(
        description="Extractor and backbone settings every frame of this atlas was described with."
    )


class SubmapIn(BaseModel):
    name: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$", examples=["corridor-3"])


class SubmapOut(BaseModel):
    name: str
    frames: int
    created_at: datetime


class PoseIn(BaseModel):
    """Camera-to-world pose, sent as a JSON string in the ``pose`` form field."""

    rotation: list[float] = Field(description="Unit quaternion [w, x, y, z].")
    translation: list[float] = Field(description="Translation [x, y, z] in metres.")


class IntrinsicsIn(BaseModel):
    """Pinhole intrinsics in pixels, sent as a JSON string in the ``intrinsics`` form field."""

    fx: float
    fy: float
    cx: float
    cy: float


class FrameOut(BaseModel):
    frame_id: int
    atlas: str
    submap: str
    robot_id: str
    timestamp: float | None
    pose: PoseIn | None
    intrinsics: IntrinsicsIn | None
    width: int
    height: int
    keypoints: int
    created_at: datetime


class CandidateOut(BaseModel):
    frame_id: int
    submap: str
    robot_id: str
    similarity: float = Field(
        description=(
            "Cosine similarity of the query's and the frame's L2-normalised LoopNet embeddings, "
            "in [-1, 1]; 1 means identical embeddings."
        )
    )


class SubmapPredictionOut(BaseModel):
    available: bool = Field(description="False until a retrain job has trained the classifier.")
    submap: str | None = None
    probability: float | None = Field(None, description="Softmax probability of that submap.")
    reason: str | None = Field(None, description="Why no prediction is given, when unavailable.")


class QueryOut(BaseModel):
    atlas: str
    model_version: int
    match: CandidateOut | None = Field(description="The best match, or null on an empty atlas.")
    candidates: list[CandidateOut] = Field(description="The top-k frames, best first.")
    loop_closure: bool = Field(description="Whether the best similarity reaches the threshold.")
    threshold: float
    predicted_submap: SubmapPredictionOut
    keypoints: int = Field(description="Local keypoints found in the query image.")
    timings_ms: dict[str, float] = Field(
        description="Milliseconds per stage: decode, local_features, global_features, heads, "
        "search, total."
    )


class ModelVersionOut(BaseModel):
    version: int
    is_active: bool
    trained: bool
    config: dict[str, Any]
    metrics: dict[str, Any]
    created_at: datetime


class HealthOut(BaseModel):
    status: str


class ReadyOut(BaseModel):
    ready: bool
    detail: str
    preset: str | None = None
    backbone: str | None = None
    local_extractor: str | None = None
