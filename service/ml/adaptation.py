"""Adaptation from revisit pairs: learned whitening of the fused input, judged on held-out pairs.

What an ``adapt`` job (service/jobs/adaptation.py) and the harness's revisit rows both run:

1. the pairs are split into training pairs and held-out pairs (whole blocks of them, in the
   order they were recorded: neighbouring pairs of one drive are near-copies of each other;
   never a pair the active version learned from);
2. a :class:`PairWhitening` is fitted on every frame of the atlas and the training pairs
   (optionally fine-tuned with a listwise loss over them, :mod:`service.ml.pair_loss`), and
   folded into heads over the same branches (:func:`fold_into_heads`);
3. the not-worse gate compares the active and the new heads on the held-out pairs (each side
   of a pair ranks every atlas frame but its own neighbourhood; right: the other side or its
   neighbourhood) and on the atlas's held-out stretches (:func:`compare_on_held_out`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, NamedTuple

import numpy as np

from service.ml.calibration_config import ImpostorProbe
from service.ml.heads import HeadsConfig, LoopNetHeads
from service.ml.held_out import HELD_OUT_SHARE, compare_on_held_out, split_for_job
from service.ml.pair_loss import PairLossConfig, Places, fine_tune, identity_start
from service.ml.pair_whitening import (
    PairWhitening,
    PairWhiteningConfig,
    fold_into_heads,
    fused_inputs,
    pair_differences,
)
from service.ml.pipeline import embed_vectors
from service.ml.retrained_impostors import ProbeRefit
from service.ml.training import TrainingData

HELD_OUT_BLOCKS = 10  # pairs are cut into this many blocks in order; held out: every 5th
MIN_HELD_OUT = 1  # a job with fewer held-out pairs than this gates on stretches only
BLOCK_VALUES = 1 << 24  # similarities held at once: judged frames x atlas


class NoUsefulPairs(ValueError):
    """An adaptation refused before it changed anything; the message says why, in one line."""


@dataclass
class AdaptationResult:
    """The adapted heads, the whitening folded into them, the gate's verdict and figures, and
    ``impostor_refit``: the same fit without an impostor probe's held-out frames, which the
    version's impostor model is refitted with (its score must not call a query's impostors
    rarer than they are). ``trained_rows``: the given pairs the fit learned from (a later
    job must not judge this version on them)."""

    heads: LoopNetHeads
    whitening: PairWhitening
    gate: dict[str, Any]
    metrics: dict[str, Any]
    impostor_refit: ProbeRefit
    trained_rows: np.ndarray


def probe_refit(
    base: HeadsConfig,
    differences: np.ndarray,
    pair_ids: np.ndarray,
    config: PairWhiteningConfig,
    *,
    whiten: bool = True,
    tune: Callable[[PairWhitening, np.ndarray], PairWhitening] | None = None,
) -> ProbeRefit:
    """Heads fitted as :func:`adapt_heads` fits them (the training pairs' ``differences``,
    ``pair_ids`` their frames' ids; ``whiten`` False: the centred input; ``tune``: the same
    loss steps on the result, over the pairs kept), on the probe's frames but those it held
    out, and on the training pairs but those holding one of them: the learned whitening
    decorrelates the atlas's frames and whitens out its pairs' differences, so with either in
    the fit the probe's held-out frames would look as orthogonal as stored ones (or their
    partners as close as trained pairs), and the score would call wrong matches rarer than
    they are. When every pair holds a held-out frame, all are kept (nothing else to fit)."""
    pair_ids = np.asarray(pair_ids, np.int64).reshape(-1, 2)

    def refit(probe: ImpostorProbe, probe_ids: np.ndarray) -> LoopNetHeads:
        inputs = fused_inputs(base, probe.local_branch, probe.global_branch)
        seen = inputs if probe.held is None else inputs[~probe.held]
        kept = np.ones(len(pair_ids), bool)
        if probe.held is not None:
            held_ids = np.asarray(probe_ids)[probe.held]
            kept = np.asarray(~np.isin(pair_ids, held_ids).any(axis=1), bool)
            if not kept.any():
                kept[:] = True
        start = fitted_start(seen, differences[kept], config, whiten)
        return fold_into_heads(base, start if tune is None else tune(start, kept))

    return refit


def fitted_start(
    frames: np.ndarray, differences: np.ndarray, config: PairWhiteningConfig, whiten: bool
) -> PairWhitening:
    """What the adaptation starts from (and the loss, if any, tunes): the learned whitening of
    ``frames`` and the pairs' ``differences``, or with ``whiten`` False the centred input."""
    if whiten:
        return PairWhitening.fit_differences(frames, differences, config)
    return identity_start(frames, len(differences))


def split_pairs(
    count: int, share: float = HELD_OUT_SHARE, trained: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Indices of training and held-out pairs among ``count`` recorded in order: about
    ``share`` of them held out, as evenly spaced whole blocks. ``trained`` (bool per pair):
    pairs the active version learned from, never held out (the gate would judge it on its
    own training pairs); the blocks are cut from the others."""
    fresh = np.arange(count) if trained is None else np.flatnonzero(~np.asarray(trained, bool))
    if len(fresh) < 2:
        return np.arange(count), np.zeros(0, dtype=np.int64)
    blocks = np.minimum(np.arange(len(fresh)) * HELD_OUT_BLOCKS // len(fresh), HELD_OUT_BLOCKS - 1)
    every = max(2, round(1 / share))
    held = fresh[(blocks % every) == every // 2]
    return np.setdiff1d(np.arange(count), held), held


class PairScores(NamedTuple):
    """How well each side of held-out pairs finds the other (each in [0, 1])."""

    recall: float  # its partner (or the partner's neighbourhood) ranked first
    mrr: float  # mean reciprocal rank of the first right frame
    # found first with a similarity above every wrong first answer: what a loop decision on
    # the similarity could accept with no false loop (recall at 100% precision)
    separated: float


def separated_share(best: np.ndarray, right: np.ndarray) -> float:
    """Share of askers whose first answer is right and more similar than every wrong first
    answer (``best``: each asker's first answer's similarity, ``right``: whether it is right)."""
    if len(best) == 0:
        return 0.0
    wrong = best[~right]
    bar = wrong.max() if len(wrong) else -np.inf
    return float(np.mean(right & (best > bar)))


def pair_scores(
    embeddings: np.ndarray, data: TrainingData, pairs: np.ndarray, window: int
) -> PairScores:
    """:class:`PairScores` of each side of ``pairs`` finding the other: every frame is ranked
    but the asking frame's own neighbourhood (same robot within ``window`` frames); right: the
    other side, or a frame of its robot within ``window`` of it."""
    codes, rank, _ = data.sequence
    askers = np.concatenate([pairs[:, 0], pairs[:, 1]])
    partners = np.concatenate([pairs[:, 1], pairs[:, 0]])
    block = max(1, BLOCK_VALUES // max(len(embeddings), 1))
    reciprocal = 0.0
    best, first_right = [], []
    for start in range(0, len(askers), block):
        ask, partner = askers[start : start + block], partners[start : start + block]
        similarity = embeddings[ask] @ embeddings.T
        own = (codes[None, :] == codes[ask, None]) & (
            np.abs(rank[None, :] - rank[ask, None]) <= window
        )
        similarity[own] = -np.inf
        right = (codes[None, :] == codes[partner, None]) & (
            np.abs(rank[None, :] - rank[partner, None]) <= window
        )
        right &= ~own
        best_right = np.where(right, similarity, -np.inf).max(axis=1)
        better = (similarity > best_right[:, None]).sum(axis=1)
        reciprocal += float(np.sum(1.0 / (better + 1)))
        best.append(similarity.max(axis=1))
        first_right.append(better == 0)
    hits = np.concatenate(first_right)
    return PairScores(
        float(np.mean(hits)),
        reciprocal / len(askers),
        separated_share(np.concatenate(best), hits),
    )


def compare_on_pairs(
    active: LoopNetHeads, new: LoopNetHeads, data: TrainingData, pairs: np.ndarray, window: int
) -> dict[str, Any]:
    """:func:`pair_scores` of both heads; not worse when none of the scores falls (the
    separated share guards the loop decision, which a better ranking alone can lower)."""
    if len(pairs) < MIN_HELD_OUT:
        return {"pairs": 0, "active": None, "new": None, "change": None, "not_worse": True}
    before = pair_scores(embed_vectors(active, data.local, data.global_), data, pairs, window)
    after = pair_scores(embed_vectors(new, data.local, data.global_), data, pairs, window)
    return {
        "pairs": int(len(pairs)),
        "active": round(before.recall, 4),
        "new": round(after.recall, 4),
        "change": round(after.recall - before.recall, 4),
        "mrr_active": round(before.mrr, 4),
        "mrr_new": round(after.mrr, 4),
        "separated_active": round(before.separated, 4),
        "separated_new": round(after.separated, 4),
        "not_worse": bool(all(b <= a for b, a in zip(before, after, strict=True))),
    }


def adapt_heads(
    data: TrainingData,
    pairs: np.ndarray,
    active: LoopNetHeads,
    config: PairWhiteningConfig,
    *,
    window: int = 2,
    min_pairs: int = 10,
    held_out_pairs: np.ndarray | None = None,
    whiten: bool = True,
    pair_loss: PairLossConfig | None = None,
    active_trained: np.ndarray | None = None,
) -> AdaptationResult:
    """Fit a learned whitening on ``data`` (the active version's branch inputs of every atlas
    frame) and ``pairs`` (``P x 2`` row indices), fold it into heads, and gate them against
    ``active`` (the heads serving now). ``held_out_pairs``: which pairs judge (None: whole
    blocks of them, :func:`split_pairs`, never one of ``active_trained``, bool per pair: those
    the active version learned from). ``whiten`` False starts from the centred input;
    ``pair_loss`` set fine-tunes the start on the training pairs (:mod:`service.ml.pair_loss`),
    stopping early on whole blocks of them kept out of the loss."""
    started = time.perf_counter()
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    base = active.config
    inputs = fused_inputs(base, data.local, data.global_)
    # a pair of identical vectors (the same image twice) says nothing about a change of view
    usable = np.flatnonzero(np.any(inputs[pairs[:, 0]] != inputs[pairs[:, 1]], axis=1))
    pairs = pairs[usable]
    if len(pairs) < min_pairs:
        raise NoUsefulPairs(
            f"only {len(pairs)} usable revisit pair(s) match the job's choice; adaptation needs "
            f"at least {min_pairs} (closures observe kept: verified or its sequence's loops; "
            "or labelled pairs)"
        )
    trained_rows = usable
    if held_out_pairs is None:
        seen = None if active_trained is None else np.asarray(active_trained, bool)[usable]
        train_idx, held_idx = split_pairs(len(pairs), trained=seen)
        train, held = pairs[train_idx], pairs[held_idx]
        trained_rows = usable[train_idx]
    else:
        train, held = pairs, np.asarray(held_out_pairs, np.int64).reshape(-1, 2)

    def start_from(chosen: np.ndarray) -> PairWhitening:
        return fitted_start(inputs, pair_differences(inputs, chosen), config, whiten)

    differences = pair_differences(inputs, train)
    whitening = fitted_start(inputs, differences, config, whiten)
    tuned: dict[str, Any] = {}
    repeat: Callable[[PairWhitening, np.ndarray], PairWhitening] | None = None
    if pair_loss is not None:
        whitening, tuned, repeat = tune_on_pairs(
            inputs, whitening, start_from, data, train, window, pair_loss
        )
    heads = fold_into_heads(base, whitening)
    fit_seconds = time.perf_counter() - started
    pairs_gate = compare_on_pairs(active, heads, data, held, window)
    stretches = split_for_job(data, 1).held_out
    # a second robot's frame finding the first robot's frames of its place is right there
    stretch_gate = compare_on_held_out(active, heads, data, stretches, window, same_place=pairs)
    gate = {
        **pairs_gate,
        "pairs_not_worse": pairs_gate["not_worse"],
        "stretches": stretch_gate,
        "not_worse": bool(pairs_gate["not_worse"] and stretch_gate["not_worse"]),
    }
    metrics = {
        "pairs": int(len(pairs)),
        "training_pairs": int(len(train)),
        "held_out_pairs": int(len(held)),
        "frames": int(len(data.submaps)),
        "shrinkage": round(whitening.shrinkage, 4),
        "dim": whitening.dim,
        **tuned,
        "fit_seconds": round(fit_seconds, 3),
        "gate_seconds": round(time.perf_counter() - started - fit_seconds, 3),
    }
    pair_ids = np.asarray(data.frame_ids)[train]
    refit = probe_refit(base, differences, pair_ids, config, whiten=whiten, tune=repeat)
    return AdaptationResult(heads, whitening, gate, metrics, refit, trained_rows)


def tune_on_pairs(
    inputs: np.ndarray,
    start: PairWhitening,
    start_from: Callable[[np.ndarray], PairWhitening],
    data: TrainingData,
    train: np.ndarray,
    window: int,
    config: PairLossConfig,
) -> tuple[
    PairWhitening, dict[str, Any], Callable[[PairWhitening, np.ndarray], PairWhitening] | None
]:
    """:func:`fine_tune` ``start`` (fitted on every training pair) for as many steps as a run
    on whole blocks of them, started from ``start_from`` those blocks and stopped early on the
    rest (their mean reciprocal rank, as the gate scores pairs), found best. Too few pairs to
    split, or no step helped: ``start``. Also returns how to repeat the kept steps from another
    start over a subset of the training pairs (a mask; None when no step was kept), for
    :func:`probe_refit`."""
    fit_idx, stop_idx = split_pairs(len(train))
    if len(stop_idx) == 0:
        return start, {"pair_loss_steps": 0}, None
    codes, rank, _ = data.sequence
    places = Places(codes, rank, window)
    stop = train[stop_idx]
    trial = fine_tune(
        inputs,
        start_from(train[fit_idx]),
        train[fit_idx],
        places,
        lambda embedded: pair_scores(embedded, data, stop, window).mrr,
        config,
    )
    steps = int(trial.metrics["pair_loss_best_step"])
    metrics = {f"{name}_trial": value for name, value in trial.metrics.items()}
    if steps == 0:
        return start, {**metrics, "pair_loss_steps": 0}, None
    kept = replace(config, steps=steps)

    def repeat(other: PairWhitening, chosen: np.ndarray) -> PairWhitening:
        return fine_tune(inputs, other, train[chosen], places, None, kept).transform

    final = fine_tune(inputs, start, train, places, None, kept)
    return final.transform, {**metrics, **final.metrics}, repeat
