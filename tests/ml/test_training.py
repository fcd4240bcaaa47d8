"""Few-shot training: both heads learn, losses fall, early stopping, shots, cancellation."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from service.ml.heads import HeadsConfig, LoopNetHeads
from service.ml.training import (
    TrainingCancelled,
    TrainingConfig,
    TrainingData,
    contrastive_loss,
    contrastive_pairs,
    evaluate,
    frame_loss,
    pca_init,
    split_shots,
    train_heads,
)

BASE = HeadsConfig(local_dim=16, global_dim=24, alpha=0.7)


def clustered(
    submaps: int = 6, per_submap: int = 8, noise: float = 0.6, seed: int = 0
) -> TrainingData:
    """Frames whose stored vectors scatter around one centre per submap."""
    rng = np.random.default_rng(seed)
    centres_d = rng.normal(size=(submaps, 16))
    centres_r = rng.normal(size=(submaps, 24))
    labels = np.repeat(np.arange(100, 100 + submaps), per_submap)
    index = labels - 100
    local = centres_d[index] + noise * rng.normal(size=(len(labels), 16))
    global_ = centres_r[index] + noise * rng.normal(size=(len(labels), 24))

    def unit(x: np.ndarray) -> np.ndarray:
        return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)

    return TrainingData(unit(local), unit(global_), labels, np.arange(len(labels)))


def test_split_takes_k_shots_spread_over_each_submap() -> None:
    submaps = np.array([1] * 10 + [2] * 3 + [3])
    train, val = split_shots(submaps, 3)
    # submap 2 has only 3 frames: one stays out for validation; a lone frame is a shot
    assert train.tolist() == [0, 4, 9, 10, 12, 13]
    assert sorted(train.tolist() + val.tolist()) == list(range(14))


def label_pairs(labels: list[int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Every pair of one label positive, every pair of two labels negative."""
    same = torch.tensor(labels)[:, None] == torch.tensor(labels)[None, :]
    return same & ~torch.eye(len(labels), dtype=torch.bool), ~same


def test_contrastive_loss_known_values() -> None:
    e = torch.tensor([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    # positives (0,1) at distance 0; negatives at sqrt(2) > margin 1: zero loss
    assert contrastive_loss(e, *label_pairs([0, 0, 1]), margin=1.0).item() == pytest.approx(
        0.0, abs=1e-6
    )
    # all different labels, margin 2: each negative pair costs (2 - d)^2
    d01, d02 = 0.0, np.sqrt(2.0)
    expected = np.mean([(2 - d01) ** 2] * 2 + [(2 - d02) ** 2] * 4)
    assert contrastive_loss(e, *label_pairs([0, 1, 2]), margin=2.0).item() == pytest.approx(
        expected, rel=1e-4
    )
    # pairs in neither mask cost nothing: (0, 2) at distance sqrt(2) pulled would cost 2
    positives, negatives = torch.zeros(3, 3, dtype=torch.bool), torch.zeros(3, 3, dtype=torch.bool)
    positives[0, 1] = positives[1, 0] = True
    assert contrastive_loss(e, positives, negatives, margin=1.0).item() == pytest.approx(
        0.0, abs=1e-6
    )


def test_contrastive_pairs_are_temporal_neighbours_within_a_submap() -> None:
    # robot a: frames 0-11 (submaps 1 and 2 of six frames each), then robot b revisits
    # submap 1 with two frames; the impostor gap of a 12-frame robot is 5 frames
    submaps = np.array([1] * 6 + [2] * 6 + [1, 1])
    robots = np.array(["a"] * 12 + ["b"] * 2)
    data = TrainingData(
        np.zeros((14, 2), np.float32), np.zeros((14, 2), np.float32), submaps, np.arange(14), robots
    )
    everyone = np.arange(14)
    positives, negatives = (m.numpy() for m in contrastive_pairs(data, everyone, window=2))
    assert positives.tolist() == positives.T.tolist() and not positives.diagonal().any()
    assert np.flatnonzero(positives[2]).tolist() == [0, 1, 3, 4, 12, 13]  # +-2, and robot b
    assert not positives[0, 5] and not negatives[0, 5]  # one submap, far apart: left alone
    assert not positives[5, 6] and not negatives[5, 6]  # a boundary's neighbours: left alone
    assert not negatives[5, 9] and negatives[5, 10]  # other submap, >= 5 frames apart: pushed
    assert negatives[12, 6] and positives[12, 13]  # other robot: by submap alone
    # the mask reads ranks among all frames: shots 0, 2 and 5 are 2 and 3 frames apart
    some_positive, _ = contrastive_pairs(data, np.array([0, 2, 5]), window=2)
    assert some_positive.numpy().tolist() == [
        [False, True, False],
        [True, False, False],
        [False, False, False],
    ]
    # window 0: the first design, whole submaps
    whole, apart = (m.numpy() for m in contrastive_pairs(data, everyone, window=0))
    assert whole[0, 5] and whole[0, 13] and apart[5, 6]


def trajectory(submaps: int = 6, per_submap: int = 10, seed: int = 0) -> TrainingData:
    """One robot's route: each frame's vectors are a random walk's position plus a little
    noise, so neighbours look alike and a submap's first and last frames much less so."""
    rng = np.random.default_rng(seed)
    n = submaps * per_submap
    walk_d = np.cumsum(rng.normal(size=(n, 16)), axis=0)
    walk_r = np.cumsum(rng.normal(size=(n, 24)), axis=0)
    local = walk_d - walk_d.mean(0) + 0.3 * rng.normal(size=walk_d.shape)
    global_ = walk_r - walk_r.mean(0) + 0.3 * rng.normal(size=walk_r.shape)

    def unit(x: np.ndarray) -> np.ndarray:
        return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)

    labels = np.repeat(np.arange(submaps), per_submap)
    return TrainingData(unit(local), unit(global_), labels, np.arange(n))


def test_temporal_positives_keep_a_submaps_far_frames_apart() -> None:
    data = trajectory()
    local, global_ = torch.from_numpy(data.local), torch.from_numpy(data.global_)
    steps = np.arange(len(data.submaps) - 1)
    neighbours = steps[data.submaps[steps] == data.submaps[steps + 1]]  # (i, i+1), one submap
    firsts = np.flatnonzero(np.diff(data.submaps, prepend=-1) != 0)  # each submap's first frame

    def similarities(heads: LoopNetHeads) -> tuple[float, float, float]:
        """Neighbours' mean cosine, a submap's first and last frames' mean cosine, and the
        share of frames whose most similar other frame is at most 2 frames away."""
        with torch.no_grad():
            e = heads.embed(local, global_)
        cosines = (e @ e.T).fill_diagonal_(-2.0)
        nearest = cosines.argmax(dim=1).numpy()
        return (
            float((e[neighbours] * e[neighbours + 1]).sum(-1).mean()),
            float((e[firsts] * e[firsts + 9]).sum(-1).mean()),
            float(np.mean(np.abs(nearest - np.arange(len(nearest))) <= 2)),
        )

    def trained(window: int) -> LoopNetHeads:
        config = TrainingConfig(
            shots=9, epochs=80, embed_dim=16, patience=1000, positive_window=window
        )
        return train_heads(data, BASE, config).heads

    start = LoopNetHeads(HeadsConfig(16, 24, BASE.alpha, embed_dim=16))
    pca_init(start, data.local, data.global_)
    near_start, _, nearest_start = similarities(start)
    near_pulled, far_kept, nearest_kept = similarities(trained(window=2))
    _, far_whole, nearest_whole = similarities(trained(window=0))
    assert nearest_start == 1.0  # the starting embedding orders the route
    # pulling whole submaps together collapses them: a frame's nearest frame is anywhere in it
    assert far_whole > 0.95 and nearest_whole < 0.6
    # temporal neighbours: neighbours rise, the route's order survives, the ends stay apart
    assert near_pulled > near_start and nearest_kept >= 0.9 and far_kept < far_whole - 0.05


def test_frame_loss_rewards_frames_that_stay_apart() -> None:
    distinct = torch.eye(4)
    collapsed = torch.ones(4, 4)
    # each view finds its own twin among distinct frames; collapsed frames are a coin toss
    assert frame_loss(distinct, distinct, 0.1) < 1e-3
    assert frame_loss(collapsed, collapsed, 0.1).item() == pytest.approx(np.log(4), rel=1e-5)
    # with the term on, training still learns the submaps
    config = TrainingConfig(shots=3, epochs=40, embed_dim=16, frame_weight=1.0)
    after = train_heads(clustered(noise=0.9), BASE, config).metrics["validation_after"]
    assert after["classifier_accuracy"] > 0.8
    with pytest.raises(ValueError, match="frame_weight"):
        TrainingConfig(frame_weight=-1.0)


def test_both_losses_fall_and_both_heads_change() -> None:
    data = clustered()
    config = TrainingConfig(shots=4, epochs=60, embed_dim=16, patience=1000)
    result = train_heads(data, BASE, config)
    history = result.history
    assert history[-1]["classification_loss"] < 0.5 * history[0]["classification_loss"]
    assert history[-1]["contrastive_loss"] < 0.8 * history[0]["contrastive_loss"]
    heads = result.heads
    assert heads.has_classifier and heads.class_labels == list(range(100, 106))
    last = heads.similarity.mlp[2]
    assert isinstance(last, torch.nn.Linear) and last.weight.abs().sum() > 0  # learned, not zero
    assert heads.config.fused_dim == 16


def test_trained_model_separates_held_out_frames() -> None:
    data = clustered(noise=0.9)
    result = train_heads(data, BASE, TrainingConfig(shots=3, epochs=80, embed_dim=16))
    after = result.metrics["validation_after"]
    before = result.metrics["validation_before"]
    assert after["classifier_accuracy"] >= before["classifier_accuracy"]
    assert after["classifier_accuracy"] > 0.8 and after["retrieval_accuracy"] > 0.8
    assert result.metrics["best_epoch"] <= result.metrics["epochs_run"]


def test_frozen_parts_keep_their_initial_weights() -> None:
    data = clustered()
    result = train_heads(
        data, BASE, TrainingConfig(shots=4, epochs=10, embed_dim=16, train=("classifier",))
    )
    last = result.heads.similarity.mlp[2]
    assert isinstance(last, torch.nn.Linear) and last.weight.abs().sum() == 0


def test_embeddings_stay_unit_and_classifier_gives_probabilities() -> None:
    data = clustered()
    heads = train_heads(data, BASE, TrainingConfig(shots=4, epochs=5, embed_dim=16)).heads
    local, global_ = torch.from_numpy(data.local[:3]), torch.from_numpy(data.global_[:3])
    with torch.no_grad():
        assert torch.allclose(heads.embed(local, global_).norm(dim=-1), torch.ones(3), atol=1e-5)
    prediction = heads.predict_submap(local[:1], global_[:1])
    assert prediction is not None and prediction.submap_id in range(100, 106)


def test_cancellation_stops_training() -> None:
    calls = []

    def stop() -> bool:
        calls.append(1)
        return len(calls) > 3

    with pytest.raises(TrainingCancelled):
        train_heads(clustered(), BASE, TrainingConfig(epochs=100, embed_dim=16), should_stop=stop)


def test_needs_two_submaps_and_valid_config() -> None:
    data = clustered(submaps=1)
    with pytest.raises(ValueError, match="two submaps"):
        train_heads(data, BASE, TrainingConfig(embed_dim=16))
    with pytest.raises(ValueError, match="should be .fusion., .similarity. or .classifier."):
        TrainingConfig(train=("backbone",))
    with pytest.raises(ValueError, match="loss weight"):
        TrainingConfig(classification_weight=0, contrastive_weight=0)


def test_evaluate_without_validation_frames_is_empty() -> None:
    data = clustered(per_submap=2)
    heads = train_heads(data, BASE, TrainingConfig(shots=2, epochs=3, embed_dim=16)).heads
    assert evaluate(heads, data, np.arange(len(data.submaps)), np.array([], dtype=np.int64)) == {}
    assert F.normalize(torch.ones(2), dim=0).norm() == pytest.approx(1.0)


def test_the_keep_term_holds_the_shots_other_cosines_near_the_start() -> None:
    data = trajectory()
    shots, _ = split_shots(data.submaps, 9)
    window = TrainingConfig().positive_window
    others = ~contrastive_pairs(data, shots, window)[0] & ~torch.eye(len(shots), dtype=torch.bool)
    local, global_ = torch.from_numpy(data.local[shots]), torch.from_numpy(data.global_[shots])
    start = LoopNetHeads(HeadsConfig(16, 24, BASE.alpha, embed_dim=16))
    pca_init(start, data.local, data.global_)

    def drift(keep_weight: float) -> float:
        """Mean absolute change of the shots' non-positive cosines over training."""
        config = TrainingConfig(
            shots=9, epochs=60, embed_dim=16, patience=1000, keep_weight=keep_weight
        )
        heads = train_heads(data, BASE, config).heads
        with torch.no_grad():
            before, after = start.embed(local, global_), heads.embed(local, global_)
        return float((after @ after.T - before @ before.T)[others].abs().mean())

    free, kept = drift(0.0), drift(10.0)
    assert kept < 0.5 * free, (kept, free)
    with pytest.raises(ValueError, match="keep_weight"):
        TrainingConfig(keep_weight=-1.0)
