"""What operators and admins send and read: jobs (one parameter schema per kind), API keys,
revisit pairs. The answers robots read are in :mod:`service.api.schemas`."""

from __future__ import annotations

from dataclasses import asdict
from datetime import datetime
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, model_validator
from pydantic.dataclasses import dataclass as pydantic_dataclass

from service.api.closed_sets import (
    JobKindValue,
    JobStatusValue,
    RoleName,
)
from service.domain.statuses import (
    AggregatorName,
)
from service.jobs.adaptation_config import AdaptConfig
from service.ml.calibration_config import CalibrationConfig
from service.ml.training import TrainingConfig


@pydantic_dataclass(frozen=True, config=ConfigDict(extra="forbid"))
class RetrainParams(TrainingConfig):
    """Parameters of a retraining job; every field has a default."""


class CalibrateParams(BaseModel):
    """Parameters of a calibration job; every field has a default."""

    model_config = ConfigDict(extra="forbid")

    aggregator: AggregatorName = Field(
        CalibrationConfig.aggregator,
        description="How a frame's local descriptors become one vector.",
    )
    words: int | None = Field(
        CalibrationConfig.words,
        ge=2,
        le=1024,
        description="VLAD vocabulary size; null: 16,384 values over the descriptor's length "
        "(DISK 128 words, XFeat 256), what automatic calibrations and the harness fit.",
    )
    alpha: float = Field(
        CalibrationConfig.alpha, ge=0, le=1, description="Weight of the local branch in the fusion."
    )


@pydantic_dataclass(frozen=True, config=ConfigDict(extra="forbid"))
class AdaptParams(AdaptConfig):
    """Parameters of an adaptation job; every field has a default."""


JOB_PARAMS = {"retrain": "params", "calibrate": "calibration", "adapt": "adaptation"}


class JobIn(BaseModel):
    model_config = ConfigDict(extra="forbid")

    kind: JobKindValue = Field(
        "retrain",
        description="'retrain': train the heads (on the latest calibration); 'calibrate': fit "
        "the atlas's calibration (local aggregation, branch whitening, calibrated score) on "
        "its stored features; 'adapt': learn a whitening from the atlas's revisit pairs "
        "(verified closures and labelled pairs). Each writes a new model version, activated "
        "when not worse than the active one.",
    )
    params: RetrainParams = Field(
        default_factory=RetrainParams, description="A retraining's parameters."
    )
    calibration: CalibrateParams = Field(
        default_factory=CalibrateParams, description="A calibration's parameters."
    )
    adaptation: AdaptParams = Field(
        default_factory=AdaptParams, description="An adaptation's parameters."
    )

    @model_validator(mode="after")
    def _parameters_of_its_kind(self) -> JobIn:
        for kind, other in JOB_PARAMS.items():
            if kind != self.kind and other in self.model_fields_set:
                raise ValueError(f"'{other}' does not apply to a {self.kind} job")
        return self

    def job_params(self) -> dict[str, Any]:
        if self.kind == "calibrate":
            return self.calibration.model_dump()
        if self.kind == "adapt":
            dumped: dict[str, Any] = TypeAdapter(AdaptParams).dump_python(
                self.adaptation, mode="json", exclude_defaults=True
            )
            return dumped
        return asdict(self.params)


class JobOut(BaseModel):
    id: int
    atlas: str
    kind: str
    status: JobStatusValue
    progress: float = Field(description="0..100")
    message: str
    params: dict[str, Any]
    metrics: dict[str, Any]
    error: str | None
    model_version: int | None = Field(description="The version a successful job created.")
    cancel_requested: bool
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    updated_at: datetime


class ApiKeyIn(BaseModel):
    model_config = ConfigDict(extra="forbid")

    name: str = Field(min_length=1, max_length=128, examples=["husky-1"])
    role: RoleName
    atlases: list[str] = Field(
        default_factory=list, description="Atlases the key may use; empty: every atlas."
    )


class ApiKeyOut(BaseModel):
    id: int
    name: str
    role: str
    atlases: list[str]
    prefix: str = Field(description="The token's first characters, to recognise it.")
    created_at: datetime
    revoked_at: datetime | None


class NewApiKeyOut(ApiKeyOut):
    token: str = Field(description="The key itself: shown this once, only its hash is stored.")


class PairIn(BaseModel):
    model_config = ConfigDict(extra="forbid")

    frame_id: int = Field(ge=1, le=2**31 - 1, description="A frame of the atlas.")
    other_frame_id: int = Field(
        ge=1, le=2**31 - 1, description="Another frame of the atlas, of the same place."
    )


class PairOut(BaseModel):
    id: int
    frame_id: int = Field(description="The frame that revisits (an observation's new frame).")
    other_frame_id: int = Field(description="The frame it was matched with.")
    robot_id: str
    other_robot_id: str
    submap: str
    other_submap: str
    source: str = Field(
        description="observe (a geometrically verified closure), sequence (a loop the robot's "
        "sequence decided, not verified by geometry) or operator (labelled)"
    )
    inliers: int | None = Field(
        description="RANSAC inliers of the pair's match (null when labelled or not verified)."
    )
    created_at: datetime
