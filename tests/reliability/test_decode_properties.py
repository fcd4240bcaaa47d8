"""Property tests of the decoder: any bytes give an RGB array or a typed 4xx error, never more."""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from service.errors import ImageTooLarge, InvalidImage
from service.ml.decode_memory import DecodeBudget
from service.ml.images import ImageLimits, decode_frame, decode_image
from tests.reliability.uploads import (
    broken_images,
    image_uploads,
    pixel_bomb,
    small_but_huge_images,
    valid_images,
)

LIMITS = ImageLimits(max_bytes=200_000, max_pixels=1_000_000)
FAST = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@FAST
@given(valid_images())
def test_every_valid_tiny_image_decodes_to_rgb(data: bytes) -> None:
    rgb = decode_image(data, LIMITS)
    assert rgb.dtype == np.uint8 and rgb.ndim == 3 and rgb.shape[2] == 3
    assert 16 <= rgb.shape[0] <= 48 and 16 <= rgb.shape[1] <= 48


@FAST
@given(st.one_of(broken_images(), image_uploads(), st.binary(max_size=4096)))
def test_any_bytes_decode_or_raise_a_typed_error(data: bytes) -> None:
    try:
        rgb = decode_image(data, LIMITS)
    except (InvalidImage, ImageTooLarge) as error:
        assert str(error)  # a message the client can read
    else:
        assert rgb.dtype == np.uint8 and rgb.shape[2] == 3


@FAST
@given(st.one_of(small_but_huge_images(), broken_images(), image_uploads()))
def test_the_service_decode_shrinks_or_raises_a_typed_error(data: bytes) -> None:
    """As the service decodes (working side 256, a budget): a frame at most 8 x 256 a side,
    its size the upload's, the budget given back."""
    budget = DecodeBudget(64 * 1024 * 1024, 1.0)
    try:
        frame = decode_frame(data, LIMITS, working_side=256, budget=budget)
    except (InvalidImage, ImageTooLarge) as error:
        assert str(error)
    else:
        assert frame.rgb.dtype == np.uint8 and frame.rgb.shape[2] == 3
        assert max(frame.rgb.shape[:2]) < 8 * 256
        assert frame.size[0] >= frame.rgb.shape[1] and frame.size[1] >= frame.rgb.shape[0]
    assert budget.used == 0


def test_pixel_bombs_are_refused_before_decoding() -> None:
    bomb = pixel_bomb(1500, 1500)
    assert len(bomb) < LIMITS.max_bytes  # small on the wire
    try:
        decode_image(bomb, LIMITS)
    except ImageTooLarge as error:
        assert "2250000 pixels" in str(error)
    else:
        raise AssertionError("a 1500x1500 image passed a 1,000,000 pixel limit")
