"""Loop closure over sequences: ordering frames into trajectories, scoring a place by the robot's
last few frames (SeqSLAM-like), and accepting loops only when consecutive observations agree
(DBoW2-like), with an explicit "new place". Pure library code: callers bring the vectors."""

from service.ml.sequences.consistency import (
    ConsistencySettings,
    Hypothesis,
    PlaceDecision,
    PlaceStatus,
    agree,
    consistent_scores,
    decide,
)
from service.ml.sequences.distinctiveness import (
    TRACKING_DROPOUT,
    Distinctiveness,
    continues_loop,
    distinctiveness,
    margin_needed,
    runs_ahead,
)
from service.ml.sequences.scoring import (
    MapMoments,
    SequenceMatch,
    SequenceSettings,
    match_sequence,
    propose_candidates,
    score_candidates,
)
from service.ml.sequences.trajectories import Trajectories, carried_timestamps, sequence_starts

__all__ = [
    "TRACKING_DROPOUT",
    "ConsistencySettings",
    "Distinctiveness",
    "Hypothesis",
    "MapMoments",
    "PlaceDecision",
    "PlaceStatus",
    "SequenceMatch",
    "SequenceSettings",
    "Trajectories",
    "agree",
    "carried_timestamps",
    "consistent_scores",
    "continues_loop",
    "decide",
    "distinctiveness",
    "margin_needed",
    "match_sequence",
    "propose_candidates",
    "runs_ahead",
    "score_candidates",
    "sequence_starts",
]
