"""Decoding a snapshot's rows, features and weights into validated values, before any write.

Every row is checked with the rules the API applies to what it stores (names and robot ids,
finite numbers, unit-quaternion poses, positive focal lengths, the retraining bounds of a
heads configuration and, as a retraining job's parameters are, its fit to the atlas's features),
every reference between rows must resolve, no row file may hold more rows than the manifest
counts (each is read a line at a time), the features must be plain numeric arrays of the shapes
the rows announce (:mod:`service.fleet.snapshot_features`), weights must load into heads of
their row's configuration, and a calibration must load (no pickle, bounded inflation) and turn
the atlas's features into its heads' inputs. Whatever fails is an :class:`InvalidInput` naming
the member and line, so a restore answers 422 and writes nothing.
"""

from __future__ import annotations

import zipfile
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np
import torch
from pydantic import BaseModel, ValidationError

from service.domain.limits import ArchiveLimits
from service.errors import InvalidInput
from service.fleet.snapshot_archive import (
    CALIBRATION_MEMBER,
    WEIGHTS_MEMBER,
    Archive,
    calibration_member,
    first_error,
    weights_member,
)
from service.fleet.snapshot_features import Features, decode_features
from service.fleet.snapshot_schema import (
    AtlasRow,
    FrameRow,
    HeadsRow,
    LoopClosureRow,
    ModelVersionRow,
    SubmapRow,
)
from service.ml.calibration import Calibration
from service.ml.heads import HeadsConfig, LoopNetHeads
from service.ml.training import TrainingConfig

RowT = TypeVar("RowT", bound=BaseModel)


def _parse_lines(member: str, lines: Iterable[bytes], model: type[RowT], most: int) -> list[RowT]:
    """The rows of a JSON-lines member, refused past ``most`` (the manifest's count) before
    the next line is parsed."""
    rows: list[RowT] = []
    for number, line in enumerate(lines, 1):
        if not line.strip():
            continue
        if len(rows) == most:
            raise InvalidInput(
                f"the snapshot's {member} holds more rows than its manifest counts ({most})"
            )
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
    calibration: Calibration | None = None
    calibration_file: Path | None = None  # the member as archived, copied back verbatim


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


def _load_weights(name: str, path: Path, config: HeadsRow) -> LoopNetHeads:
    """Heads from an archived weights file whose configuration must equal its row's."""
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
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


def _load_calibration(
    name: str, path: Path, limits: ArchiveLimits, features: Features, heads: HeadsRow
) -> Calibration:
    """A calibration member that loads without pickles, inflates within the limits and maps
    the atlas's stored features onto the heads' input sizes with finite numbers."""
    try:
        with zipfile.ZipFile(path) as zipped:
            inflated = sum(info.file_size for info in zipped.infolist())
        if inflated > limits.max_member_bytes:
            raise InvalidInput(
                f"the snapshot's {name} inflates beyond LOOPNET_SNAPSHOT_MAX_MEMBER_BYTES"
            )
        calibration = Calibration.load(path)
        probe_local, probe_global = calibration.branch_vectors(
            [np.ones((1, features.descriptor_dim), np.float32)],
            [np.ones(1, np.float32)],
            np.ones((1, features.global_dim), np.float32),
        )
    except InvalidInput:
        raise
    except Exception as exc:  # a bad zip, an object array, missing or misshapen arrays
        raise InvalidInput(f"the snapshot's {name} is not a loadable calibration: {exc}") from exc
    shapes = (probe_local.shape[1], probe_global.shape[1])
    if shapes != (heads.local_dim, heads.global_dim):
        raise InvalidInput(f"the snapshot's {name} does not fit its version's heads")
    if not (np.isfinite(probe_local).all() and np.isfinite(probe_global).all()):
        raise InvalidInput(f"the snapshot's {name} holds non-finite numbers")
    return calibration


def _check_fits(version: int, heads: HeadsRow) -> None:
    """A version's heads must fit its inputs as a retraining job's parameters must
    (:meth:`TrainingConfig.check_fits`): an embedding no wider than the fused input."""
    try:
        TrainingConfig(embed_dim=heads.embed_dim).check_fits(
            HeadsConfig(heads.local_dim, heads.global_dim, heads.alpha, heads.hidden_dim)
        )
    except ValueError as exc:
        raise InvalidInput(f"the snapshot's model version {version}: {exc}") from exc


def _versions(
    archive: Archive, features: Features, limits: ArchiveLimits
) -> tuple[list[Version], Version]:
    rows = _parse_lines(
        "model_versions.jsonl",
        archive.lines("model_versions.jsonl"),
        ModelVersionRow,
        archive.manifest.counts.model_versions,
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
    archived = {name for name in archive.files if WEIGHTS_MEMBER.match(name)}
    if referenced != archived:
        raise InvalidInput("the snapshot's weights files do not match its model versions")
    calibrations = {r.calibration_file for r in rows if r.calibration_file is not None}
    if calibrations != {name for name in archive.files if CALIBRATION_MEMBER.match(name)}:
        raise InvalidInput("the snapshot's calibration files do not match its model versions")
    versions = []
    for row in rows:
        heads_row = row.config.heads
        calibration = None
        if (row.calibration_file is None) != (row.config.calibration is None):
            raise InvalidInput(
                f"the snapshot's version {row.version} and its calibration file disagree"
            )
        if row.calibration_file is not None:
            if row.calibration_file != calibration_member(row.version):
                raise InvalidInput(
                    f"the snapshot's version {row.version} names another calibration"
                )
            calibration = _load_calibration(
                row.calibration_file,
                archive.files[row.calibration_file],
                limits,
                features,
                heads_row,
            )
        elif (heads_row.local_dim, heads_row.global_dim) != (
            features.descriptor_dim,
            features.global_dim,
        ):
            raise InvalidInput(
                f"the snapshot's model version {row.version} does not fit its features' sizes"
            )
        _check_fits(row.version, heads_row)
        if row.weights is None:
            if row.config.trained:
                raise InvalidInput(f"the snapshot's trained version {row.version} has no weights")
            heads = LoopNetHeads(_heads_config(heads_row)).eval()
        else:
            if row.weights != weights_member(row.version):
                raise InvalidInput(f"the snapshot's version {row.version} names other weights")
            heads = _load_weights(row.weights, archive.files[row.weights], heads_row)
        calibration_file = (
            archive.files[row.calibration_file] if row.calibration_file is not None else None
        )
        versions.append(Version(row, heads, calibration, calibration_file))
    return versions, next(v for v in versions if v.row.is_active)


def decode_snapshot(
    archive: Archive, limits: ArchiveLimits, feature_dims: tuple[int, int], folder: Path
) -> DecodedSnapshot:
    """Every row, array and weights file of ``archive``, validated and cross-checked;
    ``feature_dims``: the descriptor and global sizes the restoring service extracts; the
    features are inflated into ``folder``."""
    counts_row = archive.manifest.counts
    features = decode_features(archive.files["features.npz"], limits, folder, counts_row.frames)
    if (features.descriptor_dim, features.global_dim) != feature_dims:
        raise InvalidInput(
            f"the snapshot's features have sizes {features.descriptor_dim} and "
            f"{features.global_dim}, this service's {feature_dims[0]} and {feature_dims[1]}"
        )
    try:
        atlas = AtlasRow.model_validate_json(archive.read("atlas.json"))
    except ValidationError as exc:
        raise InvalidInput(f"the snapshot's atlas.json: {first_error(exc)}") from exc
    submaps = _parse_lines(
        "submaps.jsonl", archive.lines("submaps.jsonl"), SubmapRow, counts_row.submaps
    )
    frames = _parse_lines(
        "frames.jsonl", archive.lines("frames.jsonl"), FrameRow, counts_row.frames
    )
    closures = _parse_lines(
        "loop_closures.jsonl",
        archive.lines("loop_closures.jsonl"),
        LoopClosureRow,
        counts_row.loop_closures,
    )
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
    ids = features.frame_ids.tolist()
    if len(set(ids)) != len(ids) or set(ids) != set(by_id):
        raise InvalidInput("the snapshot's features.npz does not hold each frame exactly once")
    ordered = [by_id[i] for i in ids]
    counts = np.diff(features.offsets)
    if any(f.keypoint_count != int(c) for f, c in zip(ordered, counts, strict=True)):
        raise InvalidInput("the snapshot's keypoint counts disagree with its features")
    versions, active = _versions(archive, features, limits)
    for version in versions:
        labels = version.heads.class_labels
        if not set(labels) <= known_submaps:
            raise InvalidInput(
                f"the snapshot's version {version.row.version} classifies unknown submaps"
            )
    if (counts_row.submaps, counts_row.frames, counts_row.model_versions) != (
        len(submaps),
        len(frames),
        len(versions),
    ) or counts_row.loop_closures != len(closures):
        raise InvalidInput("the snapshot's row counts disagree with its manifest")
    return DecodedSnapshot(atlas, submaps, ordered, features, versions, active, closures)
