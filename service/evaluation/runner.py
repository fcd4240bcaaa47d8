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

This module loads the data and runs the service passes; the rows that start from them are
:mod:`service.evaluation.ablation_steps`, the run's state :mod:`service.evaluation.eval_run`.
"""

from __future__ import annotations

import logging
import shlex
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tqdm import tqdm

from service.app.catalog import AtlasService
from service.errors import WeightsUnavailable
from service.evaluation import report as reporting
from service.evaluation.ablation_steps import run_ablations
from service.evaluation.calibrated_pass import (
    DEFAULT_CALIBRATION,
    calibrated_methods,
)
from service.evaluation.datasets import Dataset, DatasetError, all_images, load_dataset
from service.evaluation.eval_config import EvalConfig
from service.evaluation.eval_run import EvalRun, LoadedData
from service.evaluation.image_check import unreadable_images
from service.evaluation.method_rows import (
    EXTRACTOR_LABELS,
    loopnet_methods,
    served_rows,
)
from service.evaluation.metrics import summary
from service.evaluation.pairs_pass import observed_pairs_runs
from service.evaluation.protocol import (
    MethodResult,
    assign_submaps,
)
from service.evaluation.retraining_pass import (
    RetrainingRow,
)
from service.evaluation.served_pass import ServedAnswers
from service.evaluation.service_pass import ATLAS as SERVICE_ATLAS
from service.evaluation.service_pass import InAtlas, run_service_pass
from service.evaluation.verification_pass import (
    KeypointCache,
    subsample_queries,
)
from service.jobs.calibration import MIN_FRAMES as CALIBRATION_MIN_FRAMES
from service.ml.features import FrameFeatures
from service.ml.pipeline import FeaturePipeline
from service.ml.presets import resolve_preset

log = logging.getLogger(__name__)


@dataclass
class EvalResult:
    report: dict[str, Any]
    methods: list[MethodResult] = field(default_factory=list)
    retraining: list[RetrainingRow] = field(default_factory=list)


def run_evaluation(config: EvalConfig) -> EvalResult:
    """Run every method on ``config.dataset`` and write the report into ``config.output``:
    load the data, run one service pass per extractor, add the ablations (retraining,
    adaptation, verification, sequences, baselines), write the report."""
    run = EvalRun(config, load_data(config))
    run_passes(run)
    run_ablations(run)
    return writereport_of(run)


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
        uncalibrated = loopnet_methods(
            config.alphas, config.k, dataset, submap_of, extractor, result, with_global_only=first
        )
        served = served_rows(extractor, result, dataset, submap_of)
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


def writereport_of(run: EvalRun) -> EvalResult:
    """The full report: report.json, report.md and the plots."""
    report = run.report(None)
    _write_final(run.config, run.data.dataset, run.methods, report)
    return EvalResult(report, run.methods, run.retraining)


def _observed_pairs_step(config: EvalConfig, data: LoadedData) -> InAtlas | None:
    """The pairs protocol on the first pass's atlas (:mod:`pairs_pass`), when asked for."""
    if not (
        config.adapt_observe_shots or config.adapt_labelled_shots or config.adapt_stream_percents
    ):
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
                ("stream", config.adapt_stream_percents),
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
