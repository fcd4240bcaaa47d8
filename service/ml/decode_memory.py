"""How much memory decoding an image takes, and the budget every decode in a process shares.

A compressed image says nothing of its decoded cost: a small PNG of many pixels takes 4 bytes
a pixel once Pillow holds it (RGB), and each copy on the way to the networks (mode conversion,
the array, the float tensors of the two networks) adds more (measured peaks before and after:
benchmarks/RESULTS.md, issue 24).
:func:`service.ml.images.decode_frame` therefore decodes a large JPEG at a reduced scale and
shrinks any other large image right after decoding (the networks only ever see a few hundred
pixels a side), so only the decoder's own buffer is full size; :class:`DecodeBudget` bounds what
those buffers take together: a decode reserves its estimate (:func:`decode_bytes`) before it
starts and gives it back when the frame is small, an image whose estimate exceeds the whole
budget is refused (413), and one that does not fit beside the decodes running now waits (503
after the wait).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

from service.errors import ImageTooLarge, Overloaded

# Bytes a pixel takes in Pillow's decoded image, by mode (RGB is stored as 4 bytes).
BYTES_PER_PIXEL = {"1": 1, "L": 1, "P": 1, "I;16": 2, "I;16B": 2, "I;16L": 2}
DEFAULT_BYTES_PER_PIXEL = 4
# Pillow's WebP decoder holds the frame as RGBA three more times on the way (libwebp's buffer,
# the bytes it returns, the file object read from), as measured (benchmarks/bomb_memory.py).
DECODER_COPIES = {"WEBP": 4}
# After the full-size decode: the shrunk image, its orientation or RGB copy (4 bytes a pixel
# each), the array's bytes and the writable array handed to the networks (3 bytes a pixel each).
WORKING_BYTES_PER_PIXEL = 4 + 4 + 3 + 3


def decode_bytes(
    fmt: str, mode: str, decoded_pixels: int, converted: bool, working_pixels: int
) -> int:
    """Peak bytes of one decode: Pillow's image at its decoded size in format ``fmt`` (with
    ``converted``: plus an RGB copy at that size, for modes Pillow cannot shrink), then the
    working-size copies."""
    per_pixel = BYTES_PER_PIXEL.get(mode, DEFAULT_BYTES_PER_PIXEL)
    if fmt in DECODER_COPIES:
        per_pixel = DEFAULT_BYTES_PER_PIXEL * DECODER_COPIES[fmt]
    full = per_pixel + (DEFAULT_BYTES_PER_PIXEL if converted else 0)
    return decoded_pixels * full + working_pixels * WORKING_BYTES_PER_PIXEL


class DecodeBudget:
    """Bytes that the image decodes of a process may hold at once (``total``)."""

    def __init__(
        self, total: int, wait_seconds: float, setting: str = "LOOPNET_DECODE_MEMORY_BYTES"
    ):
        if total < 1 or wait_seconds <= 0:
            raise ValueError(f"need total >= 1, wait_seconds > 0; got {total}, {wait_seconds}")
        self.total = total
        self.wait_seconds = wait_seconds
        self.setting = setting
        self._cond = threading.Condition()
        self._used = 0
        self.peak = 0  # the most bytes reserved at once (for tests and benchmarks)

    @property
    def used(self) -> int:
        with self._cond:
            return self._used

    @contextmanager
    def reserve(self, nbytes: int) -> Iterator[None]:
        """Hold ``nbytes`` of the budget for the block: ImageTooLarge (413) when more than the
        whole budget, Overloaded (503) when it stays full for ``wait_seconds``."""
        if nbytes > self.total:
            raise ImageTooLarge(
                f"decoding the image takes about {nbytes} bytes, more than {self.setting}="
                f"{self.total}; send it smaller (the networks use a few hundred pixels a side)"
            )
        deadline = time.monotonic() + self.wait_seconds
        with self._cond:
            while self._used + nbytes > self.total:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise Overloaded(
                        "the images being decoded fill the decode memory budget; retry shortly"
                    )
                self._cond.wait(left)
            self._used += nbytes
            self.peak = max(self.peak, self._used)
        try:
            yield
        finally:
            with self._cond:
                self._used -= nbytes
                self._cond.notify_all()
