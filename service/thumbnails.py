"""Frame thumbnails: a small JPEG per frame, made at ingest from the already decoded image.

The console shows frames through them; nothing else of an uploaded image is kept. Frames stored
before thumbnails existed (or restored from an older snapshot) get :data:`PLACEHOLDER`.
"""

from __future__ import annotations

import io
from functools import lru_cache

import numpy as np
from PIL import Image, ImageDraw
from sqlalchemy import select
from sqlalchemy.orm import Session

from service.storage.models import Frame, FrameThumbnail

LONG_SIDE = 192  # pixels of the thumbnail's longer side
QUALITY = 80  # JPEG quality: a 192 px frame takes a few KB
MEDIA_TYPE = "image/jpeg"


def make_thumbnail(rgb: np.ndarray, long_side: int = LONG_SIDE) -> bytes:
    """JPEG bytes of ``rgb`` (``H x W x 3`` uint8) shrunk so its longer side is ``long_side``."""
    image = Image.fromarray(rgb)
    image.thumbnail((long_side, long_side), Image.Resampling.BILINEAR, reducing_gap=2.0)
    out = io.BytesIO()
    image.save(out, format="JPEG", quality=QUALITY, optimize=True)
    return out.getvalue()


@lru_cache(maxsize=1)
def placeholder() -> bytes:
    """A grey JPEG with a crossed frame, for frames that have no thumbnail."""
    image = Image.new("RGB", (LONG_SIDE, LONG_SIDE * 9 // 16), (200, 200, 200))
    draw = ImageDraw.Draw(image)
    w, h = image.size
    draw.rectangle((0, 0, w - 1, h - 1), outline=(140, 140, 140), width=2)
    draw.line((0, 0, w, h), fill=(160, 160, 160), width=2)
    draw.line((0, h, w, 0), fill=(160, 160, 160), width=2)
    draw.text((8, 8), "no thumbnail", fill=(90, 90, 90))
    out = io.BytesIO()
    image.save(out, format="JPEG", quality=QUALITY)
    return out.getvalue()


def get_thumbnail(session: Session, *, frame_id: int) -> bytes | None:
    return session.scalar(select(FrameThumbnail.jpeg).where(FrameThumbnail.frame_id == frame_id))


# ----- snapshots: one npz member with every thumbnail of an atlas ----------------------------

SNAPSHOT_MEMBER = "thumbnails.npz"


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


def restore_member(session: Session, data: bytes | None, frame_id_map: dict[int, int]) -> int:
    """Add an archive's thumbnails under the restored frame ids (an archive written before
    thumbnails has none: its frames show the placeholder). Returns how many were added."""
    if data is None:
        return 0
    arrays = np.load(io.BytesIO(data))
    offsets, blob = arrays["offsets"], arrays["data"].tobytes()
    added = 0
    for i, old_id in enumerate(arrays["frame_ids"].tolist()):
        if old_id in frame_id_map:
            jpeg = blob[int(offsets[i]) : int(offsets[i + 1])]
            session.add(FrameThumbnail(frame_id=frame_id_map[old_id], jpeg=jpeg))
            added += 1
    return added
