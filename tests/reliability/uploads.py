"""Hypothesis strategies for image uploads: tiny valid images in every mode and format the
decoder meets, their broken relatives (truncated, bit-flipped, wrong format, bombs), and
small-but-huge ones (a few kilobytes on the wire, far more pixels than the networks use: the
decoder shrinks them, within its memory budget).

The valid ones are tiny so that thousands of requests that reach the CNNs fit in minutes (DISK
resizes every frame to the working long side anyway).
"""

from __future__ import annotations

import io

import numpy as np
from hypothesis import strategies as st
from PIL import Image

FORMATS = ("PNG", "JPEG", "WEBP")
PNG_MODES = ("RGB", "L", "RGBA", "LA", "P", "1", "I;16")
JPEG_MODES = ("RGB", "L", "CMYK")
WEBP_MODES = ("RGB", "RGBA")


def encode_image(
    width: int, height: int, mode: str, fmt: str, seed: int, orientation: int | None = None
) -> bytes:
    """A ``width x height`` image of random pixels in ``mode``, encoded as ``fmt``."""
    rng = np.random.default_rng(seed)
    rgb = Image.fromarray(rng.integers(0, 256, (height, width, 3), dtype=np.uint8))
    image = rgb.convert("I;16") if mode == "I;16" else rgb.convert(mode)
    buffer = io.BytesIO()
    params: dict[str, object] = {}
    if orientation is not None and fmt in ("JPEG", "WEBP", "PNG"):
        exif = Image.Exif()
        exif[0x0112] = orientation
        params["exif"] = exif.tobytes()
    image.save(buffer, format=fmt, **params)
    return buffer.getvalue()


@st.composite
def valid_images(draw: st.DrawFn, min_side: int = 16, max_side: int = 48) -> bytes:
    fmt = draw(st.sampled_from(FORMATS))
    allowed = {"JPEG": JPEG_MODES, "WEBP": WEBP_MODES}.get(fmt, PNG_MODES)
    return encode_image(
        draw(st.integers(min_side, max_side)),
        draw(st.integers(min_side, max_side)),
        draw(st.sampled_from(allowed)),
        fmt,
        draw(st.integers(0, 2**16)),
        draw(st.none() | st.integers(0, 9)),
    )


@st.composite
def broken_images(draw: st.DrawFn) -> bytes:
    """A valid tiny image, then truncated, bit-flipped or given a foreign header."""
    data = bytearray(draw(valid_images()))
    how = draw(st.sampled_from(["truncate", "flip", "splice", "foreign"]))
    if how == "truncate":
        return bytes(data[: draw(st.integers(0, max(0, len(data) - 1)))])
    if how == "flip":
        for _ in range(draw(st.integers(1, 8))):
            i = draw(st.integers(0, len(data) - 1))
            data[i] ^= 1 << draw(st.integers(0, 7))
        return bytes(data)
    if how == "splice":
        i = draw(st.integers(0, len(data)))
        return bytes(data[:i]) + draw(st.binary(max_size=64)) + bytes(data[i:])
    header = draw(st.sampled_from([b"GIF89a", b"BM", b"\x00\x00\x01\x00", b"%PDF-1.4", b"II*\x00"]))
    return header + bytes(data)


def multi_picture_jpeg(width: int = 32, height: int = 24) -> bytes:
    """An MPO file (what phone cameras write): two JPEG pictures, the first one the photo."""
    first, second = (
        Image.fromarray(np.random.default_rng(seed).integers(0, 256, (height, width, 3), np.uint8))
        for seed in (1, 2)
    )
    buffer = io.BytesIO()
    first.save(buffer, "MPO", save_all=True, append_images=[second])
    return buffer.getvalue()


def pixel_bomb(width: int, height: int) -> bytes:
    """A PNG of one colour: a few kilobytes on the wire, ``width x height`` pixels decoded."""
    buffer = io.BytesIO()
    Image.new("L", (width, height)).save(buffer, format="PNG", optimize=True)
    return buffer.getvalue()


def solid_image(width: int, height: int, mode: str, fmt: str) -> bytes:
    """One colour in ``mode``, encoded as ``fmt``: kilobytes for millions of pixels."""
    image = Image.new("RGB", (width, height), (90, 120, 200))
    image = image.convert(mode, dither=Image.Dither.NONE)
    buffer = io.BytesIO()
    image.save(buffer, format=fmt)
    return buffer.getvalue()


@st.composite
def small_but_huge_images(draw: st.DrawFn, max_pixels: int = 1_000_000) -> bytes:
    """Solid images of at most ``max_pixels`` whose long side passes the decoder's shrink
    threshold at the tests' 256 px working side (or comes near it), in every format and in the
    modes Pillow cannot shrink directly."""
    fmt = draw(st.sampled_from(FORMATS))
    allowed = {"JPEG": JPEG_MODES, "WEBP": WEBP_MODES}.get(fmt, PNG_MODES)
    long = draw(st.sampled_from([1000, 2048, 3000]))  # 1000: just under the threshold
    lowest = max(16, -(-long // 10))  # the decoder's aspect limit: 10
    short = draw(st.integers(lowest, max(lowest, min(long, max_pixels // long))))
    width, height = (long, short) if draw(st.booleans()) else (short, long)
    return solid_image(width, height, draw(st.sampled_from(allowed)), fmt)


def image_uploads() -> st.SearchStrategy[bytes]:
    """Every kind of upload a robot (or an attacker) might send."""
    return st.one_of(
        small_but_huge_images(),
        valid_images(),
        valid_images(min_side=1, max_side=15),  # below the minimum size
        st.sampled_from([encode_image(2000, 1, "L", "PNG", 0), multi_picture_jpeg()]),
        broken_images(),
        st.binary(max_size=256),
        st.sampled_from([b"", pixel_bomb(1500, 1500), pixel_bomb(4000, 100)]),
    )
