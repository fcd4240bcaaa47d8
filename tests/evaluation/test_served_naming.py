"""Which frame a served answer names first: the one its swept probability is about."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from service.app.results import Candidate, DeferredLoop, QueryResult, SequenceAnswer, SubmapGuess
from service.evaluation.dataset_model import Dataset, QueryFrame, ReferenceFrame
from service.evaluation.metrics import Ranking
from service.evaluation.protocol import evaluate_ranking
from service.evaluation.served_sweep import (
    SEQUENCE_LOOP_LOGIT,
    answered_frames,
    confirmed_rows,
    swept_logit,
    swept_score,
)
from service.ml.decision import Decision


def answer(
    *, closable: bool, loop_frame: int | None = None, sequence_passed: bool = False
) -> QueryResult:
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
        sequence=SequenceAnswer(0.5, 10, [30], 1.0, 30, 0.1, None, passed=sequence_passed),
        decision=Decision(0.3, 0.98, passed=False, closable=closable),
    )


def test_a_closable_answer_names_its_match_whose_probability_is_swept() -> None:
    assert answered_frames(answer(closable=True))[:2] == [7, 31]


def test_an_answer_no_threshold_closes_names_the_sequences_place() -> None:
    assert answered_frames(answer(closable=False)) == [30, 7, 31]


def test_a_loop_names_its_frame() -> None:
    assert answered_frames(answer(closable=False, loop_frame=31))[0] == 31


def test_a_served_sweep_never_accepts_an_answer_that_is_not_closable() -> None:
    """Every answer names the right frame, but only two could be loops: R@100%P is 2 of 4."""
    references = [ReferenceFrame(Path(f"r{i}.png"), str(i), i) for i in range(4)]
    queries = [QueryFrame(Path(f"q{i}.png"), frozenset({i})) for i in range(4)]
    dataset = Dataset("toy", "folders", Path("."), references, queries, "same frame")
    ranking = Ranking(np.arange(4).reshape(4, 1), np.array([[0.99], [0.0], [0.7], [0.0]]))
    closable = np.array([True, False, True, False])
    swept = evaluate_ranking("m", "m", "served", ranking, dataset, [0] * 4, eligible=closable)
    every = evaluate_ranking("m", "m", "served", ranking, dataset, [0] * 4)
    assert swept.recall_at_full_precision == 0.5 and every.recall_at_full_precision == 1.0


def test_a_loop_on_the_sequences_evidence_is_swept_as_one_at_every_threshold() -> None:
    assert swept_score(answer(closable=False, loop_frame=30, sequence_passed=True)) == (1.0, True)
    assert swept_score(answer(closable=False))[1] is False
    assert swept_score(answer(closable=True))[1] is True
    passed = answer(closable=False, loop_frame=30, sequence_passed=True)
    assert swept_logit(passed) == SEQUENCE_LOOP_LOGIT
    assert swept_logit(answer(closable=False)) == float("-inf")


def test_a_pending_loop_is_swept_only_once_a_later_answer_confirms_it() -> None:
    """A sequence loop left to a later frame is not a loop at every threshold on its own answer
    (which names the pending frame first); a later answer's confirmation of that frame is what
    the served rows count, late, in that frame's row."""
    pending = answer(closable=False, sequence_passed=True)
    assert pending.sequence is not None
    pending.sequence.awaits_next = True
    pending.pending_loop_frame_id = 30
    assert swept_score(pending) == (0.0, False)
    assert swept_logit(pending) == float("-inf")
    assert answered_frames(pending)[0] == 30
    later = answer(closable=False, loop_frame=31, sequence_passed=True)
    later.confirmed = (DeferredLoop(frame_id=54, loop_frame_id=29), DeferredLoop(55, 30))
    assert confirmed_rows(later, {54: 3, 55: 4, 56: 5}) == [3, 4]
    assert confirmed_rows(later, {55: 4}) == [4]  # a frame the sweep has no row of
    assert confirmed_rows(pending, {55: 4}) == []
