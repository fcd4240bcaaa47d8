"""Adapted LoopNet in the evaluation: the ``adapt`` job's learned whitening from revisit pairs.

The revisit protocol of :mod:`service.evaluation.retraining_pass` with the adaptation job's own
code (:func:`adapt_heads`): K frames per submap from the *query* condition are revisits the
service verified, each paired with its partner reference (the middle one of its right
references); they join the atlas (as a second robot's frames, as ``observe`` stores them) and
are left out of the test queries. The whitening is fitted on the atlas's frames and the
training pairs; the job's gate judges it on held-out pairs and held-out stretches, and says
which version the service would serve. Scores come from the impostor model the job refits.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from service.evaluation.calibrated_pass import top1_spread
from service.evaluation.datasets import Dataset
from service.evaluation.metrics import correct_matrix, rank_by_similarity
from service.evaluation.protocol import evaluate_ranking
from service.evaluation.retraining_pass import (
    RetrainingRow,
    StartingPoint,
    _rows,
    _scored,
    _subset,
    query_submaps,
    shot_data,
)
from service.evaluation.service_pass import PassResult
from service.jobs.adaptation_config import DEFAULT_METHOD, METHOD_TEXT, AdaptConfig, AdaptMethod
from service.ml.adaptation import adapt_heads
from service.ml.heads import LoopNetHeads
from service.ml.pair_loss import PairLossConfig
from service.ml.pair_whitening import PairWhiteningConfig
from service.ml.pipeline import embed_vectors

PROTOCOL = "revisit-adapt"


def partner_of(dataset: Dataset) -> np.ndarray:
    """Each query's partner reference (its middle right one), -1 when it has none."""
    partners = np.full(len(dataset.queries), -1, dtype=np.int64)
    for i, query in enumerate(dataset.queries):
        if query.positives:
            positives = sorted(query.positives)
            partners[i] = positives[len(positives) // 2]
    return partners


def adaptation_rows(
    dataset: Dataset,
    submap_of: Sequence[int],
    result: PassResult,
    start: StartingPoint,
    *,
    shots: Sequence[int],
    config: PairWhiteningConfig | None = None,
    method: AdaptMethod = DEFAULT_METHOD,
    pair_loss: PairLossConfig | None = None,
    k: int = 10,
    extractor_label: str = "DISK",
) -> list[RetrainingRow]:
    """One adapted model per K (revisit pairs per submap), from ``start``, by the adapt job's
    ``method`` (``pair_loss``: its loss's settings when the method trains on the pairs)."""
    steps = AdaptConfig(method=method)
    ref_local, ref_global = start.references
    query_local, query_global = start.queries
    ref_submaps = np.asarray(submap_of, dtype=np.int64)
    n_refs = len(ref_submaps)
    revisited = query_submaps(dataset, submap_of)
    partners = partner_of(dataset)
    active = LoopNetHeads(start.base).eval()
    rows: list[RetrainingRow] = []
    for k_shots in shots:
        query_shots, test, data = shot_data(start, ref_submaps, revisited, k_shots)
        pairs = np.stack([n_refs + np.arange(len(query_shots)), partners[query_shots]], axis=1)
        adapted = adapt_heads(
            data,
            pairs,
            active,
            config or PairWhiteningConfig(),
            min_pairs=2,
            window=2,
            whiten=steps.whitens,
            pair_loss=(pair_loss or PairLossConfig()) if steps.trains_on_pairs else None,
        )
        heads = adapted.heads
        started = time.perf_counter()
        references = embed_vectors(heads, ref_local, ref_global)
        ranking = rank_by_similarity(
            embed_vectors(heads, query_local[test], query_global[test]) @ references.T, k
        )
        per_query = (time.perf_counter() - started) * 1000.0 / max(len(test), 1)
        cosine_top = ranking.scores[:, 0].copy()
        ranking, score_text = _scored(heads, start, ranking, adapted.impostor_refit)
        subset = _subset(dataset, test)
        right = correct_matrix(ranking, [q.positives for q in subset.queries])[:, 0]
        after = evaluate_ranking(
            f"adapted-revisit-k{k_shots}",
            f"LoopNet {extractor_label} adapted: {METHOD_TEXT[method]} ({len(pairs)} revisit "
            f"pairs, {k_shots}/submap)",
            "adapted",
            ranking,
            subset,
            submap_of,
            query_ms=np.full(len(test), per_query),
            details={
                "protocol": PROTOCOL,
                "shots_per_submap": k_shots,
                "adaptation": adapted.metrics,
                "score": score_text,
                "top1_spread": top1_spread(cosine_top, ranking.scores[:, 0], right),
            },
        )
        before = evaluate_ranking(
            f"untrained-{PROTOCOL}-k{k_shots}",
            start.before.label,
            "loopnet",
            _rows(start.before.ranking, test),
            subset,
            submap_of,
        )
        gate = {**adapted.gate, "frames": adapted.gate.get("pairs", 0)}
        rows.append(
            RetrainingRow(
                protocol=PROTOCOL,
                shots=k_shots,
                train_frames=int(adapted.metrics["training_pairs"]),
                test_queries=int(len(test)),
                before=before,
                after=after,
                classifier_submap_accuracy=float("nan"),
                train_seconds=float(adapted.metrics["fit_seconds"]),
                epochs_run=0,
                best_epoch=1,
                shots_used=k_shots,
                calibrated=start.calibrated,
                gate=gate,
            )
        )
    return rows
