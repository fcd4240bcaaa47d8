"""The service's side of the loop decision: which candidates are verified, the evidence an
answer hands to :func:`service.ml.decision.decide_loop`, and the status it leads to."""

from __future__ import annotations

import math
from dataclasses import replace

from service.app.results import Candidate, SequenceAnswer
from service.app.robot_evidence import Verdict
from service.ml.decision import CANDIDATE_PROBABILITY, DEFAULT_RIVAL_GAP, Decision, Evidence
from service.ml.sequences import PlaceStatus
from service.ml.viewpoint import DEFAULT_SCALE_TOLERANCE, support

# Up to this many frames an atlas is small: every frame the search returns is verified, since
# its global ranking is the least reliable (no calibration yet) and verifying all costs little.
SMALL_ATLAS_FRAMES = 32


def verified_count(top: int, frames: int) -> int:
    """Candidates to verify: the setting's ``top``, or all of a small atlas's (0: off)."""
    if top <= 0:
        return 0
    return max(top, frames) if frames <= SMALL_ATLAS_FRAMES else top


def is_rival(best: Candidate, other: Candidate, gap: int = DEFAULT_RIVAL_GAP) -> bool:
    """Whether ``other`` is another place than ``best``: a frame of the same robot more than
    ``gap`` frames away along its trajectory (ids grow with insertion), or a frame of
    another robot in another submap. Another robot's frame in the same submap may well show
    the same place, so it never counts against the match."""
    if other.robot_id == best.robot_id:
        return abs(other.frame_id - best.frame_id) > gap
    return other.submap != best.submap


def rival_reserve(
    candidates: list[Candidate], checked: int, gap: int = DEFAULT_RIVAL_GAP
) -> Candidate | None:
    """The candidate to verify when none of the first ``checked`` turns out to be another
    place than the best: the most similar one after them that is a rival of every one of
    them (so of whichever the re-rank puts first). None when the search found no such frame."""
    head = candidates[:checked]
    for candidate in candidates[checked:]:
        if all(is_rival(c, candidate, gap) for c in head):
            return candidate
    return None


def verified_rivals(candidates: list[Candidate], gap: int = DEFAULT_RIVAL_GAP) -> list[Candidate]:
    """The verified candidates of another place than the best (``candidates`` in their final
    order): what the decision's rival part weighs."""
    if not candidates:
        return []
    best = candidates[0]
    return [c for c in candidates[1:] if c.inliers is not None and is_rival(best, c, gap)]


def has_verified_rival(candidates: list[Candidate], gap: int = DEFAULT_RIVAL_GAP) -> bool:
    """Whether a verified rival stands beside the best: without one the decision has no rival
    to weigh."""
    return bool(verified_rivals(candidates, gap))


def answer_evidence(
    candidates: list[Candidate],
    frames: int,
    sequence: SequenceAnswer | None,
    scale_tolerance: float = DEFAULT_SCALE_TOLERANCE,
    rival_gap: int = DEFAULT_RIVAL_GAP,
    sequence_agrees: bool | None = True,
) -> Evidence | None:
    """The decision's evidence for the best candidate (``candidates`` in their final order);
    None without candidates. The rival's inliers are counted in the best's terms: both
    discounted by their zoom as the re-rank discounts them (``scale_tolerance``).
    ``sequence_agrees``: whether the robot's sequence places it where the best candidate is
    (:func:`sequence_part`)."""
    if not candidates:
        return None
    best = candidates[0]
    per_inlier = support(1, best.scale, scale_tolerance)
    rivals = [
        support(c.inliers or 0, c.scale, scale_tolerance) / per_inlier
        for c in verified_rivals(candidates, rival_gap)
    ]
    score_excess = best.score - math.log10(max(frames, 1)) if best.score is not None else None
    return Evidence(
        inliers=best.inliers,
        inlier_ratio=best.inlier_ratio,
        rival_inliers=max(rivals) if rivals else None,
        score_excess=score_excess,
        sequence_margin=sequence_part(sequence, sequence_agrees),
        frames=frames,
    )


def sequence_part(sequence: SequenceAnswer | None, agrees: bool | None) -> float | None:
    """The sequence's evidence for the best candidate: its margin when the sequence places the
    robot where that candidate is; the margin's negative when it places it elsewhere (the
    candidate's place then scores at least the margin below the sequence's own, since the
    margin is over the best rival place); None when the sequence is not informative or
    where it points cannot be compared (``agrees`` None).

    A sequence's margin is about its own place: lent to a single-frame match of another place
    (a frame nine places off, or the robot's own frames of half a minute ago that verify as
    well), it closed loops the sequence itself contradicted."""
    if sequence is None or not informative(sequence) or agrees is None:
        return None
    return sequence.margin if agrees else -sequence.margin


def informative(sequence: SequenceAnswer | None) -> bool:
    """A sequence's margin means something only against a rival place and over more than one
    frame: a robot's first frames, or a map with one place, have none to stand out from."""
    return sequence is not None and sequence.rival_frame_id is not None and sequence.length > 1


def probable_candidate(verdict: Verdict, decision: Decision) -> Verdict:
    """A new-place verdict whose match is still more likely the same place than not is a
    ``candidate``: not certain enough to close a loop, not evidence of a new place either."""
    p = decision.loop_probability
    if verdict.status == PlaceStatus.NEW_PLACE and p is not None and p >= CANDIDATE_PROBABILITY:
        return replace(verdict, status=PlaceStatus.CANDIDATE)
    return verdict
