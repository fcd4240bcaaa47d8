"""Place-recognition metrics from ranked retrievals: Recall@K, the paper's submap and frame
accuracy, and loop closure as a thresholded decision (precision-recall, AUC-PR, recall at 100%
precision).

Conventions (those of VPR-methods-evaluation and VPR-Bench):

- A query counts in Recall@K when it has at least one right reference; it is a hit when one of
  its K best-ranked references is right.
- Loop-closure decision: a query is *accepted* when its best similarity is at or above the
  threshold. An accepted query whose best match is right is a true positive, one whose best
  match is wrong a false positive. Recall divides the true positives by the queries that have
  a right reference, so the curve ends at Recall@1, not at 1.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Ranking:
    """The ``K`` best references of every query, best first.

    Attributes:
        indices: ``Q x K`` int64 reference indices.
        scores: ``Q x K`` float similarities (higher is more similar).
    """

    indices: np.ndarray
    scores: np.ndarray

    def __post_init__(self) -> None:
        if self.indices.shape != self.scores.shape or self.indices.ndim != 2:
            raise ValueError(
                f"indices {self.indices.shape} and scores {self.scores.shape} must be Q x K"
            )


def rank_by_similarity(similarity: np.ndarray, k: int) -> Ranking:
    """``Q x R`` similarities -> the ``k`` best references of each query (ties: lower index)."""
    k = min(k, similarity.shape[1])
    order = np.argsort(-similarity, axis=1, kind="stable")[:, :k]
    return Ranking(order.astype(np.int64), np.take_along_axis(similarity, order, axis=1))


def correct_matrix(ranking: Ranking, positives: Sequence[frozenset[int]]) -> np.ndarray:
    """``Q x K`` bool: is the reference at rank k right for query q."""
    return np.array(
        [
            [int(i) in truth for i in row]
            for row, truth in zip(ranking.indices, positives, strict=True)
        ],
        dtype=bool,
    ).reshape(ranking.indices.shape)


def recall_at_k(
    ranking: Ranking, positives: Sequence[frozenset[int]], ks: Sequence[int] = (1, 5, 10)
) -> dict[int, float]:
    """Share of answerable queries with a right reference among their ``k`` best."""
    answerable = np.array([bool(p) for p in positives])
    if not answerable.any():
        return {k: float("nan") for k in ks}
    hits = correct_matrix(ranking, positives)[answerable]
    return {k: float(hits[:, :k].any(axis=1).mean()) for k in ks}


def submap_accuracy(
    ranking: Ranking, positives: Sequence[frozenset[int]], submap_of: Sequence[int]
) -> float:
    """The paper's submap accuracy: the best match's submap holds a right reference."""
    submaps = np.asarray(submap_of)
    right = [
        bool((submaps[sorted(truth)] == submaps[row[0]]).any())
        for row, truth in zip(ranking.indices, positives, strict=True)
        if truth
    ]
    return float(np.mean(right)) if right else float("nan")


@dataclass(frozen=True)
class PrecisionRecall:
    """The loop-closure decision swept over every threshold.

    Attributes:
        thresholds: distinct best-match similarities, descending; point i accepts every query
            whose best similarity is >= thresholds[i].
        precision, recall: at each threshold.
        auc: area under the curve (average precision: precision summed over recall steps).
        recall_at_full_precision: the largest recall with no false positive (0 if none).
        threshold_at_full_precision: the threshold that gives it (None if recall is 0).
    """

    thresholds: np.ndarray
    precision: np.ndarray
    recall: np.ndarray
    auc: float
    recall_at_full_precision: float
    threshold_at_full_precision: float | None


def precision_recall(
    best_scores: np.ndarray, best_correct: np.ndarray, answerable: int
) -> PrecisionRecall:
    """PR curve of accepting queries by their best similarity.

    Args:
        best_scores: ``Q`` best-match similarities.
        best_correct: ``Q`` bool, the best match is right.
        answerable: how many queries have a right reference (the recall denominator).
    """
    scores = np.asarray(best_scores, dtype=np.float64)
    correct = np.asarray(best_correct, dtype=bool)
    order = np.argsort(-scores, kind="stable")
    scores, correct = scores[order], correct[order]
    true_pos = np.cumsum(correct)
    accepted = np.arange(1, len(scores) + 1)
    # one point per distinct threshold: the last position of each run of equal scores
    last_of_run = np.r_[scores[1:] != scores[:-1], True] if len(scores) else np.zeros(0, bool)
    thresholds = scores[last_of_run]
    precision = true_pos[last_of_run] / accepted[last_of_run]
    recall = true_pos[last_of_run] / max(answerable, 1)
    auc = float(np.sum(np.diff(np.r_[0.0, recall]) * precision))
    # Once a false positive is accepted precision never returns to 1: the points with
    # precision 1 are a prefix of the curve, and its last one has the largest recall.
    perfect = np.flatnonzero(precision >= 1.0)
    if len(perfect) and recall[perfect[-1]] > 0:
        full_recall, full_threshold = float(recall[perfect[-1]]), float(thresholds[perfect[-1]])
    else:
        full_recall, full_threshold = 0.0, None
    return PrecisionRecall(thresholds, precision, recall, auc, full_recall, full_threshold)


def summary(values: Sequence[float] | np.ndarray) -> dict[str, float]:
    """Median and 95th percentile (ms) of a list of timings."""
    if not len(values):
        return {"median": float("nan"), "p95": float("nan"), "n": 0}
    array = np.asarray(values, dtype=np.float64)
    return {
        "median": float(np.median(array)),
        "p95": float(np.percentile(array, 95)),
        "n": int(len(array)),
    }
