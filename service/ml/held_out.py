"""What a retraining job keeps out of training to judge its new heads by: whole stretches.

The job holds out the frames its calibration's impostor probe holds out (about a fifth of each
robot's sequence, in stretches a twentieth of it long: :func:`held_out_stretches`). Shots and
the validation frames that pick the best epoch come from the rest, so no step of training or
model selection sees a held-out place. The not-worse gate then compares the active and the new
heads on those places. The first gate judged on the frames beside the shots (one per submap
next to them), where a version that had learnt the shots by heart looked as good as any and
passed versions that lowered the queries' Recall@1 (benchmarks/archive/RESULTS-history.md,
"Retraining that does not forget"). Nearest-frame accuracy alone saturates on a single
traversal (every version that does not wreck the space finds a held-out frame's own
neighbour, also while the queries lose), so the
gate also compares the mean average precision of each held-out frame's whole neighbourhood,
which still moves when the top-1 does not.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from service.ml.calibration import CalibrationConfig, held_out_stretches
from service.ml.heads import LoopNetHeads
from service.ml.pipeline import embed_vectors
from service.ml.training import TrainingData, split_shots

HELD_OUT_SHARE = CalibrationConfig().impostor_holdout  # as the impostor probe holds out
BLOCK_VALUES = 1 << 24  # similarities (and right-answer flags) held at once: held-out x atlas
# held-out frames (evenly spread) the gate judges by: each is compared with every atlas frame,
# so the gate's cost stays bounded on large atlases (a fifth of 1M frames would be 2e14 FLOP)
JUDGED_FRAMES = 8192
AP_FRAMES = 2048  # of those, the ones whose whole ranking is scored: a sort each
# a submap of at most this many frames is one place (its frames are each other's right
# answers); a longer one is a route (a robot's whole drive in one submap), where only a frame's
# neighbours along it are its place: counting a drive's 1,772 winter frames as one place made
# the gate reward a version for ranking "winter" first and refuse one that removed the season
PLACE_SUBMAP_FRAMES = 25


@dataclass(frozen=True)
class JobSplit:
    """Indices into a job's :class:`TrainingData`: shots train, validation picks the best
    epoch, held-out frames (whole stretches) judge the result."""

    shots: np.ndarray
    validation: np.ndarray
    held_out: np.ndarray


def split_for_job(data: TrainingData, shots: int, share: float = HELD_OUT_SHARE) -> JobSplit:
    """Hold out stretches of ``share`` of the frames; ``shots`` per submap from the rest
    (:func:`split_shots`), whose other frames validate."""
    robots = data.robots if data.robots is not None else np.zeros(len(data.submaps))
    held = held_out_stretches([str(r) for r in robots], np.asarray(data.frame_ids), share)
    rest = np.flatnonzero(~held)
    picked, _ = split_shots(data.submaps[rest], shots)
    train = rest[picked]
    return JobSplit(train, np.setdiff1d(rest, train), np.flatnonzero(held))


@dataclass(frozen=True)
class HeldOutScores:
    """How well a version's held-out frames find their neighbourhood (both in [0, 1])."""

    accuracy: float  # share whose most similar other frame is a right one
    mean_average_precision: float  # of the ranking of all other frames, right ones first


def _average_precision(similarity: np.ndarray, right: np.ndarray) -> float:
    """Average precision of one frame's ranking of the others (``-inf`` marks itself); ties
    count against the right frames. 0 when it has no right frame."""
    right_scores = similarity[right]
    if len(right_scores) == 0:
        return 0.0
    ordered = np.sort(similarity)
    # rank (from 1) of each right frame: frames at least as similar, itself excluded
    ranks = len(ordered) - np.searchsorted(ordered, right_scores, side="left")
    ranks = np.sort(ranks)
    return float(np.mean(np.arange(1, len(ranks) + 1) / ranks))


def _evenly(frames: np.ndarray, most: int) -> np.ndarray:
    """At most ``most`` of ``frames``, evenly spread (all of them when there are fewer)."""
    if len(frames) <= most:
        return frames
    picked: np.ndarray = frames[np.linspace(0, len(frames) - 1, most).astype(int)]
    return picked


def held_out_scores(
    heads: LoopNetHeads,
    data: TrainingData,
    held_out: np.ndarray,
    window: int,
    same_place: np.ndarray | None = None,
) -> HeldOutScores:
    """Ranks every other frame of the atlas (by the heads' embedding) for each ``held_out``
    frame (:data:`JUDGED_FRAMES` of them at most); right ones are in its submap when the
    submap is a place (:data:`PLACE_SUBMAP_FRAMES`), or of its robot at most ``window`` frames
    away: a place no training step saw must still find its own neighbourhood, not a trained
    place. (Only stretch edges would have a right answer among the
    frames outside the stretches.) ``same_place``: ``P x 2`` rows known to show one place
    (revisit pairs): the neighbourhood of a pair's other frame is right too, so a frame of
    a second robot that finds the first robot's frames of its place is not counted wrong."""
    embeddings = embed_vectors(heads, data.local, data.global_)
    codes, rank, _ = data.sequence
    places = place_submaps(data.submaps)
    held_out = _evenly(held_out, JUDGED_FRAMES)
    ranked = set(_evenly(held_out, AP_FRAMES).tolist())
    block = max(1, BLOCK_VALUES // len(embeddings))
    hits = 0
    precisions: list[float] = []
    for start in range(0, len(held_out), block):
        rows = held_out[start : start + block]
        similarity = embeddings[rows] @ embeddings.T
        similarity[np.arange(len(rows)), rows] = -np.inf  # not itself
        right = (places[None, :] == places[rows, None]) | (
            (codes[None, :] == codes[rows, None])
            & (np.abs(rank[None, :] - rank[rows, None]) <= window)
        )
        if same_place is not None and len(same_place):
            right |= _partners_neighbourhood(right, data, places, same_place, window)
        right[np.arange(len(rows)), rows] = False
        hits += int(np.sum(right[np.arange(len(rows)), similarity.argmax(axis=1)]))
        precisions += [
            _average_precision(similarity[i], right[i])
            for i, row in enumerate(rows)
            if int(row) in ranked
        ]
    return HeldOutScores(hits / len(held_out), float(np.mean(precisions)))


def place_submaps(submaps: np.ndarray) -> np.ndarray:
    """Per frame, a code shared by the frames of its submap when the submap is a place (at most
    :data:`PLACE_SUBMAP_FRAMES` frames), else -1 - its own index (no other frame shares it)."""
    _, inverse, counts = np.unique(submaps, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    alone = -1 - np.arange(len(inverse))
    return np.where(counts[inverse] <= PLACE_SUBMAP_FRAMES, inverse, alone)


def _partners_neighbourhood(
    right: np.ndarray,
    data: TrainingData,
    places: np.ndarray,
    same_place: np.ndarray,
    window: int,
) -> np.ndarray:
    """Per row of ``right`` (its frame's neighbourhood), the neighbourhoods of the other frames
    of the ``same_place`` pairs that touch it (``places``: :func:`place_submaps`)."""
    codes, rank, _ = data.sequence
    both = np.concatenate([same_place, same_place[:, ::-1]])
    extra = np.zeros_like(right)
    for i in range(len(right)):
        partners = both[right[i, both[:, 0]], 1]
        if len(partners):
            extra[i] = np.any(
                (places[None, :] == places[partners, None])
                | (
                    (codes[None, :] == codes[partners, None])
                    & (np.abs(rank[None, :] - rank[partners, None]) <= window)
                ),
                axis=0,
            )
    return extra


def compare_on_held_out(
    active: LoopNetHeads,
    new: LoopNetHeads,
    data: TrainingData,
    held_out: np.ndarray,
    window: int,
    same_place: np.ndarray | None = None,
) -> dict[str, Any]:
    """:func:`held_out_scores` of the active and the new heads: the new version is not worse
    when it is at least as good by both nearest-frame accuracy and mean average precision."""
    if len(held_out) == 0:
        return {"frames": 0, "active": None, "new": None, "change": None, "not_worse": True}
    before = held_out_scores(active, data, held_out, window, same_place)
    after = held_out_scores(new, data, held_out, window, same_place)
    return {
        "frames": int(len(held_out)),
        "judged_frames": min(len(held_out), JUDGED_FRAMES),
        "judged_on": "held-out stretches: the other frames of their submap (one of at most "
        f"{PLACE_SUBMAP_FRAMES} frames) or within {window} frames"
        + (", or of their revisit pairs' places" if same_place is not None else "")
        + ", nearest (accuracy) and all ranked (mean average precision)",
        "active": round(before.accuracy, 4),
        "new": round(after.accuracy, 4),
        "change": round(after.accuracy - before.accuracy, 4),
        "map_active": round(before.mean_average_precision, 4),
        "map_new": round(after.mean_average_precision, 4),
        "map_change": round(after.mean_average_precision - before.mean_average_precision, 4),
        "not_worse": bool(
            after.accuracy >= before.accuracy
            and after.mean_average_precision >= before.mean_average_precision
        ),
    }
