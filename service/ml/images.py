"""Decode uploaded bytes into RGB arrays and resize them for each network.

Decoding is strict: an empty, truncated or non-image upload and one over the byte or pixel
limits raise a typed error before any pixel buffer is allocated for the full image.
"""

from __future__ import annotations

import io
import struct
import warnings

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image, ImageFile, ImageOps, UnidentifiedImageError

from service.errors import ImageTooLarge, InvalidImage
from service.ml.image_limits import ImageLimits

ImageFile.LOAD_TRUNCATED_IMAGES = False
# MPO: the multi-picture JPEG many phone cameras write; its first picture is the photo.
SUPPORTED_FORMATS = ("JPEG", "MPO", "PNG", "WEBP")
# What Pillow raises on corrupt input, at open and at decode (found by fuzzing the decoder).
CORRUPT_IMAGE_ERRORS = (OSError, SyntaxError, ValueError, EOFError, struct.error)


def decode_image(data: bytes, limits: ImageLimits | None = None) -> np.ndarray:
    """Decode JPEG/PNG/WebP bytes into an ``H x W x 3`` uint8 RGB array, EXIF orientation applied.

    Raises:
        InvalidImage: empty, not an image, an unsupported format, or truncated.
        ImageTooLarge: more bytes or pixels than ``limits`` allow.
    """
    limits = limits or ImageLimits()
    too_many_pixels = f"the image has more pixels than {limits.pixels_setting}={limits.max_pixels}"
    if not data:
        raise InvalidImage("the uploaded file is empty")
    if len(data) > limits.max_bytes:
        raise ImageTooLarge(f"the upload is {len(data)} bytes; the limit is {limits.max_bytes}")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            image = Image.open(io.BytesIO(data))
    except UnidentifiedImageError as exc:
        raise InvalidImage("the upload is not a JPEG, PNG or WebP image") from exc
    except (Image.DecompressionBombWarning, Image.DecompressionBombError) as exc:
        raise ImageTooLarge(too_many_pixels) from exc
    except CORRUPT_IMAGE_ERRORS as exc:
        raise InvalidImage(
            f"the image header could not be read (truncated or corrupt): {exc}"
        ) from exc
    if image.format not in SUPPORTED_FORMATS:
        raise InvalidImage(f"image format {image.format} is not supported; send JPEG, PNG or WebP")
    width, height = image.size
    if width * height > limits.max_pixels:
        raise ImageTooLarge(f"{too_many_pixels}: it is {width}x{height} = {width * height} pixels")
    _check_shape(width, height, limits)
    try:
        image.load()
        rgb = (ImageOps.exif_transpose(image) or image).convert("RGB")
    except CORRUPT_IMAGE_ERRORS as exc:
        raise InvalidImage(f"the image could not be decoded (truncated or corrupt): {exc}") from exc
    return np.asarray(rgb, dtype=np.uint8).copy()


def _check_shape(width: int, height: int, limits: ImageLimits) -> None:
    short, long = sorted((width, height))
    if short < limits.min_side or long > limits.max_aspect * short:
        raise InvalidImage(
            f"the image is {width}x{height}; it needs at least {limits.min_side} pixels on each "
            f"side and a long side at most {limits.max_aspect:g} times the short one"
        )


def to_tensor(rgb: np.ndarray) -> torch.Tensor:
    """``H x W x 3`` uint8 -> ``1 x 3 x H x W`` float32 in [0, 1]."""
    return torch.from_numpy(rgb).permute(2, 0, 1).unsqueeze(0).float().div_(255.0)


def resize_long_side(image: torch.Tensor, long_side: int) -> torch.Tensor:
    """Resize ``B x 3 x H x W`` so its long side is ``long_side``, keeping the aspect ratio.

    Images are both downsampled (antialiased) and upsampled: DISK was trained near 1024 px and
    the paper resizes every frame to that long side.
    """
    h, w = image.shape[-2:]
    scale = long_side / max(h, w)
    size = (max(1, round(h * scale)), max(1, round(w * scale)))
    if size == (h, w):
        return image
    return F.interpolate(
        image, size=size, mode="bilinear", align_corners=False, antialias=scale < 1
    )


def resize_exact(image: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Resize ``B x 3 x H x W`` to exactly ``height x width`` (the backbone's input)."""
    if tuple(image.shape[-2:]) == (height, width):
        return image
    down = image.shape[-2] > height or image.shape[-1] > width
    return F.interpolate(
        image, size=(height, width), mode="bilinear", align_corners=False, antialias=down
    )
