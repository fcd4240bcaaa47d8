"""An adaptation job (kind ``adapt``): learn from the atlas's revisit pairs, gate, publish.

The pairs (verified closures ``observe`` recorded and operator-labelled ones, chosen by robot,
time and submap) give a learned whitening of the fused input (:mod:`service.ml.adaptation`),
fine-tuned with a listwise loss over the pairs when the job's method says so
(:mod:`service.ml.pair_loss`), folded into heads over the active calibration's branches. The not-worse gate compares it with
the active version on held-out pairs and held-out stretches; a version that is worse is kept
but not activated (unless ``retrain_activate_worse``), and the job's message gives the gain it
found, or says it found none. A job without enough usable pairs is refused with the reason.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from service.app import model_versions as models_store
from service.app.revisit_pairs import pair_frames
from service.index.builder import load_model_inputs
from service.jobs.adaptation_config import METHOD_TEXT
from service.jobs.adaptation_config import AdaptConfig as AdaptConfig
from service.ml.active_model import ActiveModel
from service.ml.adaptation import NoUsefulPairs, adapt_heads
from service.ml.pair_loss import PairLossConfig
from service.ml.pair_whitening import PairWhiteningConfig
from service.ml.training import TrainingCancelled, TrainingData
from service.storage import jobs
from service.storage import repository as repo

if TYPE_CHECKING:
    from service.jobs.retraining import JobRunner


def run_adaptation(
    runner: JobRunner, job_id: int, atlas_id: int, params: dict[str, Any], files: list[Any]
) -> int:
    """Fit, gate, publish; returns the new model version (active or not)."""
    config = AdaptConfig(**params)
    runner._progress(job_id, 1, "loading stored features and revisit pairs")
    with runner.sessions() as session:
        active = repo.active_model_version(session, atlas_id=atlas_id)
        active_heads = models_store.load_heads(active, runner.settings.models_dir)
        active_config = models_store.VersionConfig.of(active)
        calibration = models_store.load_calibration(active, runner.settings.models_dir)
        stored = load_model_inputs(session, atlas_id, calibration)
        chosen = pair_frames(session, atlas_id=atlas_id, where=config.pair_filter())
    row_of = {int(frame): i for i, frame in enumerate(stored.ids)}
    found = [(p, row_of[a], row_of[b]) for p, a, b in chosen if a in row_of and b in row_of]
    pair_ids = np.array([p for p, _, _ in found], np.int64)
    pairs = np.array([(a, b) for _, a, b in found], np.int64).reshape(-1, 2)
    data = TrainingData(
        stored.local, stored.global_, stored.submaps, stored.ids, np.asarray(stored.robots)
    )
    runner._progress(job_id, 10, f"{METHOD_TEXT[config.method]}: {len(pairs)} pairs")
    result = adapt_heads(
        data,
        pairs,
        active_heads,
        PairWhiteningConfig(config.shrinkage, config.max_dims),
        window=config.window,
        min_pairs=config.min_pairs,
        whiten=config.whitens,
        pair_loss=PairLossConfig() if config.trains_on_pairs else None,
        active_trained=in_ranges(pair_ids, (active_config.training or {}).get(TRAINED_PAIRS)),
    )
    gate = result.gate
    activate = gate["not_worse"] or runner.settings.retrain_activate_worse
    with runner.sessions() as session:
        if jobs.get_job(session, job_id=job_id).cancel_requested:
            raise TrainingCancelled("cancelled after fitting")
    version, weights, version_calibration = runner.write_version_files(
        job_id,
        atlas_id,
        result.heads,
        calibration,
        active_config,
        files,
        progress=40,
        impostor_refit=result.impostor_refit,
    )
    metrics: dict[str, Any] = {**result.metrics, "held_out": gate, "activated": activate}
    if activate:
        runner._progress(job_id, 50, f"re-embedding {len(stored)} frames from stored features")
        model = ActiveModel(result.heads, calibration)
        metrics.update(runner._reembed(job_id, atlas_id, version, model, len(stored), files))
    runner.publish(
        job_id,
        atlas_id,
        models_store.VersionConfig(
            result.heads.config,
            trained=True,
            training={
                "adapt": params,
                "method": METHOD_TEXT[config.method],
                TRAINED_PAIRS: id_ranges(pair_ids, result.trained_rows),
            },
            job_id=job_id,
            calibration=version_calibration,
        ),
        metrics,
        weights_path=str(weights.relative_to(runner.settings.models_dir)),
        activate=activate,
        message=f"model version {version} {verdict(gate, activate)}",
    )
    return version


TRAINED_PAIRS = "trained_pairs"  # a version's training record: the pair ids it learned from


def id_ranges(ids: np.ndarray, rows: np.ndarray) -> list[list[int]]:
    """``ids[rows]`` as ``[first, last]`` ranges, one per run of consecutive rows (a job's
    training pairs are whole blocks of the pairs in recording order: a few ranges)."""
    rows = np.sort(np.asarray(rows, np.int64))
    if len(rows) == 0:
        return []
    breaks = np.flatnonzero(np.diff(rows) != 1)
    starts, ends = np.r_[rows[0], rows[breaks + 1]], np.r_[rows[breaks], rows[-1]]
    return [[int(ids[a]), int(ids[b])] for a, b in zip(starts, ends, strict=True)]


def in_ranges(ids: np.ndarray, ranges: list[list[int]] | None) -> np.ndarray | None:
    """Per id, whether it lies in one of ``ranges`` (None: no record, e.g. a calibrated
    version, which learned from no pair). A pair recorded inside a range that the job's
    choice left out counts as learned from: it then trains, it is never wrongly judged on."""
    if ranges is None:
        return None
    inside = np.zeros(len(ids), bool)
    for first, last in ranges:
        inside |= (ids >= first) & (ids <= last)
    return inside


def verdict(gate: dict[str, Any], activated: bool) -> str:
    """One line: the gain on held-out pairs, or that there was none, and what became of it."""
    if gate["change"] is None:
        found = "no held-out pairs to measure a gain on"
    else:
        gain = "a gain" if gate["change"] > 0 else "no gain" if gate["change"] == 0 else "a loss"
        found = (
            f"{gain}: held-out pairs ({gate['pairs']}) find their partner first "
            f"{gate['active']:.3f} -> {gate['new']:.3f}"
        )
    if activated:
        return f"is active ({found})" if gate["not_worse"] else f"is active, forced ({found})"
    why = (
        f"worse on held-out pairs{_what_fell(gate)}"
        if not gate["pairs_not_worse"]
        else "worse on the atlas's held-out stretches"
    )
    return f"was not activated: {why} ({found})"


def _what_fell(gate: dict[str, Any]) -> str:
    """Which of the held-out pairs' scores fell besides the one :func:`verdict` quotes."""
    fell = [
        f"{label} {gate[name + '_active']:.3f} -> {gate[name + '_new']:.3f}"
        for name, label in (
            ("mrr", "mean reciprocal rank"),
            ("separated", "found above every wrong first answer"),
        )
        if gate.get(name + "_new") is not None and gate[name + "_new"] < gate[name + "_active"]
    ]
    return f": {'; '.join(fell)}" if fell else ""


__all__ = ["AdaptConfig", "NoUsefulPairs", "run_adaptation", "verdict"]
