"""Embed stored frames with a model version into an index (no CNN pass)."""

from __future__ import annotations

import contextlib
import queue
import threading
from collections.abc import Callable, Iterator, Sequence
from typing import TypeVar

import numpy as np
from sqlalchemy.orm import Session

from service.index.store import VectorStore
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

T = TypeVar("T")

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


Batch = tuple[np.ndarray, np.ndarray, list[str]]  # frame ids, their embeddings, their robots
AHEAD = 2  # batches read and embedded ahead of the one the index is adding


def add_stored_frames(
    session: Session,
    atlas_id: int,
    model: ActiveModel,
    index: VectorStore,
    *,
    frame_ids: Sequence[int] | None = None,
    progress: Callable[[int], None] | None = None,
    precision: str = "fp32",
) -> int:
    """Embed the atlas's stored frames (all, or ``frame_ids``) and add them to ``index``.

    Returns how many frames were added; ``progress`` gets the running count. ``precision``
    ("auto", "fp32", "bf16") is the embedding's matrix arithmetic (see ``embed_vectors``).
    """
    resolved = resolve_precision(precision)

    def embedded(ids: Sequence[int] | None) -> Iterator[Batch]:
        for batch in iter_model_inputs(session, atlas_id, model.calibration, frame_ids=ids):
            embeddings = embed_vectors(model.heads, batch.local, batch.global_, resolved)
            yield batch.ids, embeddings, batch.robots

    def wanted() -> np.ndarray:
        if frame_ids is None:
            return stored_frame_ids(session, atlas_id)
        return np.asarray(frame_ids, dtype=np.int64)

    return fill_index(index, embedded, frame_ids, wanted, progress)


def fill_index(
    index: VectorStore,
    embedded: Callable[[Sequence[int] | None], Iterator[Batch]],
    frame_ids: Sequence[int] | None,
    wanted: Callable[[], np.ndarray],
    progress: Callable[[int], None] | None = None,
) -> int:
    """Add the ``embedded`` batches of ``frame_ids`` (None: every frame) to ``index``.

    An empty index is first trained for the final size (``wanted()``: the ids to come) on its
    sample's embeddings (:meth:`AtlasIndex.prepare`), so the frames go straight into its
    inverted lists. The next batches are read and embedded in a thread while the index adds
    the current one: the two halves of the work run on two cores (both release the GIL in
    their C loops), with no synchronisation inside either.
    """
    added = 0
    with index.bulk():  # one rebuild at the final size, not one per threshold passed
        if index.size == 0:
            _prepare(index, wanted(), embedded)
        for ids, embeddings, robots in read_ahead(embedded(frame_ids), AHEAD):
            added += index.add(ids, embeddings, robots)
            if progress is not None:
                progress(added)
    index.wait_rebuilt()  # a bulk build ends with the index type its size calls for
    return added


def _prepare(
    index: VectorStore,
    wanted: np.ndarray,
    embedded: Callable[[Sequence[int]], Iterator[Batch]],
) -> None:
    """Train an empty ``index`` for the ``wanted`` frames on the embeddings of its sample."""
    sample = index.training_ids(wanted)
    if sample is None:
        return
    vectors = [embeddings for _, embeddings, _ in embedded(sample.tolist())]
    if vectors:
        index.prepare(len(wanted), np.concatenate(vectors))


def read_ahead(items: Iterator[T], depth: int) -> Iterator[T]:
    """``items``, produced by a thread at most ``depth`` items ahead of the consumer. The
    producer's exception is raised in the consumer; a consumer that stops early stops it."""
    handoff: queue.Queue[tuple[T] | BaseException | None] = queue.Queue(depth)  # None: the end
    stop = threading.Event()

    def put(entry: tuple[T] | BaseException | None) -> bool:
        while not stop.is_set():
            with contextlib.suppress(queue.Full):
                handoff.put(entry, timeout=0.1)
                return True
        return False

    def produce() -> None:
        try:
            for item in items:
                if not put((item,)):
                    return
        except BaseException as exc:  # handed to the consumer, which raises it
            put(exc)
            return
        put(None)

    producer = threading.Thread(target=produce, name="read-ahead", daemon=True)
    producer.start()
    try:
        while (entry := handoff.get()) is not None:
            if isinstance(entry, BaseException):
                raise entry
            yield entry[0]
    finally:
        stop.set()
        producer.join()
