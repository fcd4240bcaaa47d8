"""Learned whitening from revisit pairs: a hand-computed case, Ledoit-Wolf's intensity, the
heads it folds into, and the gate's pair scores."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from sklearn.covariance import ledoit_wolf_shrinkage as sklearn_shrinkage

from service.jobs.adaptation import verdict
from service.ml.adaptation import (
    NoUsefulPairs,
    PairScores,
    adapt_heads,
    pair_scores,
    separated_share,
    split_pairs,
)
from service.ml.heads import HeadsConfig, LoopNetHeads
from service.ml.pair_whitening import (
    PairWhitening,
    PairWhiteningConfig,
    fold_into_heads,
    fused_inputs,
    ledoit_wolf_shrinkage,
)
from service.ml.training import TrainingData

# centred 2-d frames; pairs (0, 1), (1, 0) differ by (+-2, 0) and (2, 3), (3, 2) by (0, +-1)
FRAMES = np.array(
    [[1, 0], [-1, 0], [0, 0.5], [0, -0.5], [1, 1], [1, -1], [-1, 1], [-1, -1]], np.float64
)
PAIRS = np.array([[0, 1], [1, 0], [2, 3], [3, 2]])


def test_whitening_against_a_hand_computed_case() -> None:
    """C_S = diag(2, 0.5): whitening scales x by sqrt(1.25 / 2) and y by sqrt(1.25 / 0.5), so
    (1, 1) and (1, -1), orthogonal before, have cosine (0.625 - 2.5) / (0.625 + 2.5) = -0.6:
    the direction revisits vary along (x) now counts less than the one they keep (y)."""
    whitening = PairWhitening.fit(FRAMES, PAIRS, PairWhiteningConfig(shrinkage=0.0))
    assert whitening.dim == 2 and whitening.pairs == 4
    np.testing.assert_allclose(whitening.mean, 0.0, atol=1e-7)
    out = whitening.transform(FRAMES[[4, 5]])
    assert float(out[0] @ out[1]) == pytest.approx(-0.6, abs=1e-6)
    # the whitened pairs' covariance is the identity times the mean eigenvalue, 1.25
    z = (FRAMES[PAIRS[:, 0]] - FRAMES[PAIRS[:, 1]]) @ whitening.projection
    np.testing.assert_allclose(z.T @ z / len(z), 1.25 * np.eye(2), atol=1e-6)


def test_full_shrinkage_keeps_the_ranking() -> None:
    """Shrunk all the way, C_S is a multiple of I: a rotation of the centred frames."""
    whitening = PairWhitening.fit(FRAMES, PAIRS, PairWhiteningConfig(shrinkage=1.0))
    out = whitening.transform(FRAMES)
    unit = FRAMES / np.linalg.norm(FRAMES, axis=1, keepdims=True)
    np.testing.assert_allclose(out @ out.T, unit @ unit.T, atol=1e-6)


def test_ledoit_wolf_intensity_matches_scikit_learn() -> None:
    rng = np.random.default_rng(0)
    for count, dim in ((5, 20), (50, 20), (400, 8)):
        samples = rng.normal(size=(count, dim)) * np.linspace(0.2, 3, dim)
        ours = ledoit_wolf_shrinkage(samples)
        assert ours == pytest.approx(sklearn_shrinkage(samples, assume_centered=True), rel=1e-6)
    # few pairs shrink more than many
    few = ledoit_wolf_shrinkage(rng.normal(size=(5, 20)) * np.linspace(0.2, 3, 20))
    many = ledoit_wolf_shrinkage(rng.normal(size=(500, 20)) * np.linspace(0.2, 3, 20))
    assert few > many


def test_folded_heads_embed_as_the_whitening_transforms() -> None:
    rng = np.random.default_rng(1)
    base = HeadsConfig(local_dim=6, global_dim=4, alpha=0.6)
    local, global_ = rng.normal(size=(40, 6)), rng.normal(size=(40, 4))
    inputs = fused_inputs(base, local, global_)
    pairs = np.stack([np.arange(0, 20), np.arange(20, 40)], axis=1)
    whitening = PairWhitening.fit(inputs, pairs, PairWhiteningConfig(max_dims=7))
    heads = fold_into_heads(base, whitening)
    with torch.no_grad():
        embedded = heads.embed(
            torch.from_numpy(local.astype(np.float32)), torch.from_numpy(global_.astype(np.float32))
        ).numpy()
    np.testing.assert_allclose(embedded, whitening.transform(inputs), atol=1e-5)
    assert heads.config.fused_dim == 7 and not heads.has_classifier


def test_bad_input_is_refused() -> None:
    with pytest.raises(ValueError, match="at least one pair"):
        PairWhitening.fit(FRAMES, np.zeros((0, 2)))
    with pytest.raises(ValueError, match="shrinkage"):
        PairWhiteningConfig(shrinkage=1.5)


def _two_conditions(seed: int = 0) -> tuple[TrainingData, np.ndarray]:
    """60 places seen by two robots; the second sees every place shifted along a nuisance
    direction of large variance, so the raw space matches conditions rather than places."""
    rng = np.random.default_rng(seed)
    places = rng.normal(size=(60, 8)) * 0.3
    nuisance = rng.normal(size=(60, 8)) * np.r_[3.0, 3.0, np.zeros(6)]
    local = np.concatenate([places, places + nuisance]).astype(np.float32)
    global_ = rng.normal(size=(120, 4)).astype(np.float32) * 0.01
    robots = np.array(["a"] * 60 + ["b"] * 60)
    ids = np.r_[np.arange(60), np.arange(60)]
    data = TrainingData(local, global_, np.r_[np.arange(60), np.arange(60)] // 5, ids, robots)
    return data, np.stack([np.arange(60, 120), np.arange(60)], axis=1)


def test_adaptation_finds_the_revisits_and_passes_its_gate() -> None:
    data, pairs = _two_conditions()
    active = LoopNetHeads(HeadsConfig(8, 4, alpha=0.9)).eval()
    result = adapt_heads(data, pairs, active, PairWhiteningConfig(), window=0, min_pairs=10)
    gate = result.gate
    assert gate["pairs"] == len(split_pairs(len(pairs))[1]) * 1 > 0
    assert gate["new"] > gate["active"] and gate["pairs_not_worse"]
    assert result.metrics["training_pairs"] + result.metrics["held_out_pairs"] == 60


def test_too_few_pairs_are_refused_with_the_reason() -> None:
    data, pairs = _two_conditions()
    active = LoopNetHeads(HeadsConfig(8, 4)).eval()
    with pytest.raises(NoUsefulPairs, match="only 3 usable revisit pair"):
        adapt_heads(data, pairs[:3], active, PairWhiteningConfig(), min_pairs=10)


def test_pair_scores_count_the_partner_first() -> None:
    data, pairs = _two_conditions()
    places = np.concatenate([data.local[:60], data.local[:60]])
    unit = places / np.linalg.norm(places, axis=1, keepdims=True)
    assert pair_scores(unit, data, pairs, window=0) == (1.0, 1.0, 1.0)


def test_separated_share_is_recall_at_full_precision() -> None:
    """First answers' similarities 0.9 (right), 0.8 (wrong), 0.7 and 0.6 (right): only the
    answer above the wrong one's 0.8 could be accepted without a false loop."""
    best = np.array([0.9, 0.8, 0.7, 0.6])
    assert separated_share(best, np.array([True, False, True, True])) == 0.25
    assert separated_share(best, np.ones(4, bool)) == 1.0
    assert separated_share(best, np.zeros(4, bool)) == 0.0


def test_a_ranking_that_keeps_its_first_answers_can_lose_the_decision() -> None:
    """Robot a's frames e0..e3, robot b's revisits of them; b's last frame answers a0 first
    (wrong) both times, but the second time more similar than most right first answers:
    recall stays 7/8, the share a threshold could accept without a false loop falls."""
    data = TrainingData(
        np.zeros((8, 4), np.float32),
        np.zeros((8, 1), np.float32),
        np.arange(8) % 4,
        np.r_[np.arange(4), np.arange(4)],
        np.array(["a"] * 4 + ["b"] * 4),
    )
    pairs = np.stack([np.arange(4, 8), np.arange(4)], axis=1)
    robot_b = np.diag([1.0, 0.9, 0.9, 0.1])

    def scores(wrong_similarity: float) -> PairScores:
        revisits = robot_b.copy()
        revisits[3, 0] = wrong_similarity
        return pair_scores(np.concatenate([np.eye(4), revisits]), data, pairs, window=0)

    before, after = scores(0.3), scores(0.95)
    assert before.recall == after.recall == 7 / 8
    assert (before.separated, after.separated) == (6 / 8, 2 / 8)


def test_a_refusal_names_the_held_out_pairs_score_that_fell() -> None:
    gate = {
        "pairs": 12,
        "active": 0.5,
        "new": 0.6,
        "change": 0.1,
        "mrr_active": 0.6,
        "mrr_new": 0.7,
        "separated_active": 0.5,
        "separated_new": 0.25,
        "pairs_not_worse": False,
        "not_worse": False,
    }
    assert verdict(gate, activated=False) == (
        "was not activated: worse on held-out pairs: found above every wrong first answer "
        "0.500 -> 0.250 (a gain: held-out pairs (12) find their partner first 0.500 -> 0.600)"
    )


def test_the_split_never_holds_out_what_the_active_version_learned_from() -> None:
    train, held = split_pairs(20)
    assert len(held) > 0 and sorted([*train, *held]) == list(range(20))
    learned = np.arange(20) < 12  # the active version learned from the first 12
    train, held = split_pairs(20, trained=learned)
    assert len(held) > 0 and held.min() >= 12
    assert sorted([*train, *held]) == list(range(20))
    assert len(split_pairs(20, trained=np.ones(20, bool))[1]) == 0


def test_a_second_adaptation_is_judged_on_pairs_neither_version_learned_from() -> None:
    data, pairs = _two_conditions()
    active = LoopNetHeads(HeadsConfig(8, 4, alpha=0.9)).eval()
    first = adapt_heads(data, pairs, active, PairWhiteningConfig(), window=0, min_pairs=10)
    learned = np.isin(np.arange(60), first.trained_rows)
    assert 0 < learned.sum() < 60
    second = adapt_heads(
        data, pairs, first.heads, PairWhiteningConfig(), window=0, active_trained=learned
    )
    held = np.setdiff1d(np.arange(60), second.trained_rows)
    assert len(held) == second.gate["pairs"] > 0 and not learned[held].any()
