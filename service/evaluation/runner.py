"""``run_evaluation``: one dataset, every method, one report (the library call behind
``loopnet eval``).

Methods, all on the same reference/query split and ground truth:

- LoopNet through the service (``AtlasService.ingest_features`` / ``query_features``), once per
  local extractor, at the preset's fusion weight;
- ablations on the same stored vectors: fused at the other alphas, local only (alpha = 1) and
  global only (alpha = 0; the backbone is the same for every extractor, so it is listed once);
- the classical baselines (bag of ORB words; SeqSLAM's single-frame SAD);
- with ``sequence``: ``<method>+seqL`` rows scoring queries in dataset order through the
  service's sequence code (LoopNet per extractor and global only, each on the calibrated and
  the uncalibrated vectors), and full SeqSLAM at the same L.
"""

from __future__ import annotations

import logging
import os
import platform
import shlex
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from service.app.catalog import AtlasService
from service.errors import WeightsUnavailable
from service.evaluation import report as reporting
from service.evaluation.adaptation_pass import PROTOCOL as ADAPT_PROTOCOL
from service.evaluation.adaptation_pass import adaptation_rows
from service.evaluation.baselines import build_baseline
from service.evaluation.baselines.seqslam import full_seqslam
from service.evaluation.calibrated_pass import (
    DEFAULT_CALIBRATION,
    CalibratedBranches,
    calibrated_methods,
)
from service.evaluation.datasets import Dataset, DatasetError, all_images, load_dataset
from service.evaluation.image_check import unreadable_images
from service.evaluation.metrics import rank_by_similarity, summary
from service.evaluation.pairs_pass import observed_pairs_rows, observed_pairs_runs
from service.evaluation.protocol import (
    MethodResult,
    assign_submaps,
    embedding_ranking,
    evaluate_ranking,
)
from service.evaluation.retraining_pass import (
    PROTOCOLS,
    RetrainingRow,
    StartingPoint,
    retraining_rows,
)
from service.evaluation.sequence_pass import dataset_trajectories, sequence_methods
from service.evaluation.served_pass import ServedAnswers, served_method
from service.evaluation.service_pass import ATLAS as SERVICE_ATLAS
from service.evaluation.service_pass import InAtlas, PassResult, run_service_pass
from service.evaluation.verification_pass import (
    KeypointCache,
    subsample_queries,
    verification_methods,
)
from service.jobs.adaptation_config import DEFAULT_METHOD, AdaptMethod
from service.jobs.calibration import MIN_FRAMES as CALIBRATION_MIN_FRAMES
from service.ml.features import FrameFeatures
from service.ml.heads import HeadsConfig, LoopNetHeads
from service.ml.images import decode_image
from service.ml.pair_whitening import PairWhiteningConfig
from service.ml.pipeline import FeaturePipeline, embed_vectors
from service.ml.presets import ModelPreset, resolve_preset
from service.ml.sequences import SequenceSettings

log = logging.getLogger(__name__)

TARGET_MARGIN = 0.10
SPEEDS = SequenceSettings().speeds
UNCALIBRATED = "loopnet-uncalibrated"  # kind of today's service-path row, kept for comparison
EXTRACTOR_LABELS = {"disk": "DISK", "xfeat": "XFeat"}


@dataclass(frozen=True)
class EvalConfig:
    """One evaluation run.

    Attributes:
        dataset: the dataset folder; ``layout`` ``auto`` detects its layout.
        output: the report folder (created).
        tolerance: frame tolerance (traversals, CSV frames); None: 1.
        distance: metres for position ground truth (CSV).
        reference, query: the traversal folders, where auto-detection is not wanted.
        submap_size: consecutive reference frames per submap (datasets without their own).
        preset, long_side, max_keypoints, backbone: the model settings (``resolve_preset``).
        extractors: local extractors, one service pass each; the first is "LoopNet".
        alphas: fusion weights of the ablations.
        baselines: classical baselines to run.
        limit: keep the first ``limit`` reference frames (a quick slice).
        cache_dir: where extracted features are cached (None: ``output/cache``).
        retrain_shots: K values (shots per submap) of the retrained rows; empty: none.
        retrain_protocols: ``map`` and/or ``revisit`` (see ``retraining_pass``).
        retrain_params: retraining job parameters (``TrainingConfig`` fields) other than the
            job's defaults, e.g. ``{"positive_window": 0}`` for an ablation; ``shots`` is K.
        verify: matchers ("mnn", "lightglue") whose geometric verification of the first
            extractor's ranking adds a row each; empty: none.
        verify_top: candidates verified per query.
        ransac_backend: the verification rows' fundamental-matrix RANSAC ("batched",
            "kornia"; the service's ``LOOPNET_RANSAC_BACKEND``).
        query_stride: keep every n-th query only (bounded runs on long datasets).
        sequence: sequence lengths L of the ``+seqL`` rows; empty: none.
        sequence_contrast: the sequence rows' local contrast window (0: whole-map z-scores).
        sequence_seed_frames: newest query frames whose best matches propose candidates (0:
            every frame's, the service's default; 1: the newest frame's own search hits).
        precision: the CNNs' arithmetic (``service.ml.precision``); features cached in one
            precision are reused in another, so give each its own ``cache_dir``.
        served: add a ``loopnet-<extractor>-served`` row per extractor: the queries answered
            as the service serves them (``served_pass``).
        adapt_observe_shots: K values of the pairs protocol (``pairs_pass``: the pairs the
            service's own observe verified, a real adapt job, served before -> after); needs
            ``served``.
        adapt_labelled_shots: the same with the shots labelled as pairs with their partner
            references (the revisit protocol as served).
    """

    dataset: Path
    output: Path
    layout: str = "auto"
    tolerance: int | None = None
    distance: float = 25.0
    reference: str | None = None
    query: str | None = None
    submap_size: int = 5
    preset: str = "default"
    long_side: int | None = None
    max_keypoints: int | None = None
    backbone: str | None = None
    extractors: tuple[str, ...] = ("disk", "xfeat")
    alphas: tuple[float, ...] = (0.0, 0.3, 0.5, 0.7, 1.0)
    baselines: tuple[str, ...] = ("bow-orb", "seqslam-sad")
    limit: int | None = None
    cache_dir: Path | None = None
    examples: int = 6
    k: int = 10
    retrain_shots: tuple[int, ...] = ()
    retrain_protocols: tuple[str, ...] = PROTOCOLS
    retrain_params: dict[str, Any] = field(default_factory=dict)
    adapt_shots: tuple[int, ...] = ()
    adapt_shrinkage: float | None = None
    adapt_method: AdaptMethod = DEFAULT_METHOD
    adapt_observe_shots: tuple[int, ...] = ()
    adapt_labelled_shots: tuple[int, ...] = ()
    command: str = ""
    verify: tuple[str, ...] = ()
    verify_top: int = 5
    ransac_backend: str = "batched"
    query_stride: int = 1
    sequence: tuple[int, ...] = ()
    sequence_contrast: int = 0
    sequence_seed_frames: int = 0
    precision: str = "fp32"
    served: bool = True


@dataclass
class EvalResult:
    report: dict[str, Any]
    methods: list[MethodResult] = field(default_factory=list)
    retraining: list[RetrainingRow] = field(default_factory=list)


def _alpha_label(extractor: str, alpha: float) -> tuple[str, str]:
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


def _loopnet_methods(
    config: EvalConfig,
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
    for alpha in sorted(config.alphas, key=lambda a: (a == 1.0, -a)):
        if alpha == 0.0 and not with_global_only:
            continue
        start = time.perf_counter()
        ranking = embedding_ranking(result.reference_vectors, result.query_vectors, alpha, config.k)
        per_query = (time.perf_counter() - start) * 1000.0 / max(len(dataset.queries), 1)
        branch = "global" if alpha == 0.0 else "local" if alpha == 1.0 else "fused"
        if alpha == 0.0:
            method_name, label = (
                "global-only-uncalibrated",
                f"global only ({result.preset.backbone.name} {result.preset.backbone.pooling}"
                " raw, α=0)",
            )
        else:
            method_name, label = _alpha_label(extractor, alpha)
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


def _served_rows(
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
        rows.append(
            served_method(
                f"loopnet-{extractor}-served+seq{length}",
                f"{label} (as served, observe, L={length})",
                result.served_sequence,
                dataset,
                submap_of,
            )
        )
    return rows


def _baseline_method(
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


def _unit_embeddings(result: PassResult, alpha: float) -> tuple[np.ndarray, np.ndarray]:
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


def _full_seqslam_methods(
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


def _target(methods: Sequence[MethodResult]) -> dict[str, Any]:
    # the calibrated row; today's uncalibrated one where no calibration could be fitted
    loopnet = next((m for m in methods if m.kind == "loopnet"), None) or next(
        m for m in methods if m.kind == UNCALIBRATED
    )
    rivals = [  # single frames against single frames: sequence rows compete among themselves
        m
        for m in methods
        if (m.kind == "baseline" or m.name.startswith("global-only") or "-local-only" in m.name)
        and "+seq" not in m.name
    ]
    if not rivals:
        return {"verdict": "no baseline or single-branch ablation ran", "met": None}
    best = max(rivals, key=lambda m: m.recall[1])
    margin = loopnet.recall[1] - best.recall[1]
    met = margin >= TARGET_MARGIN
    verdict = (
        f"{loopnet.label}: Recall@1 {loopnet.recall[1]:.3f}; best of the baselines and "
        f"single-branch ablations: {best.label} {best.recall[1]:.3f}; margin {margin:+.3f} "
        f"(target ≥ +{TARGET_MARGIN:.2f}): **{'met' if met else 'NOT met'}**."
    )
    return {
        "loopnet": loopnet.name,
        "best_rival": best.name,
        "margin_recall@1": margin,
        "met": met,
        "verdict": verdict,
    }


def _machine() -> dict[str, Any]:
    import kornia

    cpus = os.cpu_count()
    summary_text = (
        f"{platform.machine()} CPU, {cpus} cores visible, torch {torch.__version__} with "
        f"{torch.get_num_threads()} threads, kornia {kornia.__version__}, no GPU"
        if not torch.cuda.is_available()
        else f"{platform.machine()}, CUDA available (not used)"
    )
    return {
        "summary": summary_text,
        "platform": platform.platform(),
        "cpu_count": cpus,
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "python": sys.version.split()[0],
    }


def _working_sizes(
    sizes: Sequence[tuple[int, int]],
    preset: ModelPreset,
    baselines: Sequence[str],
) -> dict[str, Any]:
    distinct: dict[str, int] = {}
    for w, h in sizes:
        distinct[f"{w}x{h}"] = distinct.get(f"{w}x{h}", 0) + 1
    side = preset.local.long_side
    resized = []
    for size in sorted(distinct):
        w, h = (int(v) for v in size.split("x"))
        scale = side / max(w, h)
        direction = "upsampled" if scale > 1 else "downsampled" if scale < 1 else "kept"
        resized.append(f"{size} {direction} to {round(w * scale)}x{round(h * scale)}")
    parts = [
        f"local extractors at long side {side} ({'; '.join(resized)})",
        f"backbone at {preset.backbone.input_size}x{preset.backbone.input_size}",
    ]
    if "bow-orb" in baselines:
        parts.append(f"ORB at long side {side} (grey)")
    if "seqslam-sad" in baselines:
        parts.append("SeqSLAM thumbnails 64x32 (grey, 8-px patch-normalised)")
    return {
        "decoded": ", ".join(f"{k} ({v})" for k, v in sorted(distinct.items())),
        "local_long_side": side,
        "note": "; ".join(parts) + ".",
    }


def adapted_rows(
    config: EvalConfig,
    dataset: Dataset,
    submap_of: Sequence[int],
    first_pass: PassResult,
    calibrated_branches: dict[str, CalibratedBranches],
    methods: Sequence[MethodResult],
) -> list[RetrainingRow]:
    """The adaptation job's rows (revisit pairs, :mod:`adaptation_pass`), from the service row."""
    extractor = first_pass.preset.local.name
    service_row = f"loopnet-{extractor}"
    calibrated_start = calibrated_branches.get(service_row)
    before_row = service_row if calibrated_start is not None else f"{service_row}-uncalibrated"
    before = next(m for m in methods if m.name == before_row)
    return adaptation_rows(
        dataset,
        submap_of,
        first_pass,
        StartingPoint.of(first_pass, before, calibrated_start),
        shots=config.adapt_shots,
        config=PairWhiteningConfig(shrinkage=config.adapt_shrinkage),
        method=config.adapt_method,
        k=config.k,
        extractor_label=EXTRACTOR_LABELS.get(extractor, extractor),
    )


@dataclass
class LoadedData:
    """The dataset a run evaluates, after its slice, stride and unreadable images."""

    dataset: Dataset
    submap_of: list[int]
    submap_note: str
    unreadable: dict[Path, str]
    output: Path
    cache_dir: Path


@dataclass
class EvalRun:
    """What the steps of a run fill in: rows, stage timings, what was skipped and why, the
    extractor passes and what the later rows start from."""

    config: EvalConfig
    data: LoadedData
    methods: list[MethodResult] = field(default_factory=list)
    global_only: list[MethodResult] = field(default_factory=list)
    stages: dict[str, dict[str, dict[str, float]]] = field(default_factory=dict)
    skipped: dict[str, str] = field(default_factory=dict)
    passes: list[PassResult] = field(default_factory=list)
    first_keypoints: KeypointCache | None = None
    calibrated_vectors: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    calibrated_branches: dict[str, CalibratedBranches] = field(default_factory=dict)
    retraining: list[RetrainingRow] = field(default_factory=list)
    observed_pairs: list[dict[str, Any]] = field(default_factory=list)

    @property
    def first_pass(self) -> PassResult:
        """The first extractor's pass: the "LoopNet" rows and every later step start from it."""
        return self.passes[0]

    def report(self, partial: str | None) -> dict[str, Any]:
        data = self.data
        report = _report(
            self.config,
            data.dataset,
            data.submap_note,
            self.first_pass,
            self.methods + self.global_only,
            self.stages,
            self.skipped,
            self.retraining,
            data.unreadable,
            partial,
        )
        report["observed_pairs"] = self.observed_pairs
        return report

    def checkpoint(self, next_step: str) -> None:
        """Write the rows done so far (no plots): a run stopped later keeps them."""
        if self.passes:
            report = self.report(f"stopped before {next_step}")
            output = self.data.output
            reporting.write_json(report, output / "report.json")
            reporting.write_markdown(report, self.methods + self.global_only, output / "report.md")


def run_evaluation(config: EvalConfig) -> EvalResult:
    """Run every method on ``config.dataset`` and write the report into ``config.output``:
    load the data, run one service pass per extractor, add the ablations (retraining,
    adaptation, verification, sequences, baselines), write the report."""
    run = EvalRun(config, load_data(config))
    run_passes(run)
    run_ablations(run)
    return write_report(run)


def load_data(config: EvalConfig) -> LoadedData:
    """The dataset, sliced (``limit``, ``query_stride``), without unreadable images, with the
    protocol's submaps."""
    dataset = load_dataset(
        config.dataset,
        layout=config.layout,
        tolerance=config.tolerance,
        distance=config.distance,
        reference=config.reference,
        query=config.query,
    )
    if config.limit:
        dataset = dataset.head(config.limit)
    dataset = subsample_queries(dataset, config.query_stride)
    output = Path(config.output)
    output.mkdir(parents=True, exist_ok=True)
    cache_dir = config.cache_dir or output / "cache"
    unreadable = unreadable_images(all_images(dataset), cache_dir)
    for path, why in unreadable.items():
        log.warning("skipping %s: %s", path, why)
    dataset = dataset.without(unreadable)
    if not dataset.references or not dataset.queries:
        raise DatasetError(f"{dataset.root}: no readable references or queries left")
    submap_of, submap_note = assign_submaps(dataset, config.submap_size)
    log.info(
        "%s (%s): %d references, %d queries; %s",
        dataset.name,
        dataset.layout,
        len(dataset.references),
        len(dataset.queries),
        dataset.ground_truth,
    )
    return LoadedData(dataset, submap_of, submap_note, unreadable, output, cache_dir)


def run_passes(run: EvalRun) -> None:
    """One service pass per local extractor, with its calibrated, uncalibrated and served rows
    (the calibrated rows need as many references as a calibration job does)."""
    config, data = run.config, run.data
    dataset, submap_of = data.dataset, data.submap_of
    calibrates = len(dataset.references) >= CALIBRATION_MIN_FRAMES
    if not calibrates:
        run.skipped["calibration"] = (
            f"{len(dataset.references)} references; a calibration needs {CALIBRATION_MIN_FRAMES}"
        )
        log.warning("no calibrated rows: %s", run.skipped["calibration"])
    for extractor in tqdm(config.extractors, desc="extractors", unit="pass"):
        first = not run.passes
        preset = resolve_preset(
            config.preset,
            extractor=extractor,
            backbone=config.backbone,
            long_side=config.long_side,
            max_keypoints=config.max_keypoints,
        )
        try:
            pipeline = FeaturePipeline(preset, config.precision)
        except WeightsUnavailable as exc:
            run.skipped[extractor] = str(exc)
            log.warning("skipping %s: %s", extractor, exc)
            continue
        keypoints = None
        if config.verify and first:
            keypoints = KeypointCache(data.output / "keypoints", pipeline.local)
        result = run_service_pass(
            dataset,
            submap_of,
            pipeline,
            k=config.k,
            cache_dir=data.cache_dir,
            label=extractor,
            on_features=keypoints.store if keypoints is not None else None,
            calibration={
                "aggregator": DEFAULT_CALIBRATION.aggregator,
                "words": DEFAULT_CALIBRATION.words,
                "alpha": DEFAULT_CALIBRATION.alpha,
            }
            if calibrates
            else None,
            serve=config.served,
            serve_sequence=max(config.sequence, default=0),
            in_atlas=_observed_pairs_step(config, data) if first else None,
        )
        try:
            calibrated = (
                calibrated_methods(
                    dataset,
                    submap_of,
                    extractor,
                    EXTRACTOR_LABELS.get(extractor, extractor),
                    result,
                    alphas=config.alphas,
                    k=config.k,
                    with_global_only=first,
                    vectors=run.calibrated_vectors,
                    branches=run.calibrated_branches,
                )
                if calibrates
                else []
            )
        except ValueError as exc:  # too few references to fit a calibration (impostor pairs)
            run.skipped[f"{extractor} calibration"] = str(exc)
            log.warning("no calibrated rows for %s: %s", extractor, exc)
            calibrated = []
        uncalibrated = _loopnet_methods(
            config, dataset, submap_of, extractor, result, with_global_only=first
        )
        served = _served_rows(extractor, result, dataset, submap_of)
        for method in calibrated + uncalibrated + served:
            global_row = method.name.startswith("global-only")
            (run.global_only if global_row else run.methods).append(method)
        run.stages[f"LoopNet {EXTRACTOR_LABELS.get(extractor, extractor)}"] = {
            name: summary(values) for name, values in result.stage_ms.items()
        }
        run.passes.append(result)
        if first:
            run.first_keypoints = keypoints
        run.checkpoint("the next extractor's pass")
    if not run.passes:
        raise RuntimeError(f"no local extractor could run: {run.skipped}")
    run.methods += run.global_only
    run.global_only = []


def run_ablations(run: EvalRun) -> None:
    """The rows that start from the passes: retraining and adaptation (the first pass's
    heads), verification, sequences, then the classical baselines."""
    config = run.config
    if config.retrain_shots:
        _retraining_step(run)
        run.checkpoint("verification and baselines")
    if config.adapt_shots:
        run.retraining += adapted_rows(
            config,
            run.data.dataset,
            run.data.submap_of,
            run.first_pass,
            run.calibrated_branches,
            run.methods,
        )
        run.methods += [row.after for row in run.retraining if row.protocol == ADAPT_PROTOCOL]
        run.checkpoint("verification and baselines")
    if run.first_pass.in_atlas:
        extractor = run.first_pass.preset.local.name
        label = f"LoopNet {EXTRACTOR_LABELS.get(extractor, extractor)}"
        for observed in run.first_pass.in_atlas:
            rows, report_row = observed_pairs_rows(
                observed, run.data.dataset, run.data.submap_of, label
            )
            run.methods += rows
            run.observed_pairs.append(report_row)
        run.checkpoint("verification and baselines")
    elif config.adapt_observe_shots or config.adapt_labelled_shots:
        run.skipped["pairs protocol"] = "needs the served pass (--served) and queries"
    if config.verify and run.first_keypoints is not None:
        _verification_step(run, run.first_keypoints)
        run.checkpoint("the baselines")
    if config.sequence:
        _sequence_step(run)
        run.checkpoint("the baselines")
    for name in config.baselines:
        _baseline_step(run, name)
        run.checkpoint("the remaining baselines and the plots")


def write_report(run: EvalRun) -> EvalResult:
    """The full report: report.json, report.md and the plots."""
    report = run.report(None)
    _write_final(run.config, run.data.dataset, run.methods, report)
    return EvalResult(report, run.methods, run.retraining)


def _retraining_step(run: EvalRun) -> None:
    # the heads start from the service row: calibrated when the pass could calibrate
    config, first_pass = run.config, run.first_pass
    extractor = first_pass.preset.local.name
    service_row = f"loopnet-{extractor}"
    calibrated_start = run.calibrated_branches.get(service_row)
    before_row = service_row if calibrated_start is not None else f"{service_row}-uncalibrated"
    before = next(m for m in run.methods if m.name == before_row)
    run.retraining = retraining_rows(
        run.data.dataset,
        run.data.submap_of,
        first_pass,
        StartingPoint.of(first_pass, before, calibrated_start),
        shots=config.retrain_shots,
        protocols=config.retrain_protocols,
        params=config.retrain_params,
        k=config.k,
        extractor_label=EXTRACTOR_LABELS.get(extractor, extractor),
    )
    run.methods += [row.after for row in run.retraining]


def _observed_pairs_step(config: EvalConfig, data: LoadedData) -> InAtlas | None:
    """The pairs protocol on the first pass's atlas (:mod:`pairs_pass`), when asked for."""
    if not config.adapt_observe_shots and not config.adapt_labelled_shots:
        return None

    def run(
        service: AtlasService,
        queries: Sequence[FrameFeatures],
        frame_to_reference: dict[int, int],
        served: ServedAnswers,
    ) -> list[Any]:
        return [
            run
            for source, shots in (
                ("observe", config.adapt_observe_shots),
                ("labelled", config.adapt_labelled_shots),
            )
            for run in observed_pairs_runs(
                service,
                atlas=SERVICE_ATLAS,
                dataset=data.dataset,
                submap_of=data.submap_of,
                queries=queries,
                frame_to_reference=frame_to_reference,
                before=served,
                k=config.k,
                shots=shots,
                source=source,
            )
        ]

    return run


def _verification_step(run: EvalRun, keypoints: KeypointCache) -> None:
    config, first_pass = run.config, run.first_pass
    extractor_name = first_pass.preset.local.name
    verified, verification_stages = verification_methods(
        run.data.dataset,
        run.data.submap_of,
        first_pass.ranking,
        first_pass.query_ms,
        matchers=config.verify,
        top=config.verify_top,
        ransac_backend=config.ransac_backend,
        cache=keypoints,
        similarity_threshold=first_pass.threshold,
        extractor_label=EXTRACTOR_LABELS.get(extractor_name, extractor_name),
    )
    run.methods += verified
    run.stages.update(verification_stages)


def _sequence_step(run: EvalRun) -> None:
    """``+seqL`` rows over each pass's calibrated and uncalibrated rows and the global branch."""
    config = run.config
    bases = []
    rows = {m.name: m for m in run.methods}
    for result in run.passes:
        extractor = result.preset.local.name
        calibrated_row = f"loopnet-{extractor}"
        if calibrated_row in run.calibrated_vectors:
            bases.append((rows[calibrated_row], *run.calibrated_vectors[calibrated_row]))
        bases.append(
            (
                rows[f"{calibrated_row}-uncalibrated"],
                *_unit_embeddings(result, result.preset.alpha),
            )
        )
    if "global-only" in run.calibrated_vectors:
        bases.append((rows["global-only"], *run.calibrated_vectors["global-only"]))
    if "global-only-uncalibrated" in rows:
        bases.append((rows["global-only-uncalibrated"], *_unit_embeddings(run.first_pass, 0.0)))
    run.methods += sequence_methods(
        bases,
        run.data.dataset,
        run.data.submap_of,
        config.sequence,
        config.k,
        SequenceSettings(
            contrast_window=config.sequence_contrast,
            seed_frames=config.sequence_seed_frames,
        ),
    )


def _baseline_step(run: EvalRun, name: str) -> None:
    config, data = run.config, run.data
    method, baseline_stages, similarity = _baseline_method(
        name, run.first_pass.preset.local.long_side, data.dataset, data.submap_of, config.k
    )
    run.methods.append(method)
    run.stages[method.label] = baseline_stages
    if config.sequence and name == "seqslam-sad":
        run.methods += _full_seqslam_methods(
            similarity, method, data.dataset, data.submap_of, config.sequence, config.k
        )


def _report(
    config: EvalConfig,
    dataset: Dataset,
    submap_note: str,
    first_pass: PassResult,
    methods: list[MethodResult],
    stages: dict[str, dict[str, dict[str, float]]],
    skipped: dict[str, str],
    retraining: list[RetrainingRow],
    unreadable: dict[Path, str],
    partial: str | None,
) -> dict[str, Any]:
    """The report of the rows done so far (``partial`` says what is still missing)."""
    answerable = sum(1 for q in dataset.queries if q.positives)
    tolerance_text = (
        f"±{dataset.tolerance} frames" if dataset.tolerance is not None else dataset.ground_truth
    )
    report: dict[str, Any] = {
        "command": config.command or "run_evaluation(...)",
        "partial": partial,
        "config": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(config).items()},
        "dataset": {
            "name": dataset.name,
            "root": str(dataset.root),
            "layout": dataset.layout,
            "references": len(dataset.references),
            "queries": len(dataset.queries),
            "answerable": answerable,
            "ground_truth": dataset.ground_truth,
            "tolerance": dataset.tolerance,
            "tolerance_text": tolerance_text,
            "excluded": dataset.excluded,
            "unreadable_images": {str(path): why for path, why in unreadable.items()},
        },
        "protocol": {
            "submaps": submap_note,
            "submap_size": config.submap_size,
            "predicted_submap": "submap of the best matching frame (classifier untrained)",
            "recall_ks": [1, 5, 10],
        },
        "models": (
            f"local extractors {', '.join(EXTRACTOR_LABELS.get(e, e) for e in config.extractors if e not in skipped)} "
            f"(long side {first_pass.preset.local.long_side}, at most "
            f"{first_pass.preset.local.max_keypoints} keypoints, NMS {first_pass.preset.local.nms_window}); "
            f"global backbone {first_pass.preset.backbone.name} ImageNet "
            f"({first_pass.preset.backbone.pooling} pooling); LoopNet heads untrained "
            "(block-identity fusion)"
        ),
        "skipped": skipped,
        "working_sizes": _working_sizes(
            first_pass.image_sizes, first_pass.preset, config.baselines
        ),
        "machine": _machine(),
        "methods": [m.row() for m in methods],
        "stages": stages,
        "timing_note": (
            "Per-query time of LoopNet rows: decode + CNNs + heads + FAISS search, as the API "
            "spends it (HTTP excluded). Ablations: decode + the branch's CNNs + re-embedding and "
            "exact search. Baselines: decode + describe + scoring. "
            + (
                "CNN timings come from the run that filled the feature cache."
                if any(m.details.get("features_from_cache") for m in methods)
                else "All timings measured in this run."
            )
        ),
        "target": _target(methods),
        "retraining": [row.row() for row in retraining],
    }
    return report


def _write_final(
    config: EvalConfig, dataset: Dataset, methods: list[MethodResult], report: dict[str, Any]
) -> None:
    """The plots, then report.json and report.md in full."""
    output = Path(config.output)
    tolerance_text = report["dataset"]["tolerance_text"]
    title = f"{dataset.name}: loop-closure precision-recall ({tolerance_text})"
    reporting.plot_pr_curves(methods, title, output / reporting.PR_PLOT)
    report["examples"] = reporting.plot_examples(
        dataset, methods[0], output / reporting.EXAMPLES_PLOT, count=config.examples
    )
    reporting.write_json(report, output / "report.json")
    reporting.write_markdown(report, methods, output / "report.md")


def command_line(argv: Sequence[str]) -> str:
    """The `loopnet` command line of a run, as the report records it (argv without "loopnet")."""
    return "loopnet " + " ".join(shlex.quote(a) for a in argv)
