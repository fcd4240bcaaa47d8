"""Stored thumbnails (made by :mod:`service.ml.thumbnails` at ingest): a frame's, the query
image's of a loop closure, and the one archive member that carries an atlas's thumbnails in a
snapshot."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session

from service.errors import InvalidInput
from service.npz_reader import NpzReader
from service.storage.models import Frame, FrameThumbnail, LoopClosureThumbnail

SNAPSHOT_MEMBER = "thumbnails.npz"


def frame_thumbnail(session: Session, frame_id: int) -> bytes | None:
    return session.scalar(select(FrameThumbnail.jpeg).where(FrameThumbnail.frame_id == frame_id))


def closure_thumbnail(session: Session, closure_id: int) -> bytes | None:
    kept = session.get(LoopClosureThumbnail, closure_id)
    return kept.jpeg if kept is not None else None


def export_member(session: Session, atlas_id: int) -> bytes:
    """The atlas's thumbnails as an npz: frame ids, byte offsets and the concatenated JPEGs."""
    rows = session.execute(
        select(FrameThumbnail.frame_id, FrameThumbnail.jpeg)
        .join(Frame, Frame.id == FrameThumbnail.frame_id)
        .where(Frame.atlas_id == atlas_id)
        .order_by(FrameThumbnail.frame_id)
    ).all()
    sizes = np.array([len(jpeg) for _, jpeg in rows], np.int64)
    out = io.BytesIO()
    np.savez(
        out,
        frame_ids=np.array([frame_id for frame_id, _ in rows], np.int64),
        offsets=np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64),
        data=np.frombuffer(b"".join(jpeg for _, jpeg in rows), np.uint8),
    )
    return out.getvalue()


def restore_member(
    session: Session,
    path: Path | None,
    frame_id_map: dict[int, int],
    folder: Path,
    max_bytes: int,
) -> int:
    """Add the thumbnails of an archive's member at ``path`` under the restored frame ids (an
    archive written before thumbnails has none: its frames show the placeholder); the JPEGs,
    at most ``max_bytes`` of them, are inflated into ``folder`` and read one at a time. Returns
    how many were added."""
    if path is None:
        return 0
    with NpzReader(path, f"the snapshot's {SNAPSHOT_MEMBER}") as npz:
        if npz.arrays != {"frame_ids", "offsets", "data"}:
            raise InvalidInput(
                f"the snapshot's {SNAPSHOT_MEMBER} does not hold the expected arrays"
            )
        frames = len(frame_id_map)  # one thumbnail a frame at most: 8 bytes an id, an offset
        frame_ids = npz.read("frame_ids", 8 * frames)
        offsets = npz.read("offsets", 8 * (frames + 1))
        blob = npz.extract("data", folder / "thumbnails-data.npy", max_bytes)
    if (
        frame_ids.dtype.kind != "i"
        or offsets.dtype.kind != "i"
        or frame_ids.ndim != 1
        or offsets.shape != (len(frame_ids) + 1,)
        or blob.ndim != 1
        or (len(offsets) and (offsets[0] != 0 or offsets[-1] != len(blob)))
        or np.any(np.diff(offsets) < 0)
    ):
        raise InvalidInput(f"the snapshot's {SNAPSHOT_MEMBER} has inconsistent arrays")
    added = 0
    for i, old_id in enumerate(frame_ids.tolist()):
        if old_id in frame_id_map:
            jpeg = blob[int(offsets[i]) : int(offsets[i + 1])].tobytes()
            session.add(FrameThumbnail(frame_id=frame_id_map[old_id], jpeg=jpeg))
            added += 1
    return added
