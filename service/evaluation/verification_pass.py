"""Geometric verification in the evaluation harness: the service's retrieval ranking, its best
candidates verified by the service's own :class:`~service.ml.verification.Verifier`, re-ranked by
:func:`~service.ml.verification.rerank`, and scored as a loop-closure decision.

Keypoints are extracted once per image by the pass's local extractor (only for the queries and
the references that appear among their verified candidates) and cached beside the feature
cache, descriptors rounded to float16 as the feature store keeps them, so what is verified
here is what the service verifies from its database.

The verified rows' precision-recall sweeps the inlier count of the re-ranked best match (the
verification's own threshold); the operating point at the service's defaults (similarity
threshold and minimum inliers together) is reported beside it.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from service.evaluation.datasets import Dataset
from service.evaluation.metrics import Ranking, correct_matrix, summary
from service.evaluation.protocol import MethodResult, evaluate_ranking
from service.ml.features import FrameFeatures, LocalFeatures
from service.ml.images import decode_image
from service.ml.local_extractors import LocalExtractor
from service.ml.two_view import RansacConfig
from service.ml.verification import (
    VerificationConfig,
    Verifier,
    View,
    default_min_inliers,
    rerank,
)

MATCHER_LABELS = {"mnn": "MNN + ratio", "lightglue": "LightGlue"}


def subsample_queries(dataset: Dataset, stride: int) -> Dataset:
    """Every ``stride``-th query (all references): bounds the run time on long datasets."""
    if stride <= 1:
        return dataset
    kept = dataset.queries[::stride]
    return replace(
        dataset,
        queries=kept,
        excluded=[
            *dataset.excluded,
            f"query subsample: every {ordinal(stride)} query ({len(kept)} of "
            f"{len(dataset.queries)})",
        ],
    )


def ordinal(n: int) -> str:
    """``1st``, ``2nd``, ``3rd``, ``4th``, ``11th``, ``12th``, ``13th``, ``21st`` ..."""
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


class KeypointCache:
    """Local features of single images on disk, keyed by the file and the extractor settings."""

    def __init__(self, directory: Path, extractor: LocalExtractor) -> None:
        self.directory = directory
        self.extractor = extractor
        self.signature = json.dumps(extractor.config.__dict__, sort_keys=True, default=str)
        self.extract_ms: list[float] = []

    def _path(self, image: Path) -> Path:
        stat = image.stat()
        key = f"{image.resolve()}|{stat.st_size}|{stat.st_mtime_ns}|{self.signature}"
        return self.directory / f"{hashlib.sha1(key.encode()).hexdigest()[:20]}.npz"

    def store(self, image: Path, features: FrameFeatures) -> None:
        """Keep the keypoints of a frame another pass already extracted."""
        self._save(self._path(image), features.local, features.image_size)

    def _save(self, path: Path, local: LocalFeatures, size: tuple[int, int]) -> View:
        # float16 descriptors: exactly what the feature store gives verification back
        stored = LocalFeatures(
            local.keypoints.astype(np.float32),
            local.descriptors.astype(np.float16).astype(np.float32),
            local.scores.astype(np.float32),
        )
        self.directory.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.stem + ".tmp.npz")
        np.savez(
            tmp,
            keypoints=stored.keypoints,
            descriptors=stored.descriptors.astype(np.float16),
            scores=stored.scores,
            size=np.array(size),
        )
        tmp.replace(path)
        return View(stored, size)

    def view(self, image: Path) -> View:
        path = self._path(image)
        if path.is_file():
            with np.load(path) as data:
                local = LocalFeatures(
                    data["keypoints"], data["descriptors"].astype(np.float32), data["scores"]
                )
                size = (int(data["size"][0]), int(data["size"][1]))
            return View(local, size)
        rgb = decode_image(image.read_bytes())
        start = time.perf_counter()
        local = self.extractor.extract(rgb)
        self.extract_ms.append((time.perf_counter() - start) * 1000.0)
        return self._save(path, local, (rgb.shape[1], rgb.shape[0]))


@dataclass
class VerifiedRanking:
    """One matcher's verification of a retrieval ranking.

    Attributes:
        ranking: ``Q x k`` after re-ranking the verified head; scores[:, 0] holds the inlier
            count of the re-ranked best match (the decision's score).
        best_similarity: ``Q`` retrieval similarity of the re-ranked best match.
        best_inliers: ``Q`` its inliers.
        candidate_ms: milliseconds per verified candidate (matching + RANSAC).
        query_ms: per query, all its candidates.
    """

    matcher: str
    ranking: Ranking
    best_similarity: np.ndarray
    best_inliers: np.ndarray
    candidate_ms: list[float]
    query_ms: list[float]


def verify_ranking(
    dataset: Dataset,
    base: Ranking,
    cache: KeypointCache,
    config: VerificationConfig,
    *,
    label: str,
) -> VerifiedRanking:
    """Verify the ``config.top`` best candidates of every query of ``base`` and re-rank them."""
    verifier = Verifier(config)
    indices = base.indices.copy()
    scores = np.zeros(base.scores.shape, np.float64)
    best_similarity = np.zeros(len(indices))
    best_inliers = np.zeros(len(indices), np.int64)
    candidate_ms: list[float] = []
    query_ms: list[float] = []
    for q, query in enumerate(tqdm(dataset.queries, desc=label, unit="query", leave=False)):
        query_view = cache.view(query.path)
        row = [int(i) for i in base.indices[q] if i >= 0]
        similarities = [float(s) for s in base.scores[q][: len(row)]]
        inliers: list[int | None] = [None] * len(row)
        scales: list[float | None] = [None] * len(row)
        spent = 0.0
        for position, reference in enumerate(row[: config.top]):
            found = verifier.verify(query_view, cache.view(dataset.references[reference].path))
            inliers[position] = found.inliers
            scales[position] = found.scale
            candidate_ms.append(found.ms)
            spent += found.ms
        query_ms.append(spent)
        order = rerank(similarities, inliers, scales, scale_tolerance=config.scale_tolerance)
        reranked = [row[i] for i in order]
        indices[q, : len(reranked)] = reranked
        best = order[0] if order else None
        best_inliers[q] = (inliers[best] or 0) if best is not None else 0
        best_similarity[q] = similarities[best] if best is not None else -np.inf
        scores[q, :] = -np.inf
        scores[q, : len(order)] = [
            float(n) if (n := inliers[i]) is not None else -1.0 for i in order
        ]
    return VerifiedRanking(
        config.matcher,
        Ranking(indices, scores),
        best_similarity,
        best_inliers,
        candidate_ms,
        query_ms,
    )


def operating_point(
    verified: VerifiedRanking, dataset: Dataset, similarity_threshold: float, min_inliers: int
) -> dict[str, float]:
    """Precision and recall of the service's decision: similarity and inliers both pass."""
    positives = [q.positives for q in dataset.queries]
    correct = correct_matrix(verified.ranking, positives)[:, 0]
    accepted = (verified.best_similarity >= similarity_threshold) & (
        verified.best_inliers >= min_inliers
    )
    answerable = max(sum(1 for p in positives if p), 1)
    true_positives = int((accepted & correct).sum())
    return {
        "similarity_threshold": similarity_threshold,
        "min_inliers": min_inliers,
        "accepted": int(accepted.sum()),
        "precision": true_positives / accepted.sum() if accepted.any() else float("nan"),
        "recall": true_positives / answerable,
    }


def verified_method(
    verified: VerifiedRanking,
    dataset: Dataset,
    submap_of: Sequence[int],
    *,
    extractor_label: str,
    retrieval_query_ms: Sequence[float],
    config: VerificationConfig,
    similarity_threshold: float,
) -> MethodResult:
    """The harness row of one matcher, with per-query data for choosing thresholds."""
    positives = [q.positives for q in dataset.queries]
    correct = correct_matrix(verified.ranking, positives)[:, 0]
    label = (
        f"LoopNet {extractor_label} + {MATCHER_LABELS.get(verified.matcher, verified.matcher)} "
        f"verification of top {config.top} (score = inliers)"
    )
    details: dict[str, Any] = {
        "matcher": verified.matcher,
        "verify_top": config.top,
        "ratio": config.ratio if verified.matcher == "mnn" else None,
        "ransac": config.ransac.__dict__,
        "ms_per_candidate": summary(verified.candidate_ms),
        "ms_verification_per_query": summary(verified.query_ms),
        "operating_point": operating_point(
            verified, dataset, similarity_threshold, config.min_inliers
        ),
        "per_query": {
            "best_similarity": np.round(verified.best_similarity, 6).tolist(),
            "best_inliers": verified.best_inliers.tolist(),
            "best_correct": correct.astype(int).tolist(),
        },
    }
    return evaluate_ranking(
        f"loopnet-verified-{verified.matcher}",
        label,
        "verified",
        verified.ranking,
        dataset,
        submap_of,
        query_ms=np.asarray(retrieval_query_ms, np.float64) + np.asarray(verified.query_ms),
        details=details,
    )


def verification_methods(
    dataset: Dataset,
    submap_of: Sequence[int],
    base: Ranking,
    retrieval_query_ms: Sequence[float],
    *,
    matchers: Sequence[str],
    top: int,
    cache: KeypointCache,
    similarity_threshold: float,
    extractor_label: str,
    ransac_backend: str = "batched",
) -> tuple[list[MethodResult], dict[str, dict[str, dict[str, float]]]]:
    """One verified row per matcher on the same retrieval ranking, and the stage timings."""
    methods: list[MethodResult] = []
    stages: dict[str, dict[str, dict[str, float]]] = {}
    for matcher in matchers:
        config = VerificationConfig(
            matcher=matcher,
            top=top,
            min_inliers=default_min_inliers(matcher),
            ransac=RansacConfig(backend=ransac_backend),
        )
        verified = verify_ranking(
            dataset, base, cache, config, label=f"verify {matcher}: {dataset.name}"
        )
        methods.append(
            verified_method(
                verified,
                dataset,
                submap_of,
                extractor_label=extractor_label,
                retrieval_query_ms=retrieval_query_ms,
                config=config,
                similarity_threshold=similarity_threshold,
            )
        )
        stages[f"verification {MATCHER_LABELS.get(matcher, matcher)}"] = {
            "per candidate (match + RANSAC)": summary(verified.candidate_ms),
            "per query (all verified candidates)": summary(verified.query_ms),
        }
    if cache.extract_ms:
        stages["verification keypoints"] = {"local features (uncached)": summary(cache.extract_ms)}
    return methods, stages
