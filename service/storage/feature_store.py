"""Per-frame features <-> database rows: written with the frame, read for re-embedding and
geometric verification without running a CNN again."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from sqlalchemy import Row, select
from sqlalchemy.orm import Session

from service.ml.calibration import CalibrationInputs
from service.ml.features import FrameFeatures, LocalFeatures
from service.storage.models import Frame, FrameFeatureRow, RevisitPair


def global_vector_of(stored: bytes, dim: int) -> np.ndarray:
    """A stored backbone vector as float32: float16 since the layout pooling made R 2,816
    values long (rows written before that hold float32; the length tells which)."""
    dtype = "<f2" if len(stored) == 2 * dim else "<f4"
    return np.frombuffer(stored, dtype).astype(np.float32)


def global_vector_bytes(vector: np.ndarray) -> bytes:
    """A backbone vector R as the store keeps it: little-endian float16."""
    return np.ascontiguousarray(vector, "<f2").tobytes()


def to_row(frame_id: int | None, features: FrameFeatures) -> FrameFeatureRow:
    """Pack features: descriptors and the backbone vector R as float16 (features already hold
    float16-exact values, so a stored frame is the frame), the rest float32."""
    local = features.local
    row = FrameFeatureRow(
        descriptor_dim=int(local.descriptors.shape[1]),
        global_dim=int(features.global_vector.shape[0]),
        keypoints=np.ascontiguousarray(local.keypoints, "<f4").tobytes(),
        descriptors=np.ascontiguousarray(local.descriptors, "<f2").tobytes(),
        scores=np.ascontiguousarray(local.scores, "<f4").tobytes(),
        local_vector=np.ascontiguousarray(features.local_vector, "<f4").tobytes(),
        global_vector=global_vector_bytes(features.global_vector),
    )
    if frame_id is not None:
        row.frame_id = frame_id
    return row


def local_features_of(row: FrameFeatureRow) -> LocalFeatures:
    """The stored keypoints of a frame (descriptors back to float32)."""
    return LocalFeatures(
        keypoints=np.frombuffer(row.keypoints, "<f4").reshape(-1, 2).copy(),
        descriptors=np.frombuffer(row.descriptors, "<f2")
        .reshape(-1, row.descriptor_dim)
        .astype(np.float32),
        scores=np.frombuffer(row.scores, "<f4").copy(),
    )


def load_local_features(session: Session, frame_ids: Sequence[int]) -> dict[int, LocalFeatures]:
    """The stored keypoints of several frames (for verification: no re-extraction)."""
    if not frame_ids:
        return {}
    rows = session.scalars(
        select(FrameFeatureRow).where(FrameFeatureRow.frame_id.in_(list(frame_ids)))
    )
    return {row.frame_id: local_features_of(row) for row in rows}


@dataclass(frozen=True)
class StoredVectors:
    """The two small stored vectors of frames, row-aligned with their ids, submaps and robots."""

    ids: np.ndarray  # int64 frame ids
    local: np.ndarray  # D vectors (aggregated local descriptors)
    global_: np.ndarray  # R vectors (global CNN descriptor)
    submaps: np.ndarray  # int64 submap ids
    robots: list[str]

    def __len__(self) -> int:
        return len(self.ids)


def stored_frame_ids(session: Session, atlas_id: int) -> np.ndarray:
    """The ids of an atlas's frames with stored features (those the readers below yield), in
    id order."""
    query = (
        select(Frame.id)
        .join(FrameFeatureRow, FrameFeatureRow.frame_id == Frame.id)
        .where(Frame.atlas_id == atlas_id)
        .order_by(Frame.id)
    )
    return np.fromiter(session.scalars(query), dtype=np.int64)


def _stored_rows(
    session: Session,
    atlas_id: int,
    columns: tuple[Any, ...],
    frame_ids: Sequence[int] | None,
    batch: int,
) -> Iterator[Sequence[Row[Any]]]:
    """Batches of (frame id, submap id, robot id, *columns) of an atlas's stored frames in
    frame id order, streamed from the database."""
    query = (
        select(Frame.id, Frame.submap_id, Frame.robot_id, *columns)
        .join(FrameFeatureRow, FrameFeatureRow.frame_id == Frame.id)
        .where(Frame.atlas_id == atlas_id)
        .order_by(Frame.id)
    )
    if frame_ids is not None:
        query = query.where(Frame.id.in_(list(frame_ids)))
    yield from session.execute(query.execution_options(yield_per=batch)).partitions(batch)


def iter_stored_vectors(
    session: Session, atlas_id: int, *, frame_ids: Sequence[int] | None = None, batch: int = 4096
) -> Iterator[StoredVectors]:
    """Batches of stored vectors in frame id order.

    Only the two small vectors are read, never the keypoint blobs.
    """
    columns = (
        FrameFeatureRow.local_vector,
        FrameFeatureRow.global_vector,
        FrameFeatureRow.descriptor_dim,
        FrameFeatureRow.global_dim,
    )
    for rows in _stored_rows(session, atlas_id, columns, frame_ids, batch):
        ids = np.array([r.id for r in rows], np.int64)
        submaps = np.array([r.submap_id for r in rows], np.int64)
        robots = [r.robot_id for r in rows]
        local = np.stack([np.frombuffer(r.local_vector, "<f4") for r in rows])
        global_ = np.stack([global_vector_of(r.global_vector, r.global_dim) for r in rows])
        yield StoredVectors(ids, local, global_, submaps, robots)


def load_stored_vectors(session: Session, atlas_id: int) -> StoredVectors:
    """All frames' stored vectors of an atlas, concatenated."""
    return concat_vectors(list(iter_stored_vectors(session, atlas_id)))


def concat_vectors(batches: Sequence[StoredVectors]) -> StoredVectors:
    """Batches of vectors as one (empty batches list: zero frames)."""
    if not batches:
        return StoredVectors(
            np.zeros(0, np.int64),
            np.zeros((0, 0), np.float32),
            np.zeros((0, 0), np.float32),
            np.zeros(0, np.int64),
            [],
        )
    return StoredVectors(
        np.concatenate([b.ids for b in batches]),
        np.concatenate([b.local for b in batches]),
        np.concatenate([b.global_ for b in batches]),
        np.concatenate([b.submaps for b in batches]),
        [robot for b in batches for robot in b.robots],
    )


def load_calibration_inputs(session: Session, atlas_id: int) -> CalibrationInputs:
    """An atlas's stored descriptors, scores, backbone vectors, robots and frame order: what a
    calibration is fitted on (descriptors stay float16 until aggregated)."""
    batches = list(iter_stored_descriptors(session, atlas_id))
    ids = np.concatenate([b.ids for b in batches]) if batches else np.zeros(0, np.int64)
    return CalibrationInputs(
        descriptors=[d for b in batches for d in b.descriptors],
        scores=[s for b in batches for s in b.scores],
        global_vectors=np.concatenate([b.global_ for b in batches])
        if batches
        else np.zeros((0, 0), np.float32),
        robots=[r for b in batches for r in b.robots],
        order=ids,
        same_place=known_same_place(session, atlas_id, ids),
    )


def known_same_place(session: Session, atlas_id: int, ids: np.ndarray) -> np.ndarray:
    """The atlas's revisit pairs as ``m x 2`` positions in ``ids`` (pairs of a frame not
    among them are left out): frames the fleet verified, or an operator labelled, as one
    place, which a calibration must not take for impostors."""
    rows = session.execute(
        select(RevisitPair.frame_id, RevisitPair.other_frame_id).where(
            RevisitPair.atlas_id == atlas_id
        )
    ).all()
    position = {int(frame_id): i for i, frame_id in enumerate(ids)}
    pairs = [(position[a], position[b]) for a, b in rows if a in position and b in position]
    return np.array(pairs, np.int64).reshape(-1, 2)


@dataclass(frozen=True)
class StoredDescriptors:
    """The local descriptors, scores and backbone vectors of a batch of frames (what a
    calibrated model version embeds from), row-aligned with their ids, submaps and robots."""

    ids: np.ndarray
    descriptors: list[np.ndarray]  # float16 as stored, N_i x d each
    scores: list[np.ndarray]
    global_: np.ndarray
    submaps: np.ndarray
    robots: list[str]


def iter_stored_descriptors(
    session: Session, atlas_id: int, *, frame_ids: Sequence[int] | None = None, batch: int = 256
) -> Iterator[StoredDescriptors]:
    """Batches of stored descriptors in frame id order (small batches: the blobs are large)."""
    columns = (
        FrameFeatureRow.descriptors,
        FrameFeatureRow.descriptor_dim,
        FrameFeatureRow.scores,
        FrameFeatureRow.global_vector,
        FrameFeatureRow.global_dim,
    )
    for rows in _stored_rows(session, atlas_id, columns, frame_ids, batch):
        yield StoredDescriptors(
            ids=np.array([r.id for r in rows], np.int64),
            descriptors=[
                np.frombuffer(r.descriptors, "<f2").reshape(-1, r.descriptor_dim) for r in rows
            ],
            scores=[np.frombuffer(r.scores, "<f4") for r in rows],
            global_=np.stack([global_vector_of(r.global_vector, r.global_dim) for r in rows]),
            submaps=np.array([r.submap_id for r in rows], np.int64),
            robots=[r.robot_id for r in rows],
        )
