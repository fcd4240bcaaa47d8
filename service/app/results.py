"""What a query answers: candidates, the verification summary, the submap guess."""

from __future__ import annotations

from dataclasses import dataclass, field

from service.ml.decision import Decision
from service.ml.verification import RelativePose


@dataclass
class SequenceAnswer:
    """The best reference place for the robot's sequence.

    ``frame_id`` is aligned with the newest frame; ``aligned`` gives the frame aligned with each
    query frame, oldest first (None where the reference trajectory had none). ``margin`` is the
    score minus that of the best rival place (``rival_frame_id``, None when no other place was
    scored: the rival counts as 0); ``margin_min``: the margin it needed (its place on the
    robot's own current sequence or another, or continuing the robot's last loop,
    :func:`~service.ml.sequences.margin_needed`);
    ``passed``: a loop on the sequence's own evidence.
    ``contrast_frames``: the robot's earlier frames the newest was contrasted with (0: scored on
    plain vectors, :mod:`service.ml.sequences.contrast`). ``aligned_z``: each frame's own
    evidence for its aligned frame (standardised similarity, oldest first; the newest one's
    must reach :data:`~service.ml.sequences.distinctiveness.NEWEST_Z_MIN`, and the newest few
    may not together look off the map, :mod:`service.ml.sequences.off_map`). ``awaits_next``: it
    passed, but its newest frame's own evidence is below
    :data:`~service.ml.sequences.distinctiveness.CONFIRM_Z`, so its loop waits for a later
    frame answered at once. ``reason``: why it is not a loop now (None when it passed and does
    not wait)."""

    score: float
    length: int
    aligned: list[int | None]
    speed: float
    frame_id: int
    margin: float
    rival_frame_id: int | None
    passed: bool
    contrast_frames: int = 0
    margin_min: float = 0.0
    aligned_z: list[float] = field(default_factory=list)
    reason: str | None = None
    awaits_next: bool = False


@dataclass(frozen=True)
class DeferredLoop:
    """A loop a robot's frame ``frame_id`` proposed with map frame ``loop_frame_id`` and left
    to a later frame to confirm (the setting ``sequence_confirm_z``)."""

    frame_id: int
    loop_frame_id: int


@dataclass
class Candidate:
    frame_id: int
    submap: str
    robot_id: str
    similarity: float
    inliers: int | None = None
    score: float | None = None  # calibrated: -log10 P(an impostor pair is this similar)
    inlier_ratio: float | None = None
    verified: bool = False
    relative_pose: RelativePose | None = None
    scale: float | None = None  # the inliers' zoom from the query to this frame


@dataclass
class VerificationSummary:
    """How the candidates of an answer were verified."""

    enabled: bool
    matcher: str | None = None
    verified_candidates: int = 0
    min_inliers: int | None = None


@dataclass
class SubmapGuess:
    available: bool
    submap: str | None = None
    probability: float | None = None
    reason: str | None = None


@dataclass
class QueryResult:
    atlas: str
    model_version: int
    match: Candidate | None
    candidates: list[Candidate]
    loop_closure: bool
    threshold: float
    predicted_submap: SubmapGuess
    keypoints: int
    timings_ms: dict[str, float] = field(default_factory=dict)
    margin: float | None = None
    verification: VerificationSummary = field(
        default_factory=lambda: VerificationSummary(enabled=False)
    )
    score_threshold: float | None = None  # set when the decision used the calibrated score
    # "loop" (accepted: consistent over the robot's last observations), "candidate" (passes,
    # not yet consistent) or "new_place" (nothing passes)
    status: str = "new_place"
    new_place: bool = True  # status == "new_place", a field of its own
    consistent: int = 0  # consecutive agreeing observations, this one included
    loop_frame_id: int | None = None  # the frame to close the loop with, when status is "loop"
    # a loop the sequence passed with but left to a later frame (status "candidate")
    pending_loop_frame_id: int | None = None
    # the pending loops of the robot's frames just before, oldest first, that this answer's loop
    # confirms (close them now)
    confirmed: tuple[DeferredLoop, ...] = ()
    sequence: SequenceAnswer | None = None
    query_thumbnail: bytes | None = field(default=None, repr=False)  # kept if a loop closes
    # the search's frames, best first, filter applied: what an observation keeps as the places
    # its frame proposes to later sequences (not part of the answer)
    proposals: list[int] = field(default_factory=list, repr=False)
    decision: Decision | None = None  # the loop probability, its parts and why it failed
    # the asking robot's newest frames taken as its current stay and left out (service.app.stay)
    stay_frames: int = 0

    @property
    def proposed_loop_frame_id(self) -> int | None:
        """The frame of this answer's loop, answered or pending (None: no loop): what an
        observation stores for tracking, and the frame the harness names first."""
        return self.loop_frame_id if self.loop_frame_id is not None else self.pending_loop_frame_id


def place_margin(candidates: list[Candidate]) -> float | None:
    """Similarity of the match minus that of the best candidate from another place, a place
    being a submap: small or negative means a look-alike elsewhere competes with the match.
    None when every searched frame lies in the match's submap."""
    if not candidates:
        return None
    best = candidates[0]
    others = [c.similarity for c in candidates[1:] if c.submap != best.submap]
    return round(best.similarity - max(others), 6) if others else None
