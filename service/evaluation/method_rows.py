"""The harness's rows from one pass's answers: the service's uncalibrated row and its alpha
ablations, the rows as served, the classical baselines and full SeqSLAM (what
:func:`service.evaluation.runner.run_evaluation` puts side by side)."""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from tqdm import tqdm

from service.evaluation.baselines import build_baseline
from service.evaluation.baselines.seqslam import full_seqslam
from service.evaluation.datasets import Dataset
from service.evaluation.metrics import rank_by_similarity, summary
from service.evaluation.protocol import MethodResult, embedding_ranking, evaluate_ranking
from service.evaluation.sequence_pass import dataset_trajectories
from service.evaluation.served_pass import served_method
from service.evaluation.service_pass import PassResult
from service.ml.heads import HeadsConfig, LoopNetHeads
from service.ml.images import decode_image
from service.ml.pipeline import embed_vectors
from service.ml.sequences import SequenceSettings

SPEEDS = SequenceSettings().speeds
UNCALIBRATED = "loopnet-uncalibrated"  # kind of today's service-path row, kept for comparison
EXTRACTOR_LABELS = {"disk": "DISK", "xfeat": "XFeat"}


def alpha_label(extractor: str, alpha: float) -> tuple[str, str]:
    name = EXTRACTOR_LABELS.get(extractor, extractor)
    if alpha == 1.0:
        return (
            f"{extractor}-local-only-uncalibrated",
            f"local only ({name} mean, uncalibrated, α=1)",
        )
    return (
        f"{extractor}-uncalibrated-alpha{alpha:g}",
        f"fused {name} α={alpha:g} (uncalibrated, untrained heads)",
    )


def loopnet_methods(
    alphas: Sequence[float],
    k: int,
    dataset: Dataset,
    submap_of: Sequence[int],
    extractor: str,
    result: PassResult,
    with_global_only: bool,
) -> list[MethodResult]:
    """The service's answers plus the alpha ablations on the same stored vectors."""
    name = EXTRACTOR_LABELS.get(extractor, extractor)
    preset_alpha = result.preset.alpha
    ms = result.stage_ms
    extraction = {
        "local": np.add(ms["decode"], ms["local_features"])[len(dataset.references) :],
        "global": np.add(ms["decode"], ms["global_features"])[len(dataset.references) :],
    }
    extraction["fused"] = (
        extraction["local"] + np.array(ms["global_features"])[len(dataset.references) :]
    )
    service_method = evaluate_ranking(
        f"loopnet-{extractor}-uncalibrated",
        f"LoopNet {name} α={preset_alpha:g} uncalibrated (an atlas before its first calibration)",
        UNCALIBRATED,
        result.ranking,
        dataset,
        submap_of,
        query_ms=result.query_ms,
        details={"features_from_cache": result.cached, "signature": result.signature},
    )
    methods = [service_method]
    for alpha in sorted(alphas, key=lambda a: (a == 1.0, -a)):
        if alpha == 0.0 and not with_global_only:
            continue
        start = time.perf_counter()
        ranking = embedding_ranking(result.reference_vectors, result.query_vectors, alpha, k)
        per_query = (time.perf_counter() - start) * 1000.0 / max(len(dataset.queries), 1)
        branch = "global" if alpha == 0.0 else "local" if alpha == 1.0 else "fused"
        if alpha == 0.0:
            method_name, label = (
                "global-only-uncalibrated",
                f"global only ({result.preset.backbone.name} {result.preset.backbone.pooling}"
                " raw, α=0)",
            )
        else:
            method_name, label = alpha_label(extractor, alpha)
        details: dict[str, Any] = {"alpha": alpha, "features": f"{name} pass"}
        if alpha == preset_alpha:
            agree = float(np.mean(ranking.indices[:, 0] == result.ranking.indices[:, 0]))
            service_method.details["top1_agreement_with_ablation_path"] = agree
            if alpha != 0.0:  # the global branch alone keeps its row: what LoopNet must beat
                continue
        methods.append(
            evaluate_ranking(
                method_name,
                label,
                "ablation",
                ranking,
                dataset,
                submap_of,
                query_ms=extraction[branch] + per_query,
                details=details,
            )
        )
    return methods


def served_rows(
    extractor: str, result: PassResult, dataset: Dataset, submap_of: Sequence[int]
) -> list[MethodResult]:
    """The extractor's rows as served: anonymous queries, and one robot's observations with
    sequences when the pass ran them."""
    label = f"LoopNet {EXTRACTOR_LABELS.get(extractor, extractor)}"
    rows = []
    if result.served is not None:
        rows.append(
            served_method(
                f"loopnet-{extractor}-served",
                f"{label} (as served)",
                result.served,
                dataset,
                submap_of,
            )
        )
    if result.served_sequence is not None:
        length = result.served_sequence.sequence_length
        every = result.served_sequence.adapt_after_pairs
        adapting = f", adapting every {every} pairs" if every else ""
        rows.append(
            served_method(
                f"loopnet-{extractor}-served+seq{length}",
                f"{label} (as served, observe, L={length}{adapting})",
                result.served_sequence,
                dataset,
                submap_of,
            )
        )
    return rows


def baseline_method(
    name: str, long_side: int, dataset: Dataset, submap_of: Sequence[int], k: int
) -> tuple[MethodResult, dict[str, dict[str, float]], np.ndarray]:
    baseline = build_baseline(name, long_side)
    describe_ms: list[float] = []
    described = []
    paths = [r.path for r in dataset.references] + [q.path for q in dataset.queries]
    for path in tqdm(paths, desc=f"{name}: {dataset.name}", unit="img", leave=False):
        start = time.perf_counter()
        described.append(baseline.describe(decode_image(path.read_bytes())))
        describe_ms.append((time.perf_counter() - start) * 1000.0)
    n_refs = len(dataset.references)
    start = time.perf_counter()
    baseline.fit(described[:n_refs])
    fit_ms = (time.perf_counter() - start) * 1000.0
    start = time.perf_counter()
    similarity = baseline.score(described[n_refs:])
    ranking = rank_by_similarity(similarity, k)
    score_ms = (time.perf_counter() - start) * 1000.0 / max(len(dataset.queries), 1)
    method = evaluate_ranking(
        name,
        baseline.label,
        "baseline",
        ranking,
        dataset,
        submap_of,
        query_ms=np.array(describe_ms[n_refs:]) + score_ms,
        details={"settings": baseline.settings(), "fit_ms": fit_ms},
    )
    stages = {
        "decode + describe": summary(describe_ms),
        "score vs all references (per query)": {"median": score_ms, "p95": score_ms, "n": 1},
    }
    return method, stages, similarity


def unit_embeddings(result: PassResult, alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """References' and queries' embeddings by untrained heads at ``alpha`` (the service's)."""
    heads = LoopNetHeads(
        HeadsConfig(
            local_dim=result.reference_vectors[0].shape[1],
            global_dim=result.reference_vectors[1].shape[1],
            alpha=alpha,
        )
    ).eval()
    return embed_vectors(heads, *result.reference_vectors), embed_vectors(
        heads, *result.query_vectors
    )


SEQSLAM_VARIANTS = (
    ("", "SeqSLAM full (contrast enhancement, window 10, + sequence search)", 10),
    ("-raw", "SeqSLAM sequence search on raw SAD (no contrast enhancement)", None),
)


def full_seqslam_methods(
    similarity: np.ndarray,
    single: MethodResult,
    dataset: Dataset,
    submap_of: Sequence[int],
    lengths: Sequence[int],
    k: int,
) -> list[MethodResult]:
    """Full SeqSLAM on the SAD baseline's thumbnails (OpenSeqSLAM's enhancement window, and
    without it), one row per variant and L."""
    _, query_starts = dataset_trajectories(dataset)
    rows = []
    for suffix, label, window in SEQSLAM_VARIANTS:
        for length in lengths:
            start = time.perf_counter()
            scores = full_seqslam(-similarity, length, window=window, query_starts=query_starts)
            per_query = (time.perf_counter() - start) * 1000.0 / max(len(dataset.queries), 1)
            rows.append(
                evaluate_ranking(
                    f"{single.name}{suffix}+seq{length}",
                    f"{label} L={length}",
                    "baseline",
                    rank_by_similarity(scores, k),
                    dataset,
                    submap_of,
                    query_ms=np.full(len(dataset.queries), per_query),
                    details={"length": length, "window": window, "speeds": list(SPEEDS)},
                )
            )
    return rows
