"""Embed stored frames with a model version's heads into an index (no CNN pass)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

from sqlalchemy.orm import Session

from service.index import AtlasIndex
from service.ml.heads import LoopNetHeads
from service.ml.pipeline import embed_vectors
from service.ml.precision import resolve_precision
from service.storage.feature_store import iter_stored_vectors

CHUNK = 10_000  # frame ids per IN (...) query: SQLite allows 32,766 variables


def add_stored_frames(
    session: Session,
    atlas_id: int,
    heads: LoopNetHeads,
    index: AtlasIndex,
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
    added = 0
    chunks = (
        [None]
        if frame_ids is None
        else [list(frame_ids[i : i + CHUNK]) for i in range(0, len(frame_ids), CHUNK)]
    )
    for chunk in chunks:
        if chunk is not None and not chunk:
            continue
        for batch in iter_stored_vectors(session, atlas_id, frame_ids=chunk):
            embeddings = embed_vectors(heads, batch.local, batch.global_, resolved)
            added += index.add(batch.ids, embeddings, batch.robots)
            if progress is not None:
                progress(added)
    index.wait_rebuilt()  # a bulk build ends with the index type its size calls for
    return added
