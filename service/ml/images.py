"""Decode uploaded bytes into RGB arrays and resize them for each network.

Decoding is strict: an empty, truncated or non-image upload and one over the byte or pixel
limits raise a typed error before any pixel buffer is allocated for the full image.

:func:`decode_frame` (what the service decodes uploads with) also bounds the memory a decode
takes: the networks resize every frame to a few hundred pixels a side, so a frame whose long
side exceeds :data:`REDUCE_MARGIN` times that working side is decoded at a reduced scale where
the format allows it (JPEG: scaled in the DCT, Pillow's ``draft``) and shrunk by an integer box
filter right after decoding otherwise; its estimated peak is reserved from a
:class:`~service.ml.decode_memory.DecodeBudget` shared by every decode of the process. The
frame's keypoints are then mapped back to the uploaded image's pixels (:func:`in_upload_pixels`),
so sizes, poses and intrinsics keep meaning the image the robot sent.
"""

from __future__ import annotations

import dataclasses
import io
import struct
import warnings
from contextlib import nullcontext
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image, ImageFile, ImageOps, UnidentifiedImageError

from service.errors import ImageTooLarge, InvalidImage
from service.ml.decode_memory import DecodeBudget, decode_bytes
from service.ml.features import FrameFeatures, LocalFeatures
from service.ml.image_limits import ImageLimits

ImageFile.LOAD_TRUNCATED_IMAGES = False
# MPO: the multi-picture JPEG many phone cameras write; its first picture is the photo.
SUPPORTED_FORMATS = ("JPEG", "MPO", "PNG", "WEBP")
# What Pillow raises on corrupt input, at open and at decode (found by fuzzing the decoder).
CORRUPT_IMAGE_ERRORS = (OSError, SyntaxError, ValueError, EOFError, struct.error)
# A frame keeps at least this many times the networks' working side: the box-filtered shrink
# then leaves the networks' own antialiased resize nearly all of its work.
REDUCE_MARGIN = 4
SHRINKABLE_MODES = frozenset({"L", "LA", "PA", "I", "F", "RGB", "RGBA", "RGBX", "CMYK", "YCbCr"})


@dataclass(frozen=True)
class DecodedFrame:
    """An uploaded image as the networks get it: ``rgb`` (``H x W x 3`` uint8, perhaps shrunk)
    and ``size``, the (width, height) of the image as uploaded (EXIF orientation applied)."""

    rgb: np.ndarray
    size: tuple[int, int]

    @property
    def shrunk(self) -> bool:
        return self.size != (self.rgb.shape[1], self.rgb.shape[0])


def decode_image(data: bytes, limits: ImageLimits | None = None) -> np.ndarray:
    """Decode JPEG/PNG/WebP bytes into an ``H x W x 3`` uint8 RGB array at full size, EXIF
    orientation applied.

    Raises:
        InvalidImage: empty, not an image, an unsupported format, or truncated.
        ImageTooLarge: more bytes or pixels than ``limits`` allow.
    """
    return decode_frame(data, limits).rgb


def decode_frame(
    data: bytes,
    limits: ImageLimits | None = None,
    *,
    working_side: int | None = None,
    budget: DecodeBudget | None = None,
) -> DecodedFrame:
    """:func:`decode_image`, kept at most about ``REDUCE_MARGIN x working_side`` on its long
    side (None: full size) while holding its estimated peak from ``budget``.

    Raises, besides :func:`decode_image`'s errors: ImageTooLarge when the decode alone would
    exceed the budget, Overloaded when the budget stays full for its wait.
    """
    image = _open_checked(data, limits or ImageLimits())
    width, height = image.size
    keep = REDUCE_MARGIN * working_side if working_side else None
    if keep and image.format in ("JPEG", "MPO") and max(width, height) > 2 * keep:
        ratio = keep / max(width, height)
        try:  # scaled in the DCT, to the smallest size still at least ``keep``
            image.draft(image.mode, (max(1, round(width * ratio)), max(1, round(height * ratio))))
        except CORRUPT_IMAGE_ERRORS as exc:
            raise InvalidImage(f"the image could not be decoded (corrupt): {exc}") from exc
    factor = max(1, max(image.size) // keep) if keep else 1
    convert_first = factor > 1 and image.mode not in SHRINKABLE_MODES
    decoded_pixels = image.size[0] * image.size[1]
    working_pixels = -(-image.size[0] // factor) * -(-image.size[1] // factor)
    estimate = decode_bytes(
        image.format or "", image.mode, decoded_pixels, convert_first, working_pixels
    )
    with budget.reserve(estimate) if budget is not None else nullcontext():
        try:
            image.load()
            if factor > 1:
                image = (image.convert("RGB") if convert_first else image).reduce(factor)
            shrunk_size = image.size
            ImageOps.exif_transpose(image, in_place=True)
            if image.mode != "RGB":
                image = image.convert("RGB")
            array = np.asarray(image, dtype=np.uint8)
            turned = image.size != shrunk_size
            del image  # Pillow's copy goes before the array's
            rgb = array.copy()
        except CORRUPT_IMAGE_ERRORS as exc:
            raise InvalidImage(
                f"the image could not be decoded (truncated or corrupt): {exc}"
            ) from exc
    return DecodedFrame(rgb, (height, width) if turned else (width, height))


def in_upload_pixels(features: FrameFeatures, frame: DecodedFrame) -> FrameFeatures:
    """``features`` extracted from ``frame.rgb`` with keypoints and image size in the pixels of
    the image as uploaded (a shrunk frame's pixel centres mapped back)."""
    if not frame.shrunk:
        return features
    height, width = frame.rgb.shape[:2]
    scale = np.array([frame.size[0] / width, frame.size[1] / height], np.float32)
    local = features.local
    keypoints = ((local.keypoints + 0.5) * scale - 0.5).astype(np.float32)
    return dataclasses.replace(
        features,
        local=LocalFeatures(keypoints, local.descriptors, local.scores),
        image_size=frame.size,
    )


def _open_checked(data: bytes, limits: ImageLimits) -> Image.Image:
    """The opened (not yet decoded) image, its format, size and shape checked."""
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
    return image


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
