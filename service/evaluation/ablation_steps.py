"""The rows of a ``loopnet eval`` run that start from its service passes: retraining and
adaptation (from the first pass's heads), the pairs protocol's rows, verification, sequences,
then the classical baselines."""

from __future__ import annotations

from service.evaluation.adaptation_pass import PROTOCOL as ADAPT_PROTOCOL
from service.evaluation.adaptation_pass import adaptation_rows
from service.evaluation.eval_run import EvalRun
from service.evaluation.method_rows import (
    EXTRACTOR_LABELS,
    baseline_method,
    full_seqslam_methods,
    unit_embeddings,
)
from service.evaluation.pairs_pass import observed_pairs_rows
from service.evaluation.retraining_pass import StartingPoint, retraining_rows
from service.evaluation.sequence_pass import sequence_methods
from service.evaluation.verification_pass import KeypointCache, verification_methods
from service.ml.pair_whitening import PairWhiteningConfig
from service.ml.sequences import SequenceSettings


def run_ablations(run: EvalRun) -> None:
    """The rows that start from the passes: retraining and adaptation (the first pass's
    heads), verification, sequences, then the classical baselines."""
    config = run.config
    if config.retrain_shots:
        _retraining_step(run)
        run.checkpoint("verification and baselines")
    if config.adapt_shots:
        _adaptation_step(run)
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
    elif config.adapt_observe_shots or config.adapt_labelled_shots or config.adapt_stream_percents:
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


def starting_point(run: EvalRun) -> StartingPoint:
    """What retrained and adapted heads start from: the first pass's service row, calibrated
    when the pass could calibrate."""
    first_pass = run.first_pass
    service_row = f"loopnet-{first_pass.preset.local.name}"
    calibrated_start = run.calibrated_branches.get(service_row)
    before_row = service_row if calibrated_start is not None else f"{service_row}-uncalibrated"
    before = next(m for m in run.methods if m.name == before_row)
    return StartingPoint.of(first_pass, before, calibrated_start)


def _retraining_step(run: EvalRun) -> None:
    config, first_pass = run.config, run.first_pass
    extractor = first_pass.preset.local.name
    run.retraining = retraining_rows(
        run.data.dataset,
        run.data.submap_of,
        first_pass,
        starting_point(run),
        shots=config.retrain_shots,
        protocols=config.retrain_protocols,
        params=config.retrain_params,
        k=config.k,
        extractor_label=EXTRACTOR_LABELS.get(extractor, extractor),
    )
    run.methods += [row.after for row in run.retraining]


def _adaptation_step(run: EvalRun) -> None:
    """The adaptation job's rows (revisit pairs, :mod:`adaptation_pass`), from the service row."""
    config, first_pass = run.config, run.first_pass
    extractor = first_pass.preset.local.name
    run.retraining += adaptation_rows(
        run.data.dataset,
        run.data.submap_of,
        first_pass,
        starting_point(run),
        shots=config.adapt_shots,
        config=PairWhiteningConfig(shrinkage=config.adapt_shrinkage),
        method=config.adapt_method,
        k=config.k,
        extractor_label=EXTRACTOR_LABELS.get(extractor, extractor),
    )


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
                *unit_embeddings(result, result.preset.alpha),
            )
        )
    if "global-only" in run.calibrated_vectors:
        bases.append((rows["global-only"], *run.calibrated_vectors["global-only"]))
    if "global-only-uncalibrated" in rows:
        bases.append((rows["global-only-uncalibrated"], *unit_embeddings(run.first_pass, 0.0)))
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
    method, baseline_stages, similarity = baseline_method(
        name, run.first_pass.preset.local.long_side, data.dataset, data.submap_of, config.k
    )
    run.methods.append(method)
    run.stages[method.label] = baseline_stages
    if config.sequence and name == "seqslam-sad":
        run.methods += full_seqslam_methods(
            similarity, method, data.dataset, data.submap_of, config.sequence, config.k
        )
