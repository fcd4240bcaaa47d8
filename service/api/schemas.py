"""Request and response bodies of the HTTP API (pydantic), documented in the OpenAPI spec."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from pydantic import BaseModel, Field

from service.api.closed_sets import (
    CalibrationStateValue,
    PlaceStatusValue,
)
from service.app.names import NAME_PATTERN
from service.ml.sequences.distinctiveness import CONFIRM_Z, NEWEST_Z_MIN, TRACKING_DROPOUT
from service.ml.sequences.off_map import OFF_MAP_FRAMES, OFF_MAP_SLACK, OFF_MAP_Z


class ErrorOut(BaseModel):
    detail: str = Field(description="What is wrong, in words.")
    error: str = Field(description="The error's type, e.g. NotFound, InvalidImage.")


class AtlasIn(BaseModel):
    name: str = Field(pattern=NAME_PATTERN.pattern, examples=["campus"])
    description: str = Field("", max_length=1000)


class AtlasOut(BaseModel):
    name: str
    description: str
    created_at: datetime
    submaps: int
    frames: int
    active_model_version: int
    classifier_trained: bool = Field(
        description="Whether the active model version has a trained classification head."
    )
    feature_signature: dict[str, Any] = Field(
        description="Extractor and backbone settings every frame of this atlas was described with."
    )
    calibration: CalibrationStateOut


class CalibrationStateOut(BaseModel):
    state: CalibrationStateValue = Field(
        description="'uncalibrated': the active version embeds with the uncalibrated blend."
    )
    version: int | None = Field(
        None, description="The model version whose calibration job fitted the active one's."
    )
    frames_at_fit: int | None = Field(None, description="Frames the calibration was fitted on.")


class SubmapIn(BaseModel):
    name: str = Field(pattern=NAME_PATTERN.pattern, examples=["corridor-3"])


class SubmapOut(BaseModel):
    name: str
    frames: int
    created_at: datetime


class PoseIn(BaseModel):
    """Camera-to-world pose, sent as a JSON string in the ``pose`` form field."""

    rotation: list[float] = Field(description="Unit quaternion [w, x, y, z].")
    translation: list[float] = Field(description="Translation [x, y, z] in metres.")


class IntrinsicsIn(BaseModel):
    """Pinhole intrinsics in pixels, sent as a JSON string in the ``intrinsics`` form field."""

    fx: float
    fy: float
    cx: float
    cy: float


class FrameOut(BaseModel):
    frame_id: int
    atlas: str
    submap: str
    robot_id: str
    timestamp: float | None
    pose: PoseIn | None
    intrinsics: IntrinsicsIn | None
    width: int
    height: int
    keypoints: int
    created_at: datetime


class RelativePoseOut(BaseModel):
    """Pose of the query camera relative to the candidate's: ``X_candidate = R X_query + t``."""

    rotation: list[float] = Field(description="Unit quaternion [w, x, y, z] of R.")
    translation: list[float] = Field(description="Unit direction of t (two views give no scale).")


class CandidateOut(BaseModel):
    frame_id: int
    submap: str
    robot_id: str
    similarity: float = Field(
        description=(
            "Cosine similarity of the query's and the frame's L2-normalised LoopNet embeddings, "
            "in [-1, 1]; 1 means identical embeddings."
        )
    )
    inliers: int | None = Field(
        None, description="RANSAC inliers of the local-feature matches; null: not verified."
    )
    inlier_ratio: float | None = Field(None, description="Inliers / tentative matches.")
    verified: bool = Field(False, description="Inliers reach the verification minimum.")
    score: float | None = Field(
        None,
        description="Calibrated score, -log10 of the probability that two frames of different "
        "places of this atlas are this similar (3: one impostor pair in a thousand); the same "
        "meaning on every atlas and model version. Null: the model version is not calibrated.",
    )
    relative_pose: RelativePoseOut | None = Field(
        None, description="From the essential matrix when both frames have intrinsics."
    )
    scale: float | None = Field(
        None,
        description="How much larger the inliers appear in this frame than in the query (their "
        "spread, in focal lengths when both frames have intrinsics, else in image long sides): "
        "about 1 from one spot, below 1 when this frame was taken further back along the view. "
        "Null: not verified or fewer than 8 inliers.",
    )


class VerificationOut(BaseModel):
    enabled: bool
    matcher: str | None = Field(None, description="'mnn' or 'lightglue'.")
    verified_candidates: int = Field(description="Candidates that went through RANSAC.")
    min_inliers: int | None = None


class SubmapPredictionOut(BaseModel):
    available: bool = Field(description="False until a retrain job has trained the classifier.")
    submap: str | None = None
    probability: float | None = Field(None, description="Softmax probability of that submap.")
    reason: str | None = Field(None, description="Why no prediction is given, when unavailable.")


class DeferredLoopOut(BaseModel):
    frame_id: int = Field(description="The robot's frame whose loop was pending.")
    loop_frame_id: int = Field(description="The frame to close that frame's loop with.")


class SequenceOut(BaseModel):
    score: float = Field(
        description="Sequence score of the best place: standardised similarities summed along "
        "the aligned reference frames / sqrt(length); higher is better."
    )
    length: int = Field(description="Frames of the robot's sequence actually aligned.")
    aligned: list[int | None] = Field(
        description="The reference frame aligned with each frame of the sequence, oldest first "
        "(the last one with this query); null where the reference trajectory had none."
    )
    speed: float = Field(description="Reference frames passed per query frame.")
    frame_id: int = Field(description="The reference frame aligned with this query.")
    margin: float = Field(
        description="score minus that of the best rival place (a scored candidate more than 3 "
        "frames away along its trajectory, or on another one; 0 when none was scored): in "
        "standard deviations, how distinct the place is from its best look-alike."
    )
    rival_frame_id: int | None = Field(
        description="The rival place's frame aligned with this query; null when there was none."
    )
    passed: bool = Field(
        description="A loop on the sequence's own evidence: margin >= margin_min over at least "
        "LOOPNET_CONSISTENCY_FRAMES aligned frames, and this query's frame alone favours the "
        "aligned frame (its standardised similarity is at least 1)."
    )
    margin_min: float = Field(
        0.0,
        description="The margin this sequence needed to pass: LOOPNET_SEQUENCE_MARGIN_MIN_OWN_RUN "
        "when its place lies on the robot's own current sequence (a revisit within one run), "
        "else LOOPNET_SEQUENCE_MARGIN_MIN; LOOPNET_SEQUENCE_MARGIN_MIN_TRACKING when lower and "
        f"the place continues the robot's newest loop within its last {TRACKING_DROPOUT} frames "
        "(a frame along the trajectory per frame driven since).",
    )
    aligned_z: list[float] = Field(
        default_factory=list,
        description="Each frame's own evidence for its aligned reference frame, oldest first: "
        "its similarity standardised as the score's terms are (0 where none aligned). The last "
        f"is this query's; a sequence passes only where it is at least {NEWEST_Z_MIN:g}, and "
        f"where none of the last 2-{OFF_MAP_FRAMES} frames' means falls short of a robot on the "
        f"map ({OFF_MAP_Z:g} less {OFF_MAP_SLACK:g} / frames: a robot that has left the mapped "
        "route).",
    )
    reason: str | None = Field(
        None,
        description='Why the sequence is not a loop on its own evidence, e.g. "margin 3.20 is '
        'below 4.5" or "this frame\'s own evidence (aligned_z 0.41) is below 1", or why its '
        "loop waits for a later frame (awaits_next); null when it passed and does not "
        "wait.",
    )
    awaits_next: bool = Field(
        False,
        description="The sequence passed, but this frame's own evidence (the last aligned_z) is "
        f"below LOOPNET_SEQUENCE_CONFIRM_Z ({CONFIRM_Z:g} by default): a robot's first frame "
        "off the mapped route still aligns along it by the frames behind it. The loop is not "
        "answered now (status 'candidate', "
        "pending_loop_frame_id). A later observation of the robot whose loop is answered at "
        "once confirms it (in its answer's 'confirmed') when the robot's frames between wait "
        "on loops of the same place too; weak frames never confirm each other alone.",
    )
    contrast_frames: int = Field(
        0,
        description="How many of the robot's frames just before this one the sequence was "
        "contrasted with: every frame's vector less the mean of its robot's previous frames, so "
        "a change of light or season shared by a traversal cancels "
        "(LOOPNET_TRAJECTORY_CONTRAST_FRAMES); 0: scored on plain vectors (contrast off, or "
        "the robot's first frame of a sequence).",
    )


class DecisionOut(BaseModel):
    loop_probability: float | None = Field(
        description="Probability that the match is the same place, from the parts in "
        "`contributions` (a logistic model chosen on the development sets): the one number "
        "the loop decision thresholds. Null only when the atlas has no frame to match "
        "(`reason` says so)."
    )
    threshold: float = Field(
        description="The probability a loop needs (LOOPNET_LOOP_PROBABILITY_MIN)."
    )
    passed: bool = Field(
        description="loop_probability reaches the threshold and the answer is closable."
    )
    closable: bool = Field(
        False,
        description="The checks no probability threshold overrides pass: the match is verified "
        "and, on a calibrated atlas, no less rare than the best of its impostors. A closable "
        "answer below the threshold would be a loop at a lower LOOPNET_LOOP_PROBABILITY_MIN; "
        "one that is not closable never would.",
    )
    parts: dict[str, float] = Field(
        description="The value of each part the answer has: inliers (log(1 + inliers) of the "
        "match), inlier_ratio, rival, score, sequence (see contributions)."
    )
    contributions: dict[str, float] = Field(
        description="Each part's term in the model's logit (positive: for a loop): inliers, "
        "inlier_ratio, rival (inliers over the best verified candidate of another place), "
        "score (calibrated score minus log10 of the atlas's frames), sequence (the robot's "
        "sequence margin). A part the answer lacks is absent and adds nothing."
    )
    failed: str | None = Field(
        None, description="The part that held the decision back most; null when it passed."
    )
    reason: str | None = Field(
        None,
        description="Why the answer is not a loop or cannot decide fully (too few frames to "
        "calibrate, no verified candidate, ...); null when the evidence is complete and passed.",
    )


class QueryOut(BaseModel):
    atlas: str
    model_version: int
    match: CandidateOut | None = Field(description="The best match, or null on an empty atlas.")
    candidates: list[CandidateOut] = Field(description="The top-k frames, best first.")
    loop_closure: bool = Field(
        description="With verification on: the best candidate (after re-ranking by inliers) "
        "is verified and decision.loop_probability reaches its threshold. With verification "
        "off: the best similarity (or calibrated score) reaches its threshold."
    )
    threshold: float
    predicted_submap: SubmapPredictionOut
    keypoints: int = Field(description="Local keypoints found in the query image.")
    timings_ms: dict[str, float] = Field(
        description="Milliseconds per stage: decode, local_features, global_features, heads, "
        "search, verification (all verified candidates), total."
    )
    margin: float | None = Field(
        None,
        description="Similarity of the match minus that of the best frame of another submap "
        "(another place): small or negative warns of a look-alike. Null when no other submap "
        "was among the frames searched.",
    )
    verification: VerificationOut
    score_threshold: float | None = Field(
        None,
        description="The calibrated score the match had to reach for a loop closure "
        "(LOOPNET_LOOP_SCORE_MIN + log10 of the frames in the atlas: the best of N impostors is N "
        "times likelier to pass); null when the model version is not calibrated and the "
        "similarity threshold decided.",
    )
    status: PlaceStatusValue = Field(
        description="'loop': loop_closure holds and the robot's last consistency_frames "
        "observations agree on one place, or the robot's sequence passed on its own "
        "(sequence.passed) with this frame's own evidence strong enough to answer at once; "
        "'candidate': loop_closure holds, not yet consistent, or the sequence's loop waits for "
        "a later frame (pending_loop_frame_id), or the match is more likely the same "
        "place than not (decision.loop_probability >= 0.5) without reaching the loop threshold; "
        "'new_place': nothing is likely."
    )
    new_place: bool = Field(description="Nothing in the atlas is likely the same place.")
    consistent: int = Field(
        description="Consecutive agreeing observations of the robot, this one included."
    )
    loop_frame_id: int | None = Field(
        None,
        description="When status is 'loop', the frame to close the loop with: the match when the "
        "single-frame answer passed consistently, else the sequence's aligned frame "
        "(sequence.frame_id); null otherwise.",
    )
    pending_loop_frame_id: int | None = Field(
        None,
        description="The frame a passed sequence would close the loop with, left to a later "
        "observation of the robot to confirm (sequence.awaits_next; status 'candidate'): do not "
        "close it yet. Null otherwise.",
    )
    confirmed: list[DeferredLoopOut] = Field(
        default_factory=list,
        description="The loops the robot's observations just before this one left pending, "
        "oldest first, that this one confirms: its loop is answered at once (status 'loop') and "
        "each names the same place as the loop after it. Close each now, between its frame and "
        "its loop_frame_id. Empty when none waits, or when this observation does not confirm "
        "them: a pending loop followed by an answer that is neither the same place's loop nor "
        "pending is dropped, and so is one further back among the robot's frames than the "
        "service reads (10 at the defaults): a back end may forget an older pending loop.",
    )
    sequence: SequenceOut | None = Field(
        None,
        description="Sequence matching over the robot's recent frames; null without a robot "
        "or with sequence_length 0.",
    )
    decision: DecisionOut | None = Field(
        None,
        description="The loop decision explained: loop_probability, the parts behind it, the "
        "one that failed and why.",
    )
    stay_frames: int = Field(
        0,
        description="How many of the asking robot's newest frames still show this place (its "
        "current stay, back to where the robot was elsewhere) and were left out like its recent "
        "frames: a robot that has not left a place does not close a loop with itself. "
        "0 without a robot, on an uncalibrated model version, or with LOOPNET_EXCLUDE_STAY off.",
    )


class ObserveOut(QueryOut):
    frame_id: int = Field(description="Id of the frame the observation inserted.")


class ModelVersionOut(BaseModel):
    version: int
    is_active: bool
    trained: bool
    config: dict[str, Any]
    metrics: dict[str, Any]
    created_at: datetime


class HealthOut(BaseModel):
    status: str


class ReadyOut(BaseModel):
    ready: bool
    detail: str
    preset: str | None = None
    backbone: str | None = None
    local_extractor: str | None = None
    unavailable_atlases: dict[str, str] = Field(
        default_factory=dict,
        description="Atlases that cannot be loaded, with why; they answer 503, the others serve. "
        "Listed only to callers showing a valid key (the atlases it may use; anyone while the "
        "API is open); `detail` says how many to every caller.",
    )


class LoopClosureOut(BaseModel):
    id: int
    robot_id: str = Field(description="The robot whose query or observation closed the loop.")
    frame_id: int = Field(description="The matched frame.")
    matched_robot_id: str = Field(description="The robot that took the matched frame.")
    submap: str
    similarity: float
    model_version: int
    source: str = Field(description="query or observe")
    created_at: datetime
