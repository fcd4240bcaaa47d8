"""Per-atlas minimum inliers: hard impostors and the threshold above them."""

from __future__ import annotations

import numpy as np
import pytest

from service.ml.inlier_threshold import FLOOR, StayScores, fit_inlier_threshold, hard_impostors


def test_hard_impostors_are_the_most_similar_frames_of_other_places() -> None:
    # one robot, two laps of 20 places: neighbours in time look alike, and frame i + 20 is a
    # look-alike of frame i (a revisit the sequence alone cannot tell apart)
    angles = (np.arange(40) % 20) * (2 * np.pi / 20)
    embeddings = np.stack([np.cos(angles), np.sin(angles), np.zeros(40)], 1)
    embeddings[20:, 2] = 0.2  # the second lap is a slightly different version of the first
    embeddings /= np.linalg.norm(embeddings, axis=1, keepdims=True)
    pairs = hard_impostors(embeddings, ["r"] * 40, np.arange(40), frames=40)
    assert len(pairs) == 40
    for i, j in pairs:
        assert abs(i - j) >= 5  # never the frame's own neighbourhood
        assert abs(i - j) == 20  # but its look-alike from the other lap
    other_robot = hard_impostors(embeddings, ["a"] * 20 + ["b"] * 20, np.arange(40), frames=40)
    assert all(abs(i - j) == 20 for i, j in other_robot)  # another robot's frame may be close


def test_the_minimum_sits_just_above_the_impostors() -> None:
    threshold = fit_inlier_threshold("mnn", [3] * 95 + [30, 31, 32, 33, 60])
    assert (
        threshold.min_inliers
        == int(np.floor(np.quantile([3] * 95 + [30, 31, 32, 33, 60], 0.99))) + 1
    )
    assert threshold.impostor_max == 60 and threshold.accepted_impostors == 1
    assert fit_inlier_threshold("lightglue", [0, 1, 2]).min_inliers == FLOOR
    with pytest.raises(ValueError):
        fit_inlier_threshold("mnn", [])


def test_a_robots_frames_of_one_stop_are_not_each_others_impostors() -> None:
    """A robot drives 30 places 12 degrees apart on a circle but stands at place 10 for 15
    frames (frames 10-24), longer than the 5-frame gap: without stays, a frame of the stop
    finds its hard impostor in the stop itself (cosine 1, the same place); with them, among
    the places before and after it."""
    places = [*range(10), *[10] * 15, *range(11, 30)]
    angles = np.radians(12.0 * np.array(places))
    embeddings = np.stack([np.cos(angles), np.sin(angles)], 1)
    stop = set(range(10, 25))
    blind = hard_impostors(embeddings, ["r"] * len(places), np.arange(len(places)), frames=44)
    assert any(i in stop and j in stop for i, j in blind)

    # score: 2 (the place) for identical frames, below 0 for neighbouring places (cos 12 deg)
    stays = StayScores(lambda cosines: 100.0 * (cosines - 0.98), alike=1.5, elsewhere=1.0)
    seeing = hard_impostors(
        embeddings, ["r"] * len(places), np.arange(len(places)), frames=44, stays=stays
    )
    assert len(seeing) == len(places)
    for i, j in seeing:
        assert not (i in stop and j in stop), (i, j)
        assert abs(places[i] - places[j]) == 1 or abs(i - j) >= 5  # a neighbouring place
