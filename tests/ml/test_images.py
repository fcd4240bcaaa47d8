"""Decoding: formats, EXIF orientation, and a clear error for every kind of bad upload."""

from __future__ import annotations

import io
import struct
import zlib

import numpy as np
import pytest
from PIL import Image

from service.errors import ImageTooLarge, InvalidImage
from service.ml.images import ImageLimits, decode_image, resize_long_side, to_tensor
from tests.conftest import encode, gardens_point_day_night
from tests.reliability.uploads import multi_picture_jpeg


def test_decodes_real_jpeg_to_rgb() -> None:
    rgb = decode_image(gardens_point_day_night(0, "query"))
    assert rgb.shape == (540, 960, 3) and rgb.dtype == np.uint8


@pytest.mark.parametrize("fmt", ["PNG", "JPEG", "WEBP"])
def test_supported_formats(fmt: str) -> None:
    array = np.random.default_rng(0).integers(0, 255, (30, 40, 3), dtype=np.uint8)
    assert decode_image(encode(array, fmt)).shape == (30, 40, 3)


def test_grayscale_and_rgba_become_rgb() -> None:
    gray = np.full((20, 24), 128, np.uint8)
    assert decode_image(encode(gray)).shape == (20, 24, 3)
    rgba = np.full((20, 24, 4), 200, np.uint8)
    assert decode_image(encode(rgba)).shape == (20, 24, 3)


def test_exif_orientation_is_applied() -> None:
    array = np.zeros((20, 40, 3), np.uint8)  # landscape
    image = Image.fromarray(array)
    exif = image.getexif()
    exif[0x0112] = 6  # rotate 90 degrees clockwise on display
    buffer = io.BytesIO()
    image.save(buffer, format="JPEG", exif=exif)
    assert decode_image(buffer.getvalue()).shape == (40, 20, 3)


def test_empty_upload() -> None:
    with pytest.raises(InvalidImage, match="empty"):
        decode_image(b"")


def test_not_an_image() -> None:
    with pytest.raises(InvalidImage, match="not a JPEG, PNG or WebP"):
        decode_image(b"%PDF-1.4 this is a document")


def test_unsupported_format() -> None:
    buffer = io.BytesIO()
    Image.new("RGB", (8, 8)).save(buffer, format="BMP")
    with pytest.raises(InvalidImage, match="BMP is not supported"):
        decode_image(buffer.getvalue())


def test_truncated_image() -> None:
    data = gardens_point_day_night(0, "query")
    with pytest.raises(InvalidImage, match="truncated or corrupt"):
        decode_image(data[: len(data) // 2])


def test_byte_limit() -> None:
    with pytest.raises(ImageTooLarge, match="bytes"):
        decode_image(b"x" * 2048, ImageLimits(max_bytes=1024))


def test_pixel_limit_is_checked_before_decoding() -> None:
    big = encode(np.zeros((200, 300, 3), np.uint8))
    with pytest.raises(ImageTooLarge, match="LOOPNET_MAX_IMAGE_PIXELS=50000: it is 300x200"):
        decode_image(big, ImageLimits(max_pixels=50_000))


def test_pillows_own_bomb_limit_is_reported_as_ours() -> None:
    # Over Pillow's own decompression-bomb threshold: the message still names our setting.
    with pytest.raises(ImageTooLarge, match="LOOPNET_MAX_IMAGE_PIXELS") as raised:
        decode_image(forged_png(30_000, 30_000))
    assert str(Image.MAX_IMAGE_PIXELS) not in str(raised.value)


def test_multi_picture_jpeg_decodes_to_its_first_picture() -> None:
    mpo = multi_picture_jpeg(32, 24)
    assert Image.open(io.BytesIO(mpo)).format == "MPO"
    first = np.asarray(Image.open(io.BytesIO(mpo)).convert("RGB"))
    rgb = decode_image(mpo)
    assert rgb.shape == (24, 32, 3)
    np.testing.assert_array_equal(rgb, first)


@pytest.mark.parametrize(("width", "height"), [(1, 1), (40_000, 1), (15, 40), (400, 20)])
def test_images_below_the_minimum_size_are_refused(width: int, height: int) -> None:
    image = encode(np.zeros((height, width, 3), np.uint8))
    with pytest.raises(InvalidImage, match="at least 16 pixels on each side"):
        decode_image(image)


def forged_png(width: int, height: int) -> bytes:
    """A tiny PNG whose header claims ``width x height`` pixels."""
    bomb = encode(np.zeros((1, 1, 3), np.uint8))
    ihdr = bomb.index(b"IHDR")
    header = b"IHDR" + struct.pack(">II", width, height) + bomb[ihdr + 12 : ihdr + 17]
    crc = struct.pack(">I", zlib.crc32(header) & 0xFFFFFFFF)
    return bomb[:ihdr] + header + crc + bomb[ihdr + 21 :]


def test_decompression_bomb_header() -> None:
    # A tiny PNG that claims 30000 x 30000 pixels: refused from its header alone.
    with pytest.raises(ImageTooLarge):
        decode_image(forged_png(30_000, 30_000))


def test_resize_long_side_up_and_down() -> None:
    small = to_tensor(np.zeros((32, 64, 3), np.uint8))
    assert tuple(resize_long_side(small, 256).shape[-2:]) == (128, 256)
    large = to_tensor(np.zeros((540, 960, 3), np.uint8))
    assert tuple(resize_long_side(large, 480).shape[-2:]) == (270, 480)
