"""The place a robot's sequence names, and the answer that is about it.

A robot that streams has two guesses of where it is: the single frame that verifies best, and
the place its sequence of frames aligns with (:mod:`service.app.sequences`). When the sequence
stands out from its rivals by at least the decision's neutral margin and the best verified
frame is another place, the answer is about the sequence's place: the candidate there goes
first (the sequence's aligned frame is verified when no checked candidate shows it) and the
single frame becomes its rival, so the decision weighs both. Its margin then backs the place
it was measured for (:func:`service.app.decision.sequence_part`); lent to the single frame, it
closed loops the sequence contradicted (benchmarks/RESULTS.md, issue 25, stop 37).
"""

from __future__ import annotations

from sqlalchemy.orm import Session

from service.app.decision import informative
from service.app.results import Candidate, SequenceAnswer
from service.app.robot_evidence import RobotEvidence
from service.ml.decision import CENTRES
from service.storage import repository as repo
from service.storage.models import Frame


def names_the_place(sequence: SequenceAnswer | None) -> bool:
    """Whether the robot's sequence says where it is firmly enough for the answer to be about
    its place: informative, with a margin from the decision's neutral point on (below it, the
    sequence part argues for no place at all)."""
    return sequence is not None and informative(sequence) and sequence.margin >= CENTRES["sequence"]


def place_first(candidates: list[Candidate], place: Candidate) -> list[Candidate]:
    """``candidates`` with ``place`` (the candidate at the sequence's place) first, the others
    in their order: the single frame that verified best becomes a rival of the sequence's place
    when it is another, and the decision weighs both."""
    return [place, *(c for c in candidates if c.frame_id != place.frame_id)]


def naming_sequence(evidence: RobotEvidence | None) -> SequenceAnswer | None:
    """The robot's sequence when it names a place (:func:`names_the_place`), else None."""
    sequence = evidence.sequence if evidence is not None else None
    return sequence if names_the_place(sequence) else None


def at_sequence_place(
    candidates: list[Candidate], evidence: RobotEvidence | None
) -> Candidate | None:
    """The first verified candidate at the place the robot's sequence names
    (:func:`names_the_place`); None when it names none or no verified
    candidate shows it."""
    sequence = naming_sequence(evidence)
    if evidence is None or sequence is None:
        return None
    for candidate in candidates:
        if candidate.inliers is not None and evidence.same_place(
            candidate.frame_id, sequence.frame_id
        ):
            return candidate
    return None


def sequence_place(
    session: Session,
    evidence: RobotEvidence | None,
    checked: list[Candidate],
    candidates: list[Candidate],
    frames: dict[int, Frame],
    names: dict[int, str],
) -> Candidate | None:
    """The candidate at the place the robot's sequence names (:func:`names_the_place`) when
    none of the ``checked`` ones shows it: the first of the other hits that does, else the
    sequence's aligned frame itself (its frame row added to ``frames``). None when the
    sequence names no place or a checked candidate shows it."""
    sequence = naming_sequence(evidence)
    if evidence is None or sequence is None:
        return None
    for i, candidate in enumerate(candidates):
        if evidence.same_place(candidate.frame_id, sequence.frame_id):
            return None if i < len(checked) else candidate
    frame = repo.frames_by_id(session, frame_ids=[sequence.frame_id]).get(sequence.frame_id)
    if frame is None or evidence.sequence_similarity is None:
        return None
    frames[frame.id] = frame
    return Candidate(frame.id, names[frame.submap_id], frame.robot_id, evidence.sequence_similarity)
