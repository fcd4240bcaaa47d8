"""Decoding a snapshot's rows, features and weights into validated values, before any write.

Every row is checked with the rules the API applies to what it stores (names and robot ids,
finite numbers, unit-quaternion poses, positive focal lengths, the retraining bounds of a
heads configuration), every reference between rows must resolve, the features must be plain
numeric arrays of the shapes the rows announce (:mod:`service.fleet.snapshot_features`), and weights must
load into heads of their row's configuration. Whatever fails is an :class:`InvalidInput`
naming the member and line, so a restore answers 422 and writes nothing.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from datetime import datetime
from typing import Annotated, Any, Literal, TypeVar

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from service.atlas.names import NAME_PATTERN
from service.errors import InvalidInput
from service.fleet.snapshot_archive import (
    WEIGHTS_MEMBER,
    Archive,
    ArchiveLimits,
    first_error,
    weights_member,
)
from service.fleet.snapshot_features import MAX_DIM, Features, decode_features
from service.ml.geometry import Intrinsics, Pose
from service.ml.heads import HeadsConfig, LoopNetHeads

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


class VersionConfigRow(BaseModel):
    model_config = ConfigDict(extra="allow", strict=True)  # training records its parameters

    heads: HeadsRow
    trained: bool


class ModelVersionRow(_Row):
    version: int = Field(ge=1, le=999_999_999)
    config: VersionConfigRow
    metrics: dict[str, Any]
    is_active: bool
    created_at: datetime
    weights: str | None  # required key: null for untrained heads rebuilt from the config


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


RowT = TypeVar("RowT", bound=BaseModel)


def _parse_lines(member: str, data: bytes, model: type[RowT]) -> list[RowT]:
    rows = []
    for number, line in enumerate(data.splitlines(), 1):
        if not line.strip():
            continue
        try:
            rows.append(model.model_validate_json(line))
        except ValidationError as exc:
            raise InvalidInput(
                f"the snapshot's {member}, line {number}: {first_error(exc)}"
            ) from exc
    return rows


@dataclass
class Version:
    row: ModelVersionRow
    heads: LoopNetHeads


@dataclass
class DecodedSnapshot:
    atlas: AtlasRow
    submaps: list[SubmapRow]
    frames: list[FrameRow]  # in the order of ``features.frame_ids``
    features: Features
    versions: list[Version]
    active: Version
    loop_closures: list[LoopClosureRow]


def _heads_config(row: HeadsRow) -> HeadsConfig:
    return HeadsConfig(**row.model_dump())


def _load_weights(name: str, data: bytes, config: HeadsRow) -> LoopNetHeads:
    """Heads from an archived weights file whose configuration must equal its row's."""
    try:
        payload = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
        stored = HeadsRow.model_validate(payload["config"], strict=False)
        labels = payload["class_labels"]
        if stored != config:
            raise InvalidInput(f"the snapshot's {name} was trained for another configuration")
        if not isinstance(labels, list) or not all(isinstance(v, int) for v in labels):
            raise InvalidInput(f"the snapshot's {name} has malformed class labels")
        heads = LoopNetHeads(_heads_config(stored), labels)
        heads.load_state_dict(payload["state_dict"])
    except InvalidInput:
        raise
    except Exception as exc:
        raise InvalidInput(f"the snapshot's {name} is not loadable heads: {exc}") from exc
    return heads.eval()


def _versions(archive: Archive, features: Features) -> tuple[list[Version], Version]:
    rows = _parse_lines(
        "model_versions.jsonl", archive.members["model_versions.jsonl"], ModelVersionRow
    )
    numbers = [r.version for r in rows]
    if len(set(numbers)) != len(numbers):
        raise InvalidInput("the snapshot's model_versions.jsonl repeats a version")
    active = [r for r in rows if r.is_active]
    if len(active) != 1 or active[0].version != archive.manifest.active_model_version:
        raise InvalidInput(
            "the snapshot must have exactly one active model version, the manifest's "
            f"active_model_version ({archive.manifest.active_model_version})"
        )
    referenced = {r.weights for r in rows if r.weights is not None}
    archived = {name for name in archive.members if WEIGHTS_MEMBER.match(name)}
    if referenced != archived:
        raise InvalidInput("the snapshot's weights files do not match its model versions")
    versions = []
    for row in rows:
        heads_row = row.config.heads
        if (heads_row.local_dim, heads_row.global_dim) != (
            features.descriptor_dim,
            features.global_dim,
        ):
            raise InvalidInput(
                f"the snapshot's model version {row.version} does not fit its features' sizes"
            )
        if row.weights is None:
            if row.config.trained:
                raise InvalidInput(f"the snapshot's trained version {row.version} has no weights")
            heads = LoopNetHeads(_heads_config(heads_row)).eval()
        else:
            if row.weights != weights_member(row.version):
                raise InvalidInput(f"the snapshot's version {row.version} names other weights")
            heads = _load_weights(row.weights, archive.members[row.weights], heads_row)
        versions.append(Version(row, heads))
    return versions, next(v for v in versions if v.row.is_active)


def decode_snapshot(
    archive: Archive, limits: ArchiveLimits, feature_dims: tuple[int, int]
) -> DecodedSnapshot:
    """Every row, array and weights file of ``archive``, validated and cross-checked;
    ``feature_dims``: the descriptor and global sizes the restoring service extracts."""
    members = archive.members
    try:
        atlas = AtlasRow.model_validate_json(members["atlas.json"])
    except ValidationError as exc:
        raise InvalidInput(f"the snapshot's atlas.json: {first_error(exc)}") from exc
    submaps = _parse_lines("submaps.jsonl", members["submaps.jsonl"], SubmapRow)
    frames = _parse_lines("frames.jsonl", members["frames.jsonl"], FrameRow)
    closures = _parse_lines("loop_closures.jsonl", members["loop_closures.jsonl"], LoopClosureRow)
    submap_ids = [s.id for s in submaps]
    if len(set(submap_ids)) != len(submap_ids) or len({s.name for s in submaps}) != len(submaps):
        raise InvalidInput("the snapshot's submaps.jsonl repeats a submap")
    known_submaps = set(submap_ids)
    by_id: dict[int, FrameRow] = {}
    for number, frame in enumerate(frames, 1):
        where = f"the snapshot's frames.jsonl, line {number}"
        if frame.id in by_id:
            raise InvalidInput(f"{where}: frame {frame.id} appears twice")
        if frame.submap_id not in known_submaps:
            raise InvalidInput(f"{where}: frame {frame.id} names an unknown submap")
        try:
            frame.check_geometry()
        except InvalidInput as exc:
            raise InvalidInput(f"{where}: {exc}") from exc
        by_id[frame.id] = frame
    for number, closure in enumerate(closures, 1):
        if (
            closure.frame_id not in by_id
            or closure.submap_id not in known_submaps
            or (closure.query_frame_id is not None and closure.query_frame_id not in by_id)
        ):
            raise InvalidInput(
                f"the snapshot's loop_closures.jsonl, line {number}: unknown frame or submap"
            )
    features = decode_features(members["features.npz"], limits)
    if (features.descriptor_dim, features.global_dim) != feature_dims:
        raise InvalidInput(
            f"the snapshot's features have sizes {features.descriptor_dim} and "
            f"{features.global_dim}, this service's {feature_dims[0]} and {feature_dims[1]}"
        )
    ids = features.frame_ids.tolist()
    if len(set(ids)) != len(ids) or set(ids) != set(by_id):
        raise InvalidInput("the snapshot's features.npz does not hold each frame exactly once")
    ordered = [by_id[i] for i in ids]
    counts = np.diff(features.offsets)
    if any(f.keypoint_count != int(c) for f, c in zip(ordered, counts, strict=True)):
        raise InvalidInput("the snapshot's keypoint counts disagree with its features")
    versions, active = _versions(archive, features)
    for version in versions:
        labels = version.heads.class_labels
        if not set(labels) <= known_submaps:
            raise InvalidInput(
                f"the snapshot's version {version.row.version} classifies unknown submaps"
            )
    counts_row = archive.manifest.counts
    if (counts_row.submaps, counts_row.frames, counts_row.model_versions) != (
        len(submaps),
        len(frames),
        len(versions),
    ) or counts_row.loop_closures != len(closures):
        raise InvalidInput("the snapshot's row counts disagree with its manifest")
    return DecodedSnapshot(atlas, submaps, ordered, features, versions, active, closures)
