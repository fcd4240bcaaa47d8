"""How a served answer enters a PR sweep: the frame it names first and the number swept.

The service closes a loop when its decision is closable (verified, no less rare than the
impostors) and its ``loop_probability`` reaches the threshold, or when a robot's sequence
passes on its own evidence, whatever the threshold. The harness's served rows
(:mod:`service.evaluation.served_pass`) and ``eval-online``'s served replay
(:mod:`service.evaluation.online_served`) sweep the same way: closable answers from their
probability (or logit) up, sequence loops at every threshold, the others never. A sequence
loop left to a later frame (``awaits_next``) counts for its own frame once a later answer
confirms it (:func:`confirmed_rows`), as a back end closes it then.
"""

from __future__ import annotations

import numpy as np

from service.app.results import QueryResult
from service.ml.decision import Decision, logit, probability

# a loop on the robot's sequence's own evidence, in a logit sweep: above every decision's
# logit (at most about 70), so accepted at every threshold a sweep reports
SEQUENCE_LOOP_LOGIT = 1000.0


def answered_frames(answer: QueryResult) -> list[int]:
    """The frames an answer names, the one to act on first: the loop's frame (answered or
    pending); else the match when the decision could close it (the swept probability is the
    match's: a lower threshold makes it the loop); else the robot's sequence's aligned frame,
    else the match; then the other candidates."""
    ids = [c.frame_id for c in answer.candidates]
    first = answer.proposed_loop_frame_id
    decision = answer.decision
    if first is None and answer.match is not None and decision is not None and decision.closable:
        first = answer.match.frame_id
    if first is None and answer.sequence is not None:
        first = answer.sequence.frame_id
    if first is None:
        return ids
    return [first, *(f for f in ids if f != first)]


def loop_probability(answer: QueryResult) -> float:
    """The number the service thresholds (0 when the answer has no decision)."""
    decision = answer.decision
    if decision is None or decision.loop_probability is None:
        return 0.0
    return float(decision.loop_probability)


def swept_score(answer: QueryResult) -> tuple[float, bool]:
    """The served sweep's score of an answer and whether some threshold makes it a loop: a
    loop on the robot's sequence's own evidence is one at every threshold (1.0), a closable
    decision from its probability on (:func:`swept_probability`), the others never."""
    if closed_by_sequence(answer):
        return 1.0, True
    return swept_probability(answer), swept_decision(answer, closable_only=True) is not None


def closed_by_sequence(answer: QueryResult) -> bool:
    """A loop on the robot's sequence's own evidence, answered at once: the service closes it
    whatever ``LOOPNET_LOOP_PROBABILITY_MIN`` says. One that awaits a later frame is not (yet)."""
    sequence = answer.sequence
    return sequence is not None and sequence.passed and not sequence.awaits_next


def confirmed_rows(answer: QueryResult, row_of: dict[int, int]) -> list[int]:
    """The rows (``row_of``: a stored frame's row in the sweep) of the robot's earlier frames
    whose pending loops ``answer`` confirms: each then counts as a loop on the sequence's
    evidence."""
    return [row_of[c.frame_id] for c in answer.confirmed if c.frame_id in row_of]


def swept_logit(answer: QueryResult) -> float:
    """:func:`swept_score` on the logit scale (:func:`decision_logit`): -inf for an answer no
    threshold makes a loop, :data:`SEQUENCE_LOOP_LOGIT` for a loop by the sequence."""
    if closed_by_sequence(answer):
        return SEQUENCE_LOOP_LOGIT
    return decision_logit(answer, closable_only=True)


def swept_probability(answer: QueryResult, closable_only: bool = True) -> float:
    """``loop_probability`` as the decision computes it, before its rounding to 6 decimals
    (which ties most verified sequence answers at 1.0, so a sweep could not order them):
    the same order and threshold, in [0, 1]; 0 without a decision, and with ``closable_only``
    for an answer no threshold makes a loop (:func:`swept_decision`; the served row's sweep
    leaves those out)."""
    decision = swept_decision(answer, closable_only)
    return 0.0 if decision is None else probability(decision.parts)


def decision_logit(answer: QueryResult, closable_only: bool = False) -> float:
    """The decision model's logit of the answer's parts (-inf without a decision, and with
    ``closable_only`` for an answer that is not ``decision.closable``): ordered as
    ``loop_probability`` but neither rounded nor saturated at 1.0, so a sweep can still order
    the answers the rounded probability ties."""
    decision = swept_decision(answer, closable_only)
    return -np.inf if decision is None else logit(decision.parts)


def swept_decision(answer: QueryResult, closable_only: bool) -> Decision | None:
    """The answer's decision when a sweep may accept it: None without a probability, or with
    ``closable_only`` when the decision is not ``closable``."""
    decision = answer.decision
    if decision is None or decision.loop_probability is None:
        return None
    if closable_only and not decision.closable:
        return None
    return decision
