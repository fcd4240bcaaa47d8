"""Sequence scoring, trajectory order and temporal consistency on synthetic trajectories whose
answers are known by construction."""

from __future__ import annotations

import numpy as np
import pytest

from service.ml.sequences import (
    TRACKING_DROPOUT,
    ConsistencySettings,
    Distinctiveness,
    Hypothesis,
    MapMoments,
    PlaceStatus,
    SequenceMatch,
    SequenceSettings,
    Trajectories,
    consistent_scores,
    continues_loop,
    decide,
    distinctiveness,
    margin_needed,
    match_sequence,
    runs_ahead,
    score_candidates,
    sequence_starts,
)


def _unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=-1, keepdims=True)).astype(np.float32)


def _aliased_route(rng: np.random.Generator, places: int, looks: int, dim: int = 32):
    """A route of ``places`` frames that each look like one of only ``looks`` appearances:
    every frame has many look-alikes, but a run of consecutive appearances is unique."""
    appearance = _unit(rng.normal(size=(looks, dim)))
    label = rng.integers(0, looks, size=places)
    return appearance, label


def _seeds(queries: np.ndarray, reference: np.ndarray, k: int) -> list[np.ndarray]:
    return [np.argsort(-(reference @ q), kind="stable")[:k] for q in queries]


def test_single_frames_are_ambiguous_and_the_sequence_is_not() -> None:
    rng = np.random.default_rng(0)
    appearance, label = _aliased_route(rng, places=300, looks=6)
    reference = _unit(appearance[label] + 0.15 * rng.normal(size=(300, 32)))
    query = _unit(appearance[label] + 0.15 * rng.normal(size=(300, 32)))
    trajectories = Trajectories.single(300)
    moments = MapMoments.of(reference)
    settings = SequenceSettings(length=8, speeds=(1.0,), seeds=60)
    single_right = sequence_right = 0
    tested = range(20, 300, 7)
    for t in tested:
        single_right += int(abs(int(np.argmax(reference @ query[t])) - t) <= 0)
        window = query[t - 7 : t + 1]
        matches = match_sequence(
            window,
            _seeds(window, reference, 60),
            lambda i: reference[i],
            trajectories,
            moments,
            settings,
        )
        assert matches[0].length == 8
        assert matches[0].aligned == tuple(
            range(matches[0].reference - 7, matches[0].reference + 1)
        )
        sequence_right += int(matches[0].reference == t)
    assert single_right / len(tested) < 0.4
    assert sequence_right == len(tested)


def test_a_speed_within_the_range_is_found() -> None:
    rng = np.random.default_rng(1)
    appearance, label = _aliased_route(rng, places=400, looks=5)
    reference = _unit(appearance[label] + 0.1 * rng.normal(size=(400, 32)))
    trajectories = Trajectories.single(400)
    moments = MapMoments.of(reference)
    for speed in (0.8, 1.25):
        # the robot passes `speed` reference frames per query frame, ending at frame 120
        places = 120 - np.rint(speed * np.arange(12)[::-1]).astype(int)
        query = _unit(appearance[label[places]] + 0.1 * rng.normal(size=(12, 32)))
        seeds = _seeds(query, reference, 80)
        ranged = match_sequence(
            query,
            seeds,
            lambda i: reference[i],
            trajectories,
            moments,
            SequenceSettings(length=12, speeds=(0.8, 0.9, 1.0, 1.1, 1.25), seeds=80),
        )
        fixed = match_sequence(
            query,
            seeds,
            lambda i: reference[i],
            trajectories,
            moments,
            SequenceSettings(length=12, speeds=(1.0,), seeds=80),
        )
        assert ranged[0].reference == places[-1]
        assert ranged[0].speed == speed
        assert ranged[0].aligned == tuple(int(p) for p in places)
        assert ranged[0].score > fixed[0].score


def test_reverse_traversal_is_found_only_when_asked() -> None:
    rng = np.random.default_rng(2)
    appearance, label = _aliased_route(rng, places=200, looks=5)
    reference = _unit(appearance[label] + 0.1 * rng.normal(size=(200, 32)))
    places = np.arange(150, 140, -1)
    query = _unit(appearance[label[places]] + 0.1 * rng.normal(size=(10, 32)))
    trajectories, moments = Trajectories.single(200), MapMoments.of(reference)
    seeds = _seeds(query, reference, 60)
    both = SequenceSettings(length=10, speeds=(1.0,), reverse=True, seeds=60)
    matches = match_sequence(query, seeds, lambda i: reference[i], trajectories, moments, both)
    assert (matches[0].reference, matches[0].speed) == (141, -1.0)


def test_map_moments_equal_the_full_similarity_rows() -> None:
    rng = np.random.default_rng(3)
    reference = _unit(rng.normal(size=(500, 16)))
    query = _unit(rng.normal(size=(4, 16)))
    moments = MapMoments(16, fold_every=8)
    moments.add(reference[:450])  # folded at once
    for vector in reference[450:]:  # one at a time: pending, folded every 8
        moments.add(vector)
    moments.add(reference[:3])
    moments.remove(reference[:3])
    full = query @ reference.T
    for _ in range(2):
        mean, std = moments.row_stats(query)
        np.testing.assert_allclose(mean, full.mean(axis=1), atol=1e-6)
        np.testing.assert_allclose(std, full.std(axis=1), atol=1e-6)
        moments.add(reference[:5])
        moments.remove(reference[:5])  # exact with frames still pending


def test_a_time_gap_or_a_jump_back_starts_a_new_sequence() -> None:
    starts = sequence_starts([0.0, 1.0, None, 2.0, 40.0, 41.0, 5.0, 6.0], max_gap_seconds=30)
    assert starts.tolist() == [True, False, False, False, True, False, True, False]
    # two robots interleaved, one with a gap; frames without timestamps keep arrival order
    robots = ["a", "b", "a", "b", "a", "a", "b"]
    times = [0.0, None, 1.0, None, 100.0, 101.0, None]
    t = Trajectories.build(robots, times, max_gap_seconds=30)
    assert t.recent(5, 10).tolist() == [4, 5]  # the gap cut robot a's sequence
    assert t.recent(2, 10).tolist() == [0, 2]
    assert t.recent(6, 10).tolist() == [1, 3, 6]
    assert t.step(np.array([4]), np.array([-1])).tolist() == [-1]  # never walks across the cut
    # timestamps reorder frames that arrived out of order
    shuffled = Trajectories.build(["a"] * 3, [2.0, 1.0, 3.0])
    assert shuffled.recent(2, 3).tolist() == [1, 0, 2]


def test_sequence_scoring_resets_after_a_gap() -> None:
    rng = np.random.default_rng(4)
    appearance, label = _aliased_route(rng, places=200, looks=6)
    reference = _unit(appearance[label] + 0.1 * rng.normal(size=(200, 32)))
    # the map was driven in two sessions with a long pause after frame 99
    times = [float(i) if i < 100 else 1000.0 + i for i in range(200)]
    trajectories = Trajectories.build(["map"] * 200, times, max_gap_seconds=30)
    moments = MapMoments.of(reference)
    query = _unit(appearance[label[96:104]] + 0.1 * rng.normal(size=(8, 32)))
    matches = match_sequence(
        query,
        _seeds(query, reference, 60),
        lambda i: reference[i],
        trajectories,
        moments,
        SequenceSettings(length=8, speeds=(1.0,), seeds=60),
    )
    best = next(m for m in matches if m.reference == 103)
    assert best.length == 4  # frames 100..103 only: 96..99 lie in the other session
    assert best.aligned == (-1, -1, -1, -1, 100, 101, 102, 103)


def test_consistency_needs_k_agreeing_observations() -> None:
    t = Trajectories.build(["a"] * 50 + ["b"] * 50)
    settings = ConsistencySettings(required=3, max_step=2)
    seen: list[Hypothesis | None] = []
    statuses = []
    for reference, passed in [
        (10, True),
        (11, True),
        (12, True),
        (13, True),
        (40, True),
        (41, True),
        (42, False),
        (60, True),
        (None, False),
    ]:
        seen.append(None if reference is None else Hypothesis(reference, passed))
        statuses.append(decide(seen, t, settings))
    assert [d.status for d in statuses] == [
        PlaceStatus.CANDIDATE,
        PlaceStatus.CANDIDATE,
        PlaceStatus.LOOP,
        PlaceStatus.LOOP,
        PlaceStatus.CANDIDATE,
        PlaceStatus.CANDIDATE,
        PlaceStatus.NEW_PLACE,
        PlaceStatus.CANDIDATE,
        PlaceStatus.NEW_PLACE,
    ]
    assert [d.consistent for d in statuses] == [1, 2, 3, 3, 1, 2, 0, 1, 0]
    # frames 49 and 50 are neighbours by index but belong to two robots: no agreement
    assert (
        decide(
            [Hypothesis(48, True), Hypothesis(49, True), Hypothesis(50, True)], t, settings
        ).consistent
        == 1
    )


def test_consistent_scores_give_decide_at_every_threshold() -> None:
    rng = np.random.default_rng(5)
    t = Trajectories.single(100)
    references = np.array([10, 11, 13, 14, 70, 71, 72, 72, -1, 30, 31, 32])
    scores = rng.uniform(0, 1, size=len(references))
    settings = ConsistencySettings(required=3, max_step=2)
    accept_at = consistent_scores(references, scores, t, settings)
    for threshold in np.r_[scores, 0.0, 1.0]:
        history = [
            None if r < 0 else Hypothesis(int(r), bool(s >= threshold))
            for r, s in zip(references, scores, strict=True)
        ]
        for i in range(len(history)):
            loop = decide(history[: i + 1], t, settings).status is PlaceStatus.LOOP
            assert loop == bool(accept_at[i] >= threshold)


def test_settings_reject_nonsense() -> None:
    with pytest.raises(ValueError):
        SequenceSettings(length=0)
    with pytest.raises(ValueError):
        SequenceSettings(speeds=(0.0,))
    with pytest.raises(ValueError):
        ConsistencySettings(required=0)


def test_local_contrast_standardises_against_the_aligned_frames_neighbours() -> None:
    rng = np.random.default_rng(6)
    reference = _unit(rng.normal(size=(60, 8)))
    query = _unit(reference[20:25] + 0.1 * rng.normal(size=(5, 8)))
    settings = SequenceSettings(length=5, speeds=(1.0,), contrast_window=4)
    trajectories = Trajectories.single(60)
    [match] = score_candidates(
        query,
        np.array([24]),
        lambda i: reference[i],
        trajectories,
        MapMoments.of(reference).row_stats(query),
        settings,
    )
    expected = 0.0
    for row, frame in enumerate(range(20, 25)):
        window = query[row] @ reference[frame - 2 : frame + 3].T
        expected += (query[row] @ reference[frame] - window.mean()) / window.std()
    assert match.score == pytest.approx(expected / np.sqrt(5), rel=1e-5)
    assert match.aligned == (20, 21, 22, 23, 24)


def test_a_restarted_replica_rebuilt_from_stored_rows_answers_the_same() -> None:
    """One process grew its state frame by frame; another rebuilt it from the stored rows
    (vectors, robots, timestamps) at once: the same sequence answer, to rounding."""
    rng = np.random.default_rng(7)
    appearance, label = _aliased_route(rng, places=240, looks=6)
    reference = _unit(appearance[label] + 0.1 * rng.normal(size=(240, 32)))
    robots = ["a" if i % 3 else "b" for i in range(240)]
    times = [float(i) for i in range(240)]
    grown = MapMoments(32, fold_every=16)
    for vector in reference:
        grown.add(vector)
    rebuilt = MapMoments.of(reference)
    order_a = Trajectories.build(robots, times, max_gap_seconds=30)
    order_b = Trajectories.build(robots, times, max_gap_seconds=30)
    query = _unit(reference[order_a.recent(200, 6)] + 0.05 * rng.normal(size=(6, 32)))
    seeds = _seeds(query, reference, 50)
    settings = SequenceSettings(length=6)
    first = match_sequence(query, seeds, lambda i: reference[i], order_a, grown, settings)
    second = match_sequence(query, seeds, lambda i: reference[i], order_b, rebuilt, settings)
    assert [(m.reference, m.aligned, m.speed) for m in first] == [
        (m.reference, m.aligned, m.speed) for m in second
    ]
    np.testing.assert_allclose([m.score for m in first], [m.score for m in second], rtol=1e-9)
    assert first[0].reference == 200


def _match(reference: int, score: float) -> SequenceMatch:
    return SequenceMatch(reference, score, 5, 1.0, (reference,), 0.5, (1.0,))


def test_the_margin_is_over_the_best_rival_another_place() -> None:
    """Candidates within the window are the best place shifted by a frame or two: never its
    rival; the first one beyond it, or on another trajectory, is."""
    two_routes = Trajectories.single(40, np.arange(40) == 20)  # frames 0-19 and 20-39
    near = [_match(10, 9.0), _match(12, 8.5), _match(7, 8.0), _match(14, 6.0), _match(30, 5.0)]
    assert distinctiveness(near, two_routes, window=3) == Distinctiveness(3.0, 14)
    other_route = [_match(19, 9.0), _match(21, 8.0), _match(3, 2.0)]  # 21: the next route
    assert distinctiveness(other_route, two_routes, window=3) == Distinctiveness(1.0, 21)
    alone = [_match(10, 7.5), _match(11, 7.0)]  # no other place scored: the rival is chance (0)
    assert distinctiveness(alone, two_routes, window=3) == Distinctiveness(7.5, None)
    assert distinctiveness([], two_routes, window=3) is None


def test_a_look_alike_stretch_has_a_small_margin_and_the_true_place_a_large_one() -> None:
    """A route that repeats itself (a second lap of the same appearances) scores its two laps
    alike: the sequence score is high on both, only the margin says the answer is unsure."""
    rng = np.random.default_rng(3)
    appearance, label = _aliased_route(rng, places=120, looks=8)
    lap = _unit(appearance[label] + 0.1 * rng.normal(size=(120, 32)))
    unique = _unit(rng.normal(size=(120, 32)))
    reference = np.vstack([lap, lap + 0.0, unique])  # frames 0-119 and 120-239 look alike
    reference = _unit(reference + 0.05 * rng.normal(size=reference.shape))
    trajectories = Trajectories.single(360)
    moments = MapMoments.of(reference)
    settings = SequenceSettings(length=8, speeds=(1.0,), seeds=40)

    def margin(query: np.ndarray) -> tuple[float, float]:
        matches = match_sequence(
            query,
            _seeds(query, reference, 40),
            reference.__getitem__,
            trajectories,
            moments,
            settings,
            top=None,
        )
        distinct = distinctiveness(matches, trajectories, window=3)
        assert distinct is not None
        return matches[0].score, distinct.margin

    in_lap = _unit(lap[50:58] + 0.1 * rng.normal(size=(8, 32)))
    in_unique = _unit(unique[50:58] + 0.1 * rng.normal(size=(8, 32)))
    lap_score, lap_margin = margin(in_lap)
    unique_score, unique_margin = margin(in_unique)
    assert lap_score > 5.0 and unique_score > 5.0  # both look like confident sequences
    assert lap_margin < 1.0 < 5.0 < unique_margin


def test_a_place_continues_the_last_loop_only_just_ahead_on_its_trajectory() -> None:
    """Loop tracking: the next frame along the loop's own trajectory continues it; at the same
    frame (a lagging track), behind it, two or more ahead (a jumping track), or on another
    trajectory, the full margin applies again."""
    two_routes = Trajectories.single(40, np.arange(40) == 20)  # frames 0-19 and 20-39
    assert [continues_loop(two_routes, r, 10) for r in (9, 10, 11, 12, 13)] == [
        False,
        False,
        True,
        False,
        False,
    ]
    assert not continues_loop(two_routes, 20, 19)  # the next trajectory
    assert not continues_loop(two_routes, 11, None)  # no loop before
    margins = {"other_run": 4.0, "own_run": 6.0}
    assert margin_needed(two_routes, 11, None, previous_loop=10, tracking=2.5, **margins) == 2.5
    assert margin_needed(two_routes, 14, None, previous_loop=10, tracking=2.5, **margins) == 4.0
    assert margin_needed(two_routes, 11, None, previous_loop=10, tracking=None, **margins) == 4.0
    # a tracking margin above the one that applies changes nothing
    assert margin_needed(two_routes, 11, None, previous_loop=10, tracking=9.0, **margins) == 4.0


def test_a_place_may_not_run_ahead_of_a_recent_loop_faster_than_the_fastest_speed() -> None:
    """A robot at speed 1.25 passes at most 1.25 map frames a frame, and an alignment rounds by
    one: 2 frames ahead of the previous frame's loop is its pace, 3 is not; 3 in two frames is,
    4 is not. Lagging behind (a robot slowing or standing) is allowed; a place on another
    trajectory is not compared; reverse speeds count running ahead backwards too."""
    route = Trajectories.single(40)
    ahead = [runs_ahead(route, 10 + k, 10, 1, 1.25) for k in range(-2, 5)]
    assert ahead == [None, None, None, None, None, 3, 4]
    assert runs_ahead(route, 13, 10, 2, 1.25) is None and runs_ahead(route, 14, 10, 2, 1.25) == 4
    assert runs_ahead(route, 2, 10, 1, 1.25) is None  # far behind: not running ahead
    assert runs_ahead(route, 2, 10, 1, 1.25, both_ways=True) == 8
    two_routes = Trajectories.single(40, starts=np.arange(40) == 20)
    assert runs_ahead(two_routes, 25, 10, 1, 1.25) is None  # another trajectory


def test_a_track_lost_for_a_frame_or_two_is_picked_up_where_the_robot_has_driven_since() -> None:
    """Loop tracking across a dropout: a loop closed ``g`` frames ago is continued by the
    frame ``g`` along its trajectory only, and not once the robot has driven further than
    TRACKING_DROPOUT frames since it."""
    route = Trajectories.single(40)
    assert [continues_loop(route, r, 10, frames_since=2) for r in (11, 12, 13)] == [
        False,
        True,
        False,
    ]
    assert continues_loop(route, 10 + TRACKING_DROPOUT, 10, frames_since=TRACKING_DROPOUT)
    beyond = TRACKING_DROPOUT + 1
    assert not continues_loop(route, 10 + beyond, 10, frames_since=beyond)
    margins = {"other_run": 4.0, "own_run": 6.0, "tracking": 2.5}
    assert margin_needed(route, 12, None, previous_loop=10, frames_since=2, **margins) == 2.5
    assert margin_needed(route, 11, None, previous_loop=10, frames_since=2, **margins) == 4.0
