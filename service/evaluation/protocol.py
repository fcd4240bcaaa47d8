"""The evaluation protocol: submaps of the map, and every metric of one method's ranking.

The paper's protocol groups the reference frames into submaps of consecutive frames (or takes
the dataset's own submaps, as LoopDB's) and asks, for each query of another traversal or
condition, for the [submap/frame] it revisits. The predicted submap is the submap of the best
matching frame (the classification head is not trained yet; the report says so). A query is
right for *submap accuracy* when that submap holds a right reference, and for *frame accuracy*
when the best frame itself is right (which is Recall@1).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from service.evaluation.datasets import Dataset
from service.evaluation.metrics import (
    Ranking,
    correct_matrix,
    precision_recall,
    rank_by_similarity,
    recall_at_k,
    submap_accuracy,
    summary,
)
from service.ml.heads import HeadsConfig, LoopNetHeads
from service.ml.pipeline import embed_vectors

RECALL_KS = (1, 5, 10)


def assign_submaps(dataset: Dataset, submap_size: int) -> tuple[list[int], str]:
    """Submap number of every reference, and how they were formed (for the report)."""
    if dataset.has_native_submaps:
        labels: dict[str, int] = {}
        numbers = [labels.setdefault(str(r.submap), len(labels)) for r in dataset.references]
        return numbers, f"the dataset's own submaps ({len(labels)})"
    if submap_size < 1:
        raise ValueError(f"submap size must be at least 1, got {submap_size}")
    numbers = [i // submap_size for i in range(len(dataset.references))]
    return numbers, (f"{max(numbers) + 1} submaps of {submap_size} consecutive reference frames")


@dataclass
class MethodResult:
    """Every metric of one method on one dataset."""

    name: str
    label: str
    kind: str  # "loopnet", "ablation" or "baseline"
    recall: dict[int, float]
    submap_accuracy: float
    frame_accuracy: float
    auc_pr: float
    recall_at_full_precision: float
    threshold_at_full_precision: float | None
    pr_curve: dict[str, list[float]]
    ranking: Ranking
    query_ms: dict[str, float] = field(default_factory=dict)
    details: dict[str, Any] = field(default_factory=dict)

    def row(self) -> dict[str, Any]:
        """The JSON form (without the per-query ranking)."""
        return {
            "name": self.name,
            "label": self.label,
            "kind": self.kind,
            **{f"recall@{k}": v for k, v in self.recall.items()},
            "submap_accuracy": self.submap_accuracy,
            "frame_accuracy": self.frame_accuracy,
            "auc_pr": self.auc_pr,
            "recall_at_100_precision": self.recall_at_full_precision,
            "threshold_at_100_precision": self.threshold_at_full_precision,
            "query_ms": self.query_ms,
            "details": self.details,
            "pr_curve": self.pr_curve,
        }


def evaluate_ranking(
    name: str,
    label: str,
    kind: str,
    ranking: Ranking,
    dataset: Dataset,
    submap_of: Sequence[int],
    *,
    query_ms: Sequence[float] | np.ndarray = (),
    details: dict[str, Any] | None = None,
    eligible: np.ndarray | None = None,
) -> MethodResult:
    """``eligible``: per query, whether any threshold may accept its answer (None: all); the
    PR curve sweeps those only, the others are never accepted (a served answer that is not
    closable) and count only in the recall's denominator."""
    positives = [q.positives for q in dataset.queries]
    answerable = sum(1 for p in positives if p)
    recall = recall_at_k(ranking, positives, RECALL_KS)
    best_correct = correct_matrix(ranking, positives)[:, 0]
    swept = np.ones(len(best_correct), bool) if eligible is None else np.asarray(eligible, bool)
    curve = precision_recall(ranking.scores[swept, 0], best_correct[swept], answerable)
    return MethodResult(
        name=name,
        label=label,
        kind=kind,
        recall=recall,
        submap_accuracy=submap_accuracy(ranking, positives, submap_of),
        frame_accuracy=recall[1],
        auc_pr=curve.auc,
        recall_at_full_precision=curve.recall_at_full_precision,
        threshold_at_full_precision=curve.threshold_at_full_precision,
        pr_curve={  # 6 decimals keep report.json small on datasets with thousands of queries
            "threshold": np.round(curve.thresholds, 6).tolist(),
            "precision": np.round(curve.precision, 6).tolist(),
            "recall": np.round(curve.recall, 6).tolist(),
        },
        ranking=ranking,
        query_ms=summary(np.asarray(query_ms, dtype=np.float64)),
        details=details or {},
    )


def embedding_ranking(
    references: tuple[np.ndarray, np.ndarray],
    queries: tuple[np.ndarray, np.ndarray],
    alpha: float,
    k: int,
) -> Ranking:
    """Rank with untrained LoopNet heads at fusion weight ``alpha`` on stored (D, R) vectors.

    Exact cosine search, like the service's flat FAISS index: the same stored vectors through
    :func:`embed_vectors`, no CNN pass.
    """
    config = HeadsConfig(
        local_dim=references[0].shape[1], global_dim=references[1].shape[1], alpha=alpha
    )
    heads = LoopNetHeads(config).eval()
    reference_embeddings = embed_vectors(heads, *references)
    query_embeddings = embed_vectors(heads, *queries)
    return rank_by_similarity(query_embeddings @ reference_embeddings.T, k)
