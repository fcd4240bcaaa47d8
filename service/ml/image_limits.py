"""Bounds on an uploaded image, apart from the decoder: the settings take their defaults from
here without importing torch."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ImageLimits:
    """Bounds on an upload, checked before decoding the pixels.

    ``min_side`` and ``max_aspect`` refuse images the extractors find nothing in (a 1x1, a
    40000x1 strip); ``pixels_setting`` names the setting behind ``max_pixels`` in messages.
    """

    max_bytes: int = 20 * 1024 * 1024
    max_pixels: int = 40_000_000
    min_side: int = 16
    max_aspect: float = 10.0
    pixels_setting: str = "LOOPNET_MAX_IMAGE_PIXELS"
