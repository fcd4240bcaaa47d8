"""Which frame a served answer names first: the one its swept probability is about."""

from __future__ import annotations

from service.app.results import Candidate, QueryResult, SequenceAnswer, SubmapGuess
from service.evaluation.served_pass import answered_frames
from service.ml.decision import Decision


def answer(*, closable: bool, loop_frame: int | None = None) -> QueryResult:
    """A robot's observation whose match (frame 7) is not the sequence's place (frame 30)."""
    match = Candidate(7, "a", "r1", 0.9, inliers=60, verified=True)
    return QueryResult(
        atlas="campus",
        model_version=1,
        match=match,
        candidates=[match, Candidate(31, "b", "r1", 0.8, inliers=5, verified=True)],
        loop_closure=loop_frame is not None,
        threshold=0.5,
        predicted_submap=SubmapGuess(available=False),
        keypoints=100,
        loop_frame_id=loop_frame,
        sequence=SequenceAnswer(0.5, 10, [30], 1.0, 30, 0.1, None, passed=False),
        decision=Decision(0.3, 0.98, passed=False, closable=closable),
    )


def test_a_closable_answer_names_its_match_whose_probability_is_swept() -> None:
    assert answered_frames(answer(closable=True))[:2] == [7, 31]


def test_an_answer_no_threshold_closes_names_the_sequences_place() -> None:
    assert answered_frames(answer(closable=False)) == [30, 7, 31]


def test_a_loop_names_its_frame() -> None:
    assert answered_frames(answer(closable=False, loop_frame=31))[0] == 31
