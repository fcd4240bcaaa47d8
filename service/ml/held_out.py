"""What a retraining job keeps out of training to judge its new heads by: whole stretches.

The job holds out the frames its calibration's impostor probe holds out (about a fifth of each
robot's sequence, in stretches a twentieth of it long: :func:`held_out_stretches`). Shots and
the validation frames that pick the best epoch come from the rest, so no step of training or
model selection sees a held-out place. The not-worse gate then compares the active and the new
heads on those places. The first gate judged on the frames beside the shots (one per submap
next to them), where a version that had learnt the shots by heart looked as good as any: on
Nordland (summer map, winter queries) map-only retraining lowered Recall@1 0.323 -> 0.308 and
passed it (benchmarks/RESULTS.md, "Retraining that does not forget").
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
BLOCK = 1024  # held-out frames compared with every frame at once


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


def held_out_accuracy(
    heads: LoopNetHeads, data: TrainingData, held_out: np.ndarray, window: int
) -> float:
    """Share of the ``held_out`` frames whose most similar other frame of the atlas (by the
    heads' embedding) is in their submap, or of their robot at most ``window`` frames away:
    a place no training step saw must still find its own neighbourhood, not a trained place.
    (Only stretch edges would have a right answer among the frames outside the stretches.)"""
    embeddings = embed_vectors(heads, data.local, data.global_)
    codes, rank, _ = data.sequence
    right = 0
    for start in range(0, len(held_out), BLOCK):
        rows = held_out[start : start + BLOCK]
        similarity = embeddings[rows] @ embeddings.T
        similarity[np.arange(len(rows)), rows] = -np.inf  # not itself
        nearest = similarity.argmax(axis=1)
        near_in_sequence = (codes[nearest] == codes[rows]) & (
            np.abs(rank[nearest] - rank[rows]) <= window
        )
        right += int(np.sum((data.submaps[nearest] == data.submaps[rows]) | near_in_sequence))
    return right / len(held_out)


def compare_on_held_out(
    active: LoopNetHeads, new: LoopNetHeads, data: TrainingData, held_out: np.ndarray, window: int
) -> dict[str, Any]:
    """:func:`held_out_accuracy` of the active and the new heads: the new version is not worse
    when it is at least as accurate."""
    if len(held_out) == 0:
        return {"frames": 0, "active": None, "new": None, "change": None, "not_worse": True}
    before = held_out_accuracy(active, data, held_out, window)
    after = held_out_accuracy(new, data, held_out, window)
    return {
        "frames": int(len(held_out)),
        "judged_on": "held-out stretches: nearest other frame in the submap or within "
        f"{window} frames",
        "active": round(before, 4),
        "new": round(after, 4),
        "change": round(after - before, 4),
        "not_worse": after >= before,
    }
