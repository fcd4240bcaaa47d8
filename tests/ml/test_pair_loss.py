"""The listwise loss over revisit pairs: hard negatives outside both places, a fine-tuning that
ranks held-out pairs better than its start, and the adapt job's methods through the gate."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from service.ml.adaptation import AdaptationResult, adapt_heads, pair_scores
from service.ml.calibration_config import ImpostorProbe
from service.ml.heads import HeadsConfig, LoopNetHeads
from service.ml.pair_loss import (
    PairLossConfig,
    Places,
    fine_tune,
    hard_negatives,
    identity_start,
    listwise_loss,
)
from service.ml.pair_whitening import (
    PairWhitening,
    PairWhiteningConfig,
    fold_into_heads,
    fused_inputs,
    pair_differences,
)
from service.ml.training import TrainingData

PLACES, DIM, NUISANCE = 80, 24, 4


def revisits(seed: int = 0) -> tuple[TrainingData, np.ndarray]:
    """A map robot's frame of each place, then a revisiting robot's frame of each: the same
    place vector plus a strong condition along ``NUISANCE`` axes whose strength varies from
    frame to frame, so that revisits find other revisits before their own place."""
    rng = np.random.default_rng(seed)
    place = rng.normal(size=(PLACES, DIM)).astype(np.float32)
    condition = np.zeros((PLACES, DIM), np.float32)
    condition[:, :NUISANCE] = rng.normal(3.0, 2.0, size=(PLACES, NUISANCE))
    seen = place + 0.3 * rng.normal(size=(PLACES, DIM)).astype(np.float32)
    vectors = np.concatenate([place, seen + condition])
    half = DIM // 2
    data = TrainingData(
        local=np.ascontiguousarray(vectors[:, :half]),
        global_=np.ascontiguousarray(vectors[:, half:]),
        submaps=np.concatenate([np.arange(PLACES), np.arange(PLACES)]) // 10,
        frame_ids=np.concatenate([np.arange(PLACES), np.arange(PLACES)]),
        robots=np.array(["map"] * PLACES + ["revisit"] * PLACES),
    )
    pairs = np.stack([PLACES + np.arange(PLACES), np.arange(PLACES)], axis=1)
    return data, pairs


def places_of(data: TrainingData, window: int) -> Places:
    codes, rank, _ = data.sequence
    return Places(codes, rank, window)


def test_hard_negatives_are_the_nearest_frames_outside_both_places() -> None:
    # one robot, frames on a line; frame 0 asks with partner 3 (window 1: 0-1 and 2-4 excluded)
    embeddings = np.eye(8, dtype=np.float32)
    embeddings[:, 0] += np.array([0, 0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3], np.float32)
    unit = embeddings / np.linalg.norm(embeddings, axis=1, keepdims=True)
    places = Places(np.zeros(8, np.int64), np.arange(8), window=1)
    chosen = hard_negatives(unit, np.array([0]), np.array([3]), places, count=2)
    assert chosen.tolist() == [[5, 6]]
    # more negatives asked than wrong frames exist: the list repeats the hardest, never a right one
    chosen = hard_negatives(unit, np.array([0]), np.array([3]), places, count=5)
    assert set(chosen[0].tolist()) == {5, 6, 7} and chosen[0, 0] == 5


def test_listwise_loss_is_low_when_the_partner_is_first() -> None:
    embedded = torch.eye(3)
    embedded[1] = torch.tensor([0.8, 0.6, 0.0])
    near = listwise_loss(embedded, torch.tensor([0]), torch.tensor([1]), torch.tensor([[2]]), 0.1)
    far = listwise_loss(embedded, torch.tensor([0]), torch.tensor([2]), torch.tensor([[1]]), 0.1)
    assert float(near) < 0.01 < 5.0 < float(far)


def test_fine_tuning_ranks_held_out_pairs_better_than_its_start() -> None:
    """From the centred input (no whitening), 60 pairs teach the loss to discount the
    condition's axes; the 20 pairs it never saw find their partner far more often."""
    data, pairs = revisits()
    inputs = fused_inputs(HeadsConfig(DIM // 2, DIM // 2), data.local, data.global_)
    train, held = pairs[:60], pairs[60:]
    start = identity_start(inputs, len(train))
    before = pair_scores(start.transform(inputs), data, held, 0)
    result = fine_tune(
        inputs,
        start,
        train[:48],
        places_of(data, 0),
        lambda embedded: pair_scores(embedded, data, train[48:], 0)[1],
        PairLossConfig(steps=200, learning_rate=0.01, anchor=0.1),
    )
    after = pair_scores(result.transform.transform(inputs), data, held, 0)
    assert before[0] < 0.6
    assert after[0] >= before[0] + 0.25 and after[1] > before[1]
    assert result.metrics["pair_loss_best_step"] > 0
    assert (
        result.metrics["pair_loss_validation_best"] > result.metrics["pair_loss_validation_start"]
    )


def test_a_run_that_finds_nothing_returns_its_start() -> None:
    data, pairs = revisits()
    inputs = fused_inputs(HeadsConfig(DIM // 2, DIM // 2), data.local, data.global_)
    start = identity_start(inputs, 10)
    result = fine_tune(inputs, start, pairs[:10], places_of(data, 0), lambda _: 0.0)
    np.testing.assert_array_equal(result.transform.projection, start.projection)
    assert result.metrics["pair_loss_best_step"] == 0
    assert result.metrics["pair_loss_steps"] == PairLossConfig().check_every * 4


def adapted(seed: int, whiten: bool) -> tuple[TrainingData, np.ndarray, AdaptationResult]:
    """:func:`revisits` adapted from untrained heads with the loss (window 0: one frame a place)."""
    data, pairs = revisits(seed=seed)
    active = LoopNetHeads(HeadsConfig(DIM // 2, DIM // 2)).eval()
    config = PairLossConfig(learning_rate=0.01, anchor=0.1)
    result = adapt_heads(
        data, pairs, active, PairWhiteningConfig(), window=0, whiten=whiten, pair_loss=config
    )
    return data, pairs, result


@pytest.mark.parametrize("whiten", [False, True])
def test_the_adapt_methods_with_the_loss_pass_the_gate(whiten: bool) -> None:
    data, _, result = adapted(seed=1, whiten=whiten)
    assert result.gate["pairs_not_worse"] and result.gate["change"] > 0.2
    assert result.metrics["pair_loss_steps_trial"] > 0
    # the whitening alone ranks every validation pair first here: the loss has nothing to add
    assert (result.metrics["pair_loss_steps"] > 0) == (not whiten)


def test_a_low_rank_change_learns_too() -> None:
    data, pairs = revisits()
    inputs = fused_inputs(HeadsConfig(DIM // 2, DIM // 2), data.local, data.global_)
    start = identity_start(inputs, 60)
    before = pair_scores(start.transform(inputs), data, pairs[60:], 0)
    config = PairLossConfig(steps=60, learning_rate=0.01, anchor=0.1, rank=4)
    result = fine_tune(inputs, start, pairs[:60], places_of(data, 0), None, config)
    after = pair_scores(result.transform.transform(inputs), data, pairs[60:], 0)
    assert after[0] >= before[0] + 0.25
    change = result.transform.projection - start.projection
    assert np.linalg.matrix_rank(change, tol=1e-4) <= 4


def test_config_rejects_nonsense() -> None:
    with pytest.raises(ValueError, match="temperature"):
        PairLossConfig(temperature=0)
    with pytest.raises(ValueError, match="negatives"):
        PairLossConfig(negatives=0)


def test_the_impostor_probe_refit_repeats_the_kept_loss_steps() -> None:
    """A probe that holds nothing out refits the version itself: the same whitening, then the
    same steps of the loss (without them, its impostor model would score another space)."""
    data, pairs, result = adapted(seed=2, whiten=False)
    active = LoopNetHeads(HeadsConfig(DIM // 2, DIM // 2)).eval()
    assert result.metrics["pair_loss_steps"] > 0
    probe = ImpostorProbe(data.local, data.global_, np.zeros(0), np.zeros(0), in_sample=True)
    refit = result.impostor_refit(probe, np.asarray(data.frame_ids))
    x, y = torch.from_numpy(data.local), torch.from_numpy(data.global_)
    with torch.no_grad():
        np.testing.assert_allclose(refit.embed(x, y), result.heads.embed(x, y), atol=1e-5)
        untuned = adapt_heads(data, pairs, active, PairWhiteningConfig(), window=0, whiten=False)
        assert not np.allclose(untuned.heads.embed(x, y), result.heads.embed(x, y), atol=1e-3)


def test_the_impostor_probe_refit_leaves_out_its_held_frames_and_their_pairs() -> None:
    """The probe's held-out frames play queries of unseen places: the refitted whitening sees
    neither them nor the training pairs holding one (whitening out a pair's difference makes
    its frames close; kept in, held-out frames would look closer to their partners and
    farther from everything else than a query does). By hand: the same fit on the rest."""
    data, pairs = revisits(seed=3)
    ids = np.arange(2 * PLACES) + 100  # unique frame ids, as an atlas gives them
    data = TrainingData(data.local, data.global_, data.submaps, ids, data.robots)
    active = LoopNetHeads(HeadsConfig(DIM // 2, DIM // 2)).eval()
    result = adapt_heads(data, pairs, active, PairWhiteningConfig(), window=0, whiten=True)
    held = np.zeros(2 * PLACES, bool)
    held[PLACES : PLACES + 20] = True  # the revisiting robot's first 20 frames
    held[60:70] = True  # and a stretch of the map
    probe = ImpostorProbe(data.local, data.global_, np.zeros(0), np.zeros(0), False, held)
    refit = result.impostor_refit(probe, ids)
    inputs = fused_inputs(active.config, data.local, data.global_)
    train = pairs[result.trained_rows]
    clean = train[~held[train].any(axis=1)]
    assert 0 < len(clean) < len(train)
    expected = fold_into_heads(
        active.config,
        PairWhitening.fit_differences(
            inputs[~held], pair_differences(inputs, clean), PairWhiteningConfig()
        ),
    )
    x, y = torch.from_numpy(data.local), torch.from_numpy(data.global_)
    with torch.no_grad():
        np.testing.assert_allclose(refit.embed(x, y), expected.embed(x, y), atol=1e-5)
