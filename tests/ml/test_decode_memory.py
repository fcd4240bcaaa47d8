"""Decoding within a memory budget: large uploads are shrunk to what the networks use, every
decode holds its estimated peak from one budget, and keypoints keep the upload's pixels."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from service.errors import ImageTooLarge, Overloaded
from service.ml.decode_memory import DecodeBudget
from service.ml.features import FrameFeatures, LocalFeatures
from service.ml.images import REDUCE_MARGIN, DecodedFrame, decode_frame, in_upload_pixels
from tests.reliability.uploads import encode_image, pixel_bomb, solid_image

MB = 1024 * 1024


@pytest.mark.parametrize(
    ("fmt", "mode"),
    [
        ("PNG", "RGB"),
        ("JPEG", "RGB"),
        ("WEBP", "RGB"),
        ("PNG", "P"),
        ("PNG", "I;16"),
        ("PNG", "LA"),
    ],
)
def test_a_large_upload_is_shrunk_within_its_reservation(fmt: str, mode: str) -> None:
    """Issue 24: a 6300 x 6300 PNG of a few kilobytes cost 1.4 GB per request."""
    data = solid_image(6300, 6300, mode, fmt)
    assert len(data) < 1024 * 1024  # small on the wire
    budget = DecodeBudget(1024 * MB, 1.0)
    frame = decode_frame(data, working_side=256, budget=budget)
    assert frame.size == (6300, 6300) and frame.shrunk
    assert REDUCE_MARGIN * 256 <= max(frame.rgb.shape) < 2 * REDUCE_MARGIN * 256
    assert frame.rgb.dtype == np.uint8 and frame.rgb.shape[2] == 3
    # the estimate covers the full-size decode (4 bytes a pixel, 16 for WebP) and no more
    assert budget.used == 0 and 40 * MB < budget.peak < (700 if fmt == "WEBP" else 250) * MB


def test_small_uploads_are_decoded_as_before() -> None:
    data = encode_image(300, 200, "RGB", "JPEG", 0)
    frame = decode_frame(data, working_side=256, budget=DecodeBudget(64 * MB, 1.0))
    assert not frame.shrunk and frame.rgb.shape == (200, 300, 3)


def test_the_budget_refuses_a_decode_larger_than_itself() -> None:
    with pytest.raises(ImageTooLarge, match="LOOPNET_DECODE_MEMORY_BYTES"):
        decode_frame(pixel_bomb(4000, 4000), working_side=256, budget=DecodeBudget(8 * MB, 1.0))


def test_decodes_wait_for_room_and_give_up_after_the_wait() -> None:
    budget = DecodeBudget(100, 0.2)
    with budget.reserve(60):
        started = time.monotonic()
        with pytest.raises(Overloaded), budget.reserve(60):
            pass
        assert 0.15 < time.monotonic() - started < 2
        released: list[float] = []

        def later() -> None:
            with budget.reserve(60):
                released.append(time.monotonic())

        waiter = threading.Thread(target=later)
        budget.wait_seconds = 5
        waiter.start()
        time.sleep(0.1)
        assert not released  # still waiting for the first reservation
    waiter.join(5)
    assert released and budget.used == 0 and budget.peak == 60


def test_keypoints_of_a_shrunk_frame_are_in_the_uploads_pixels() -> None:
    frame = DecodedFrame(np.zeros((100, 200, 3), np.uint8), (800, 400))
    local = LocalFeatures(
        np.array([[-0.5, -0.5], [0.0, 0.0], [199.5, 99.5]], np.float32),
        np.ones((3, 4), np.float32) / 2,
        np.ones(3, np.float32),
    )
    features = FrameFeatures(local, np.ones(4, np.float32) / 2, np.ones(2, np.float32), (200, 100))
    mapped = in_upload_pixels(features, frame)
    np.testing.assert_allclose(mapped.local.keypoints, [[-0.5, -0.5], [1.5, 1.5], [799.5, 399.5]])
    assert mapped.image_size == (800, 400)
    assert in_upload_pixels(features, DecodedFrame(frame.rgb, (200, 100))) is features
