"""The loop decision's probability: what each part does, and what it refuses."""

from __future__ import annotations

import pytest

from service.app.decision import SMALL_ATLAS_FRAMES, verified_count
from service.ml.decision import DEFAULT_LOOP_PROBABILITY, Evidence, decide_loop


def test_a_well_verified_distinct_calibrated_match_is_a_loop() -> None:
    evidence = Evidence(
        inliers=180, inlier_ratio=0.8, rival_inliers=20, score_excess=4.0, frames=500
    )
    decision = decide_loop(evidence, min_inliers=44)
    assert decision.passed and decision.loop_probability is not None
    assert decision.loop_probability >= DEFAULT_LOOP_PROBABILITY
    assert decision.failed is None and decision.reason is None
    assert set(decision.contributions) == {"inliers", "inlier_ratio", "rival", "score"}


def test_look_alike_with_a_high_score_but_no_geometry_is_refused() -> None:
    """Two places whose embeddings agree (score far above every impostor) but whose views do
    not: the geometry fails, and the answer says it was the inliers."""
    evidence = Evidence(inliers=6, inlier_ratio=0.1, score_excess=8.0, frames=500)
    decision = decide_loop(evidence, min_inliers=44)
    assert not decision.passed
    assert decision.failed == "inliers"
    assert decision.reason is not None and "6 inliers, below 44" in decision.reason


def test_closable_says_whether_any_threshold_could_make_the_answer_a_loop() -> None:
    """A threshold on the probability moves only closable answers: a verified match no less
    rare than the impostors; an unverified match or a common one stays out at any threshold,
    whatever its probability."""
    verified = Evidence(inliers=60, inlier_ratio=0.5, score_excess=0.5, frames=500)
    low = decide_loop(verified, min_inliers=44)
    assert low.closable and not low.passed  # below the default threshold, closable at a lower
    assert decide_loop(verified, min_inliers=44, threshold=0.5).passed
    unverified = Evidence(inliers=40, inlier_ratio=1.0, score_excess=8.0, frames=500)
    refused = decide_loop(unverified, min_inliers=44, threshold=0.5)
    assert refused.loop_probability is not None and refused.loop_probability > 0.5
    assert not refused.closable and not refused.passed
    common = Evidence(inliers=300, inlier_ratio=0.9, score_excess=-0.1, frames=500)
    assert not decide_loop(common, min_inliers=44, threshold=0.5).closable
    assert not decide_loop(verified, verify=False, min_inliers=44, threshold=0.0).closable
    assert not decide_loop(None).closable


def test_a_rival_place_that_verifies_as_well_holds_the_loop_back() -> None:
    alone = Evidence(inliers=90, inlier_ratio=0.7, rival_inliers=5, score_excess=3.0, frames=500)
    rivalled = Evidence(
        inliers=90, inlier_ratio=0.7, rival_inliers=85, score_excess=3.0, frames=500
    )
    p_alone = decide_loop(alone, min_inliers=44).loop_probability
    decision = decide_loop(rivalled, min_inliers=44)
    assert p_alone is not None and decision.loop_probability is not None
    assert decision.loop_probability < p_alone
    assert not decision.passed and decision.failed == "rival"


def test_probability_grows_with_inliers() -> None:
    values = [
        decide_loop(Evidence(inliers=n, inlier_ratio=0.6, frames=10)).loop_probability
        for n in (0, 10, 40, 100, 300)
    ]
    assert all(v is not None for v in values)
    assert values == sorted(values)  # type: ignore[type-var]


def test_small_uncalibrated_atlas_answers_with_a_reason() -> None:
    decision = decide_loop(Evidence(inliers=30, inlier_ratio=0.9, frames=10), min_inliers=44)
    assert decision.loop_probability is not None
    assert decision.reason is not None and "not calibrated yet" in decision.reason
    assert "score" not in decision.contributions


def test_no_candidate_and_no_verification_say_why() -> None:
    empty = decide_loop(None)
    assert empty.loop_probability is None and empty.reason is not None
    off = decide_loop(Evidence(score_excess=5.0, frames=100), verify=False)
    assert not off.passed and off.reason is not None and "verification is off" in off.reason


def test_small_atlases_verify_every_candidate() -> None:
    assert verified_count(5, 10) == 10
    assert verified_count(5, SMALL_ATLAS_FRAMES + 1) == 5
    assert verified_count(0, 10) == 0


def test_rivals_are_frames_of_another_place() -> None:
    """Same robot: more than the gap (2 frames) away along its route; another robot: another
    submap. The best verified rival's inliers enter the evidence."""
    from service.app.decision import answer_evidence
    from service.app.results import Candidate

    def candidate(frame_id: int, inliers: int, robot: str = "r", submap: str = "s") -> Candidate:
        return Candidate(frame_id, submap, robot, 0.9, inliers, None, 0.8, inliers >= 44)

    best = candidate(10, 80)
    near, far = candidate(12, 70), candidate(20, 30)
    other_robot_same_submap = candidate(40, 75, robot="q")
    evidence = answer_evidence([best, near, far, other_robot_same_submap], 100, None)
    assert evidence is not None and evidence.rival_inliers == 30
    evidence = answer_evidence([best, candidate(41, 60, robot="q", submap="t")], 100, None)
    assert evidence is not None and evidence.rival_inliers == 60


def test_a_match_no_rarer_than_the_best_impostor_is_never_a_loop() -> None:
    """Geometry alone cannot close a loop on a calibrated atlas: 71 clean inliers between
    two look-alike frames, but a score below log10(frames)."""
    evidence = Evidence(
        inliers=71, inlier_ratio=1.0, rival_inliers=20, score_excess=-0.9, frames=400
    )
    decision = decide_loop(evidence, min_inliers=44)
    assert not decision.passed and decision.failed == "score"
    assert decision.reason is not None and "log10(400)" in decision.reason


def test_the_rival_counts_in_the_best_candidates_terms_when_zoom_weighs() -> None:
    """With the re-rank weighing zoom, a rival further back (zoom 0.7) with more inliers than
    the best (zoom 1.0) counts as what it weighs: 50 * exp(-|ln 0.7| / 0.5) = 24.5."""
    from service.app.decision import answer_evidence
    from service.app.results import Candidate

    best = Candidate(13, "s", "r", 0.9, 40, None, 0.9, False, scale=1.0)
    rival = Candidate(30, "s", "r", 0.9, 50, None, 0.9, True, scale=0.7)
    plain = answer_evidence([best, rival], 10, None, scale_tolerance=0.0)
    assert plain is not None and plain.rival_inliers == 50
    weighed = answer_evidence([best, rival], 10, None, scale_tolerance=0.5)
    assert weighed is not None
    assert weighed.rival_inliers == pytest.approx(50 * 0.7**2)


def test_the_rival_reserve_is_another_place_than_every_checked_candidate() -> None:
    """The frame verified besides the top ones when they all show one place: the first after
    them that is a rival of each (so of whichever the re-rank puts first)."""
    from service.app.decision import has_verified_rival, rival_reserve
    from service.app.results import Candidate

    def candidate(frame_id: int, robot: str = "r", submap: str = "s") -> Candidate:
        return Candidate(frame_id, submap, robot, 0.9)

    checked = [candidate(10), candidate(11), candidate(12)]
    pool = [*checked, candidate(13), candidate(40, robot="q"), candidate(41, "q", "t")]
    # 13 is within the gap of 10-12; robot q's frame 40 shares the submap: only 41 is elsewhere
    assert rival_reserve(pool, 3) is pool[5]
    assert rival_reserve(checked, 3) is None
    assert not has_verified_rival(checked)  # none verified
    checked[0].inliers, checked[2].inliers = 60, 20
    assert not has_verified_rival(checked)  # 12 is the same place as 10
    far = candidate(30)
    far.inliers = 0
    assert has_verified_rival([*checked, far])
    assert not has_verified_rival([])


def test_a_sequence_lends_its_margin_only_to_a_match_at_its_own_place() -> None:
    """The replay's false loop (eval-online, adapted version): the robot's own frame 27 back
    verified with 44 inliers beside a rival with 40, while its sequence placed it, by a margin
    of 5.2, at the right frame of the first traversal. The margin backed the wrong frame into
    a loop; for a match elsewhere it counts against."""
    from service.app.decision import answer_evidence
    from service.app.results import Candidate, SequenceAnswer

    best = Candidate(6677, "s", "r", 0.63, 44, 6.08, 0.98, True, scale=0.96)
    rival = Candidate(6666, "s", "r", 0.65, 40, 6.31, 1.0, True, scale=0.99)
    sequence = SequenceAnswer(14.6, 10, [], 1.0, 3161, 5.23, 5769, False)

    def decided(agrees: bool | None) -> tuple[float | None, bool]:
        evidence = answer_evidence([best, rival], 6700, sequence, 0.0, 2, agrees)
        assert evidence is not None
        decision = decide_loop(evidence, min_inliers=23)
        return evidence.sequence_margin, decision.passed

    assert decided(True) == (5.23, True)  # at the sequence's place: its margin backs it
    assert decided(False) == (-5.23, False)  # elsewhere: the sequence argues against it
    assert decided(None)[0] is None  # cannot be compared: the part is absent


def test_one_place_for_the_sequence_is_the_consistencys_step() -> None:
    """Two map frames are one place on one trajectory within ``max_step`` frames."""
    from service.app.robot_evidence import RobotEvidence
    from service.ml.sequences import ConsistencySettings, Trajectories

    trajectories = Trajectories.build(["r"] * 20 + ["q"] * 5)
    position = {100 + i: i for i in range(25)}
    evidence = RobotEvidence(None, [], position, trajectories, ConsistencySettings(max_step=3))
    assert evidence.same_place(104, 107) is True
    assert evidence.same_place(104, 113) is False
    assert evidence.same_place(119, 120) is False  # another robot's trajectory
    assert evidence.same_place(104, 999) is None  # not held by the map


def test_a_weak_newest_frame_leaves_its_sequences_loop_to_a_strong_later_frame() -> None:
    """A passed sequence that awaits a later frame is a candidate with its loop pending, not a
    loop; a consistent single-frame loop is not deferred. A loop answered at once confirms the
    run of pending loops just before it, walking back while each names the same place as the
    loop after it (the consistency's step); a pending loop confirms nothing (two weak frames off
    the map must not confirm each other), and a run broken by another place stops there."""
    from service.app.results import DeferredLoop, SequenceAnswer
    from service.app.robot_evidence import RobotEvidence
    from service.ml.sequences import ConsistencySettings, Hypothesis, PlaceStatus, Trajectories

    trajectories = Trajectories.build(["r"] * 20)
    position = {100 + i: i for i in range(20)}
    settings = ConsistencySettings(required=2, max_step=3)

    def evidence(
        place: int | None, awaits: bool, run: tuple[DeferredLoop, ...] = (), previous=None
    ) -> RobotEvidence:  # type: ignore[no-untyped-def]
        sequence = None
        if place is not None:
            sequence = SequenceAnswer(9.0, 5, [], 1.0, place, 5.0, None, True, awaits_next=awaits)
        return RobotEvidence(
            sequence, previous or [None], position, trajectories, settings, pending_run=run
        )

    waiting = evidence(105, awaits=True).verdict(None, False)
    assert (waiting.status, waiting.loop_frame_id, waiting.pending_loop_frame_id) == (
        PlaceStatus.CANDIDATE,
        None,
        105,
    )
    assert evidence(105, awaits=False).verdict(None, False).loop_frame_id == 105
    consistent = evidence(105, awaits=True, previous=[Hypothesis(4, True)]).verdict(104, True)
    assert (consistent.status, consistent.loop_frame_id) == (PlaceStatus.LOOP, 104)

    first, second = DeferredLoop(7, loop_frame_id=104), DeferredLoop(8, loop_frame_id=105)
    assert evidence(106, awaits=False, run=(second,)).verdict(None, False).confirmed == (second,)
    assert evidence(106, awaits=True, run=(second,)).verdict(None, False).confirmed == ()
    assert evidence(112, awaits=False, run=(second,)).verdict(None, False).confirmed == ()
    assert evidence(None, awaits=False, run=(second,)).verdict(None, False).confirmed == ()
    both = evidence(107, awaits=False, run=(first, second)).verdict(None, False)
    assert both.confirmed == (first, second)
    elsewhere = DeferredLoop(6, loop_frame_id=115)  # a run broken by another place
    assert evidence(107, awaits=False, run=(elsewhere, second)).verdict(None, False).confirmed == (
        second,
    )
    by_consistency = evidence(None, awaits=False, run=(second,), previous=[Hypothesis(6, True)])
    assert by_consistency.verdict(107, True).confirmed == (second,)


def test_a_sequence_names_a_place_from_the_decisions_neutral_margin() -> None:
    """Below the sequence part's centre a sequence argues for no place, so the answer stays
    with the best single frame; an uninformative sequence (no rival place) names none."""
    from service.app.results import Candidate, SequenceAnswer
    from service.app.sequence_place import names_the_place, place_first
    from service.ml.decision import CENTRES

    def sequence(margin: float, rival: int | None = 9) -> SequenceAnswer:
        return SequenceAnswer(10.0, 5, [], 1.0, 3, margin, rival, False)

    assert names_the_place(sequence(CENTRES["sequence"]))
    assert not names_the_place(sequence(CENTRES["sequence"] - 0.1))
    assert not names_the_place(sequence(9.0, rival=None))
    a, b, c = (Candidate(i, "s", "r", 0.5) for i in (1, 2, 3))
    assert [x.frame_id for x in place_first([a, b, c], c)] == [3, 1, 2]


def test_between_two_unverified_frames_the_rival_part_says_nothing() -> None:
    """On a calibrated version, a match and a rival both below the atlas's minimum inliers
    (cohog200's first wrong answer: 21 inliers four places off, beside a rival with 3) carry
    no rival part; one verified frame on either side keeps it, and before calibration (the
    matcher's default minimum, not the atlas's noise level) it is kept as well."""
    noise = Evidence(inliers=21, inlier_ratio=1.0, rival_inliers=3, score_excess=0.5, frames=200)
    assert "rival" not in decide_loop(noise, min_inliers=44).parts
    verified = Evidence(inliers=60, inlier_ratio=1.0, rival_inliers=3, score_excess=0.5, frames=200)
    assert "rival" in decide_loop(verified, min_inliers=44).parts
    outverified = Evidence(
        inliers=5, inlier_ratio=1.0, rival_inliers=50, score_excess=0.5, frames=200
    )
    assert decide_loop(outverified, min_inliers=44).parts["rival"] < 0
    uncalibrated = Evidence(inliers=21, inlier_ratio=1.0, rival_inliers=3, frames=10)
    assert "rival" in decide_loop(uncalibrated, min_inliers=44).parts
