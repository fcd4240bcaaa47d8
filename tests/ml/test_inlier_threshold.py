"""Per-atlas minimum inliers: hard impostors and the threshold above them."""

from __future__ import annotations

import numpy as np
import pytest

from service.ml.inlier_threshold import (
    FLOOR,
    fit_inlier_threshold,
    hard_impostors,
    midpoints,
    one_stop,
)
from service.ml.stays import StayRule


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
    # unless the fleet verified it as the same place: then the place's neighbourhood is left
    # out and the hard impostor is a frame of another place
    known = np.array([[3, 23]])
    revisited = dict(
        hard_impostors(
            embeddings, ["a"] * 20 + ["b"] * 20, np.arange(40), frames=40, same_place=known
        )
    )
    assert revisited[3] not in range(20, 28)  # b's frames within 5 of the revisit
    assert revisited[23] not in range(0, 8)
    assert revisited[4] == 24  # frames without a known revisit keep their look-alike


def test_the_minimum_sits_just_above_the_impostors() -> None:
    threshold = fit_inlier_threshold("mnn", [3] * 95 + [30, 31, 32, 33, 60])
    assert (
        threshold.min_inliers
        == int(np.floor(np.quantile([3] * 95 + [30, 31, 32, 33, 60], 0.99))) + 1
    )
    assert threshold.impostor_max == 60 and threshold.accepted_impostors == 1
    assert threshold.impostor_highest[:3] == (60, 33, 32) and threshold.impostor_median == 3
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
    stays = StayRule(lambda cosines: 100.0 * (cosines - 0.98), alike=1.5, elsewhere=1.0)
    seeing = hard_impostors(
        embeddings, ["r"] * len(places), np.arange(len(places)), frames=44, stays=stays
    )
    assert len(seeing) == len(places)
    for i, j in seeing:
        assert not (i in stop and j in stop), (i, j)
        assert abs(places[i] - places[j]) == 1 or abs(i - j) >= 5  # a neighbouring place


def test_a_pair_of_one_robots_frames_is_checked_halfway() -> None:
    """The frame halfway along the robot's sequence (by its order, not by row), for pairs of
    one robot with a frame in between; none for two robots or neighbours."""
    robots = ["a", "b", "a", "a", "b", "a", "a"]
    order = np.array([0, 0, 1, 2, 1, 3, 4])  # robot a's rows 0, 2, 3, 5, 6 in that order
    assert midpoints(robots, order, [(0, 6), (6, 0), (0, 2), (0, 1), (2, 5)]) == [3, 3, -1, -1, 3]


def test_one_stop_is_a_near_duplicate_whose_middle_matches_too() -> None:
    assert one_stop(250, 240, keypoints=500)  # a train standing at a station
    assert not one_stop(250, 100, keypoints=500)  # the frames in between show other places
    # frames along a straight route overlap: the middle matches better, but the pair is no
    # near duplicate (gardenspoint_cohog200: 15-22 inliers of 275-392 keypoints)
    assert not one_stop(22, 56, keypoints=354)
    assert not one_stop(14, 14, keypoints=40)  # below the floor, nothing is evidence
    assert fit_inlier_threshold("mnn", [10, 20], one_stop_pairs=3).one_stop_pairs == 3
