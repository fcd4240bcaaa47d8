"""Embed stored frames with a model version into an index (no CNN pass)."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence

import numpy as np
from sqlalchemy.orm import Session

from service.index import AtlasIndex
from service.ml.active_model import ActiveModel
from service.ml.calibration import Calibration
from service.ml.pipeline import embed_vectors
from service.ml.precision import resolve_precision
from service.storage.feature_store import (
    StoredVectors,
    concat_vectors,
    iter_stored_descriptors,
    iter_stored_vectors,
    stored_frame_ids,
)

CHUNK = 10_000  # frame ids per IN (...) query: SQLite allows 32,766 variables


def iter_model_inputs(
    session: Session,
    atlas_id: int,
    calibration: Calibration | None,
    *,
    frame_ids: Sequence[int] | None = None,
) -> Iterator[StoredVectors]:
    """Batches of the heads' inputs of stored frames: the stored (D, R) vectors, or with a
    calibration the calibrated branches computed from the stored descriptors, read in batches."""
    chunks = (
        [None]
        if frame_ids is None
        else [list(frame_ids[i : i + CHUNK]) for i in range(0, len(frame_ids), CHUNK)]
    )
    for chunk in chunks:
        if chunk is not None and not chunk:
            continue
        if calibration is None:
            yield from iter_stored_vectors(session, atlas_id, frame_ids=chunk)
            continue
        for batch in iter_stored_descriptors(session, atlas_id, frame_ids=chunk):
            local, global_ = calibration.branch_vectors(
                batch.descriptors, batch.scores, batch.global_
            )
            yield StoredVectors(batch.ids, local, global_, batch.submaps, batch.robots)


def load_model_inputs(
    session: Session, atlas_id: int, calibration: Calibration | None
) -> StoredVectors:
    """Every frame's heads inputs, concatenated (what retraining trains on)."""
    return concat_vectors(list(iter_model_inputs(session, atlas_id, calibration)))


def add_stored_frames(
    session: Session,
    atlas_id: int,
    model: ActiveModel,
    index: AtlasIndex,
    *,
    frame_ids: Sequence[int] | None = None,
    progress: Callable[[int], None] | None = None,
    precision: str = "fp32",
) -> int:
    """Embed the atlas's stored frames (all, or ``frame_ids``) and add them to ``index``.

    Returns how many frames were added; ``progress`` gets the running count. ``precision``
    ("auto", "fp32", "bf16") is the embedding's matrix arithmetic (see ``embed_vectors``). An
    empty index is first trained for the final size on a sample of the frames
    (:meth:`AtlasIndex.prepare`), so the frames go straight into its inverted lists.
    """
    resolved = resolve_precision(precision)

    def embedded(ids: Sequence[int] | None) -> Iterator[tuple[StoredVectors, np.ndarray]]:
        for batch in iter_model_inputs(session, atlas_id, model.calibration, frame_ids=ids):
            yield batch, embed_vectors(model.heads, batch.local, batch.global_, resolved)

    added = 0
    with index.bulk():  # one rebuild at the final size, not one per threshold passed
        if index.size == 0:
            wanted = stored_frame_ids(session, atlas_id) if frame_ids is None else frame_ids
            _prepare(index, np.asarray(wanted, dtype=np.int64), embedded)
        for batch, embeddings in embedded(frame_ids):
            added += index.add(batch.ids, embeddings, batch.robots)
            if progress is not None:
                progress(added)
    index.wait_rebuilt()  # a bulk build ends with the index type its size calls for
    return added


def _prepare(
    index: AtlasIndex,
    wanted: np.ndarray,
    embedded: Callable[[Sequence[int]], Iterator[tuple[StoredVectors, np.ndarray]]],
) -> None:
    """Train an empty ``index`` for the ``wanted`` frames on the embeddings of its sample."""
    sample = index.training_ids(wanted)
    if sample is None:
        return
    vectors = [embeddings for _, embeddings in embedded(sample.tolist())]
    if vectors:
        index.prepare(len(wanted), np.concatenate(vectors))
