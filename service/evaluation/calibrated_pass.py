"""Calibrated LoopNet rows: an atlas calibration fitted on the stored references, as the
calibration job fits it, then every query embedded by it and ranked by exact cosine search.

The calibration is fitted by :meth:`Calibration.fit` on :func:`load_calibration_inputs` of the
temporary atlas after the references are stored (never on a query). Ablations on the same
stored features: mean instead of VLAD, whitening off, other fusion weights, and each
calibrated branch alone.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from service.evaluation.datasets import Dataset
from service.evaluation.metrics import Ranking, correct_matrix, rank_by_similarity
from service.evaluation.protocol import MethodResult, evaluate_ranking
from service.evaluation.service_pass import PassResult
from service.ml.calibration import Calibration, CalibrationConfig, FittedCalibration

DEFAULT_CALIBRATION = CalibrationConfig()


@dataclass
class CalibratedBranches:
    """The service row's calibration and the calibrated branches (D_w, R_w) it gives the
    references and the queries: what retrained heads start from, as a retraining job's do."""

    calibration: Calibration
    references: tuple[np.ndarray, np.ndarray]
    queries: tuple[np.ndarray, np.ndarray]


def _query_branches(
    calibration: Calibration, result: PassResult
) -> tuple[np.ndarray, np.ndarray, float]:
    """The queries' calibrated branches and the median embedding milliseconds per frame."""
    times, local, global_ = [], [], []
    for features, r in zip(result.query_local, result.query_vectors[1], strict=True):
        start = time.perf_counter()
        d, g = calibration.branch_vectors([features.descriptors], [features.scores], r[None])
        times.append((time.perf_counter() - start) * 1000.0)
        local.append(d[0])
        global_.append(g[0])
    return np.stack(local), np.stack(global_), float(np.median(times)) if times else 0.0


def _fit(result: PassResult, config: CalibrationConfig) -> FittedCalibration:
    if result.stored_references is None:
        raise RuntimeError("the service pass kept no stored references to calibrate on")
    return Calibration.fit(result.stored_references, config)


def calibrated_methods(
    dataset: Dataset,
    submap_of: Sequence[int],
    extractor: str,
    extractor_label: str,
    result: PassResult,
    *,
    alphas: Sequence[float],
    k: int,
    with_global_only: bool,
    config: CalibrationConfig = DEFAULT_CALIBRATION,
    vectors: dict[str, tuple[np.ndarray, np.ndarray]] | None = None,
    branches: dict[str, CalibratedBranches] | None = None,
) -> list[MethodResult]:
    """The calibrated service row ``loopnet-<extractor>`` and its ablations.

    ``vectors``, when given, receives the references' and queries' unit embeddings of the
    service row (and of ``global-only``) by row name: what the sequence rows score on.
    ``branches``, when given, receives the service row's :class:`CalibratedBranches` by row
    name: what the retrained rows train on.
    """
    n_refs = len(dataset.references)
    ms = result.stage_ms
    fused_extraction = np.add(np.add(ms["decode"], ms["local_features"]), ms["global_features"])[
        n_refs:
    ]
    start = time.perf_counter()
    fitted = _fit(result, config)
    fit_s = time.perf_counter() - start
    calibration = fitted.calibration
    query_local, query_global, embed_ms = _query_branches(calibration, result)

    def rank(
        cal: Calibration,
        refs: tuple[np.ndarray, np.ndarray],
        queries: tuple[np.ndarray, np.ndarray],
    ) -> tuple[Any, float]:
        start = time.perf_counter()
        similarity = cal.fuse(*queries) @ cal.fuse(*refs).T
        ranking = rank_by_similarity(similarity, k)
        return ranking, (time.perf_counter() - start) * 1000.0 / max(len(queries[0]), 1)

    refs = (fitted.local_branch, fitted.global_branch)
    queries = (query_local, query_global)
    if vectors is not None:
        vectors[f"loopnet-{extractor}"] = (calibration.fuse(*refs), calibration.fuse(*queries))
    if branches is not None:
        branches[f"loopnet-{extractor}"] = CalibratedBranches(calibration, refs, queries)
    ranking, search_ms = rank(calibration, refs, queries)
    cosine_top = ranking.scores[:, 0].copy()
    ranking = Ranking(ranking.indices, calibration.score(ranking.scores))
    main_ms = fused_extraction + embed_ms + search_ms
    describe = _describe(fitted, fit_s, embed_ms)
    service_details: dict[str, Any] = {"ranked_by": "harness fit (no service answers)"}
    if result.calibrated is not None:  # the service's own answers after its calibration job
        ranking, cosine_top = result.calibrated.ranking, result.calibrated.cosines
        main_ms = fused_extraction + result.calibrated.query_ms
        service_details = {
            "ranked_by": "service answers after the calibration job (score)",
            "job": result.calibrated.job_metrics,
        }
    right = correct_matrix(ranking, [q.positives for q in dataset.queries])[:, 0]
    main = evaluate_ranking(
        f"loopnet-{extractor}",
        f"LoopNet {extractor_label} calibrated α={config.alpha:g} (service path)",
        "loopnet",
        ranking,
        dataset,
        submap_of,
        query_ms=main_ms,
        details={
            **describe,
            **service_details,
            "score": "calibrated: -log10 P(impostor cosine >= c)",
            "top1_spread": top1_spread(cosine_top, ranking.scores[:, 0], right),
        },
    )
    methods = [main]

    def ablation(
        name: str, label: str, ranking: Any, query_ms: np.ndarray, details: dict[str, Any]
    ) -> MethodResult:
        return evaluate_ranking(
            name, label, "ablation", ranking, dataset, submap_of, query_ms=query_ms, details=details
        )

    for alpha in sorted(alphas, key=lambda a: (a == 1.0, -a)):
        if alpha == config.alpha or (alpha == 0.0 and not with_global_only):
            continue
        variant = calibration.with_alpha(alpha)
        ranking, search_ms = rank(variant, refs, queries)
        if alpha == 0.0 and vectors is not None:
            vectors["global-only"] = (variant.fuse(*refs), variant.fuse(*queries))
        if alpha == 0.0:
            name, label = (
                "global-only",
                f"global only ({result.preset.backbone.name} {result.preset.backbone.pooling}"
                ", whitened, α=0)",
            )
            branch_ms = np.add(ms["decode"], ms["global_features"])[n_refs:]
        elif alpha == 1.0:
            name = f"{extractor}-local-only"
            label = f"local only ({extractor_label} {config.aggregator.upper()}, whitened, α=1)"
            branch_ms = np.add(ms["decode"], ms["local_features"])[n_refs:] + embed_ms
        else:
            name = f"{extractor}-calibrated-alpha{alpha:g}"
            label = f"calibrated {extractor_label} α={alpha:g}"
            branch_ms = fused_extraction + embed_ms
        methods.append(
            ablation(name, label, ranking, branch_ms + search_ms, {"alpha": alpha, **describe})
        )
    ablations = {
        f"{extractor}-mean-calibrated": (
            replace(config, aggregator="mean"),
            f"calibrated {extractor_label} with mean aggregation (whitened) α={config.alpha:g}",
        ),
        f"{extractor}-calibrated-unwhitened": (
            replace(
                config,
                local=replace(config.local, whiten=False),
                global_=replace(config.global_, whiten=False),
            ),
            f"calibrated {extractor_label} {config.aggregator.upper()}, PCA without whitening "
            f"α={config.alpha:g}",
        ),
    }
    for name, (variant_config, label) in ablations.items():
        start = time.perf_counter()
        variant_fit = _fit(result, variant_config)
        variant_fit_s = time.perf_counter() - start
        q_local, q_global, variant_ms = _query_branches(variant_fit.calibration, result)
        ranking, search_ms = rank(
            variant_fit.calibration,
            (variant_fit.local_branch, variant_fit.global_branch),
            (q_local, q_global),
        )
        details = _describe(variant_fit, variant_fit_s, variant_ms)
        methods.append(
            ablation(name, label, ranking, fused_extraction + variant_ms + search_ms, details)
        )
    return methods


def _describe(fitted: FittedCalibration, fit_s: float, embed_ms: float) -> dict[str, Any]:
    cal = fitted.calibration
    return {
        "calibration": cal.config.to_dict(),
        "fit_s": round(fit_s, 3),
        "fit_stages_s": {k: round(v, 3) for k, v in fitted.timings_s.items()},
        "local_dims": cal.local_whitening.dim,
        "global_dims": cal.global_whitening.dim,
        "embed_ms_per_frame": round(embed_ms, 3),
        "fitted_on": "stored reference frames only (no labels, no queries)",
    }


def top1_spread(cosines: np.ndarray, scores: np.ndarray, right: np.ndarray) -> dict[str, Any]:
    """Top-1 cosines and calibrated scores of right and wrong best matches."""

    def stats(values: np.ndarray) -> dict[str, float] | None:
        if len(values) == 0:
            return None
        q = np.quantile(values, [0.1, 0.5, 0.9])
        return {"p10": float(q[0]), "median": float(q[1]), "p90": float(q[2]), "n": len(values)}

    return {
        "cosine": {"right": stats(cosines[right]), "wrong": stats(cosines[~right])},
        "score": {"right": stats(scores[right]), "wrong": stats(scores[~right])},
    }
