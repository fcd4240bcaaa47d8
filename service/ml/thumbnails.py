"""Frame thumbnails: a small JPEG per frame, made at ingest from the already decoded image.

The console shows frames through them; nothing else of an uploaded image is kept. Frames stored
before thumbnails existed (or restored from an older snapshot) get :func:`placeholder`; storing
and archiving them is :mod:`service.app.thumbnails`.
"""

from __future__ import annotations

import io
from functools import lru_cache

import numpy as np
from PIL import Image, ImageDraw

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
