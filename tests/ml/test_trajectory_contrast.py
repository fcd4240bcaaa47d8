"""Trajectory contrast: a frame less the mean of its robot's previous frames, by hand and as
the sequence map keeps it while frames stream in."""

from __future__ import annotations

import numpy as np

from service.app.sequence_map import SequenceMap
from service.ml.sequences import Trajectories
from service.ml.sequences.contrast import (
    context_positions,
    contrasted_frames,
    contrasted_query,
)
from tests.app.test_trajectory_growth import stream


def unit(rows: np.ndarray) -> np.ndarray:
    rows = np.asarray(rows, np.float32)
    return rows / np.linalg.norm(rows, axis=1, keepdims=True)


def test_context_is_the_frames_before_in_the_same_sequence() -> None:
    # robot a: frames 0, 2, 3 (a gap cuts before 3); robot b: 1, 4
    trajectories = Trajectories.build(
        ["a", "b", "a", "a", "b"], [0.0, 0.0, 1.0, 60.0, 1.0], max_gap_seconds=10.0
    )
    context = context_positions(trajectories, np.array([0, 2, 3, 4]), 2)
    np.testing.assert_array_equal(context, [[-1, -1], [0, -1], [-1, -1], [1, -1]])


def test_contrasted_by_hand() -> None:
    vectors = unit([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 1.0]])
    trajectories = Trajectories.single(3)
    out = contrasted_frames(lambda p: vectors[p], trajectories, np.arange(3), window=2)
    # frame 0 has no context: zero, never alike
    np.testing.assert_array_equal(out[0], [0.0, 0.0, 0.0])
    # frame 1 less frame 0: (-1, 1, 0) / sqrt(2)
    np.testing.assert_allclose(out[1], np.array([-1.0, 1.0, 0.0]) / np.sqrt(2), atol=1e-6)
    # frame 2 less the mean of frames 0 and 1
    expected = vectors[2] - (vectors[0] + vectors[1]) / 2
    np.testing.assert_allclose(out[2], expected / np.linalg.norm(expected), atol=1e-6)
    # a query is contrasted the same way against the frames before it
    np.testing.assert_allclose(contrasted_query(vectors[2], vectors[:2]), out[2], atol=1e-6)
    assert contrasted_query(vectors[2], vectors[:0]) is None


def test_a_shared_condition_cancels() -> None:
    """Two traversals of the same places under different conditions (a large offset shared by
    each traversal's frames) only match once each is contrasted with its own recent past."""
    rng = np.random.default_rng(0)
    places = rng.normal(size=(40, 64))
    summer, winter = rng.normal(size=64) * 4, rng.normal(size=64) * 4
    first, second = unit(places + summer), unit(places + winter + rng.normal(size=(40, 64)) * 0.3)
    trajectories = Trajectories.single(40)
    a = contrasted_frames(lambda p: first[p], trajectories, np.arange(40), window=10)
    b = contrasted_frames(lambda p: second[p], trajectories, np.arange(40), window=10)
    plain_right = np.mean(np.argmax(second[10:] @ first.T, axis=1) == np.arange(10, 40))
    contrasted_right = np.mean(np.argmax(b[10:] @ a.T, axis=1) == np.arange(10, 40))
    assert contrasted_right > plain_right
    assert contrasted_right >= 0.9


def test_map_contrasts_frames_as_they_stream_like_a_rebuild() -> None:
    """Frames appended one by one (late ones rebuild the trajectories) hold the contrasted
    vectors a map built from all of them at once holds, and the same moments."""
    robots, times = stream(3, frames=200)
    vectors = unit(np.random.default_rng(1).normal(size=(len(robots), 16)))
    streamed = SequenceMap(0, 0, 16, 10.0, contrast_window=4)
    for i, (robot, time) in enumerate(zip(robots, times, strict=True)):
        streamed.append([(i + 1, robot, time)], vectors[i : i + 1])
    built = SequenceMap(0, 0, 16, 10.0, contrast_window=4)
    built.append(
        [(i + 1, r, t) for i, (r, t) in enumerate(zip(robots, times, strict=True))], vectors
    )
    np.testing.assert_allclose(streamed.contrasted, built.contrasted, atol=1e-6)
    queries = vectors[:5]
    for mine, theirs in zip(
        streamed.contrast_moments.row_stats(queries),
        built.contrast_moments.row_stats(queries),
        strict=True,
    ):
        np.testing.assert_allclose(mine, theirs, atol=1e-6)
    assert SequenceMap(0, 0, 16, 10.0).contrasted.shape == (0, 16)
