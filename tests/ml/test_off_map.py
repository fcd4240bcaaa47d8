"""The off-the-map test over a sequence match's newest frames (service.ml.sequences.off_map)."""

from __future__ import annotations

import pytest

from service.ml.sequences.off_map import OFF_MAP_FRAMES, left_the_map

ROUTE = [4.6, 6.0, 6.2, 7.7, 6.1, 4.6]  # frames that align well along the route


def test_a_robot_on_the_map_with_one_bland_frame_is_not_off_it() -> None:
    assert left_the_map(ROUTE + [0.2]) is None  # one weak frame is NEWEST_Z_MIN's to judge
    assert left_the_map(ROUTE + [0.9, 1.2, 1.4, 1.1]) is None  # a bland stretch, mean above 1.125


@pytest.mark.parametrize(
    ("newest", "frames"),
    [([0.2, 1.2], 2), ([1.2, -0.3, 1.2], 2), ([0.9, 0.8, 0.9], 3), ([1.0, 1.1, 1.1, 1.2], 4)],
)
def test_newest_frames_weak_together_say_off_the_map(newest: list[float], frames: int) -> None:
    """Nordland's off-route proxy: frames from an unmapped stretch score about 1 against the
    place the route would reach; the shortest weak run of newest frames is named."""
    found = left_the_map(ROUTE + newest)
    assert found is not None and found.frames == frames
    assert found.mean_z == pytest.approx(sum(newest[-frames:]) / frames)
    assert found.needed == pytest.approx(1.5 - 1.5 / frames)


def test_only_the_newest_frames_count_and_unaligned_frames_carry_no_evidence() -> None:
    weak_then_route = [0.0] * 6 + [3.0] * OFF_MAP_FRAMES
    assert left_the_map(weak_then_route) is None
    # frames that aligned with no map frame (-1) are left out, not read as weak
    aligned_z = [0.0, 0.0, 2.0, 1.0]
    assert left_the_map(aligned_z, aligned=[-1, -1, 10, 11]) is None
    assert left_the_map(aligned_z) is not None
    assert left_the_map([0.5]) is None  # one frame: nothing to compare
