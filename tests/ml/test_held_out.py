"""What a retraining job holds out (whole stretches of the route) and its not-worse gate."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from service.jobs.retraining import _verdict
from service.ml import held_out
from service.ml.heads import HeadsConfig, LoopNetHeads
from service.ml.held_out import _average_precision, compare_on_held_out, split_for_job
from service.ml.training import TrainingConfig, TrainingData, train_heads

FRAMES, SUBMAP = 100, 5  # one robot's route of 20 submaps; stretches of 5 frames held out
HELD = [f for start in (10, 35, 60, 85) for f in range(start, start + 5)]


def route(seed: int = 0) -> TrainingData:
    """Each submap's frames lie near its own axis (orthogonal places), 64 + 64 dims."""
    rng = np.random.default_rng(seed)
    submaps = np.arange(FRAMES) // SUBMAP
    centres = np.eye(128)[rng.permutation(128)[: FRAMES // SUBMAP]]
    vectors = centres[submaps] + 0.02 * rng.normal(size=(FRAMES, 128))
    vectors = vectors.astype(np.float32)
    return TrainingData(vectors[:, :64], vectors[:, 64:], submaps, np.arange(FRAMES))


def test_a_job_keeps_whole_stretches_out_of_training_and_validation() -> None:
    data = route()
    split = split_for_job(data, 3)
    assert split.held_out.tolist() == HELD  # a fifth of the route, in stretches of 5 frames
    assert not np.isin(split.shots, split.held_out).any()
    assert not np.isin(split.validation, split.held_out).any()
    everything = np.concatenate([split.shots, split.validation, split.held_out])
    assert sorted(everything.tolist()) == list(range(FRAMES))
    # every submap outside the stretches gives 3 shots (one frame left to validate)
    seen = np.setdiff1d(np.arange(FRAMES // SUBMAP), data.submaps[HELD])
    assert np.bincount(data.submaps[split.shots])[seen].tolist() == [3] * len(seen)


def test_the_gate_refuses_heads_that_forget_the_places_they_did_not_train_on() -> None:
    data = route()
    split = split_for_job(data, 3)
    config = HeadsConfig(local_dim=64, global_dim=64, alpha=0.5)
    active = LoopNetHeads(config).eval()  # D and R side by side: every place its own axis
    forgetful = LoopNetHeads(config).eval()
    with torch.no_grad():  # keeps the trained places' axes only: held-out frames are noise
        keep = np.zeros(128, np.float32)
        trained = np.flatnonzero(~np.isin(np.arange(FRAMES), HELD))
        keep[np.abs(np.hstack([data.local, data.global_])[trained]).argmax(axis=1)] = 1.0
        forgetful.fusion.project_local.weight.mul_(torch.from_numpy(keep[:, None]))
        forgetful.fusion.project_global.weight.mul_(torch.from_numpy(keep[:, None]))
    gate = compare_on_held_out(active, forgetful, data, split.held_out, window=2)
    assert gate["frames"] == len(HELD)
    assert gate["active"] == 1.0 and gate["new"] < 0.5 and gate["not_worse"] is False
    assert _verdict(gate, activated=False).startswith("was not activated: worse")
    assert _verdict(gate, activated=True).startswith("is active, forced")

    same = compare_on_held_out(active, LoopNetHeads(config).eval(), data, split.held_out, 2)
    assert same["not_worse"] is True and same["change"] == 0
    assert _verdict(same, activated=True) == (
        "is active (held-out stretches (20 frames) retrieval accuracy 1.000 -> 1.000, "
        f"mean average precision {same['map_active']:.3f} -> {same['map_new']:.3f})"
    )


def forgetful_heads(data: TrainingData, config: HeadsConfig) -> LoopNetHeads:
    """Heads that keep the trained places' axes only: held-out frames become noise."""
    forgetful = LoopNetHeads(config).eval()
    with torch.no_grad():
        keep = np.zeros(128, np.float32)
        trained = np.flatnonzero(~np.isin(np.arange(FRAMES), HELD))
        keep[np.abs(np.hstack([data.local, data.global_])[trained]).argmax(axis=1)] = 1.0
        forgetful.fusion.project_local.weight.mul_(torch.from_numpy(keep[:, None]))
        forgetful.fusion.project_global.weight.mul_(torch.from_numpy(keep[:, None]))
    return forgetful


def test_a_submap_that_holds_a_whole_drive_is_a_route_not_one_place(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # the same route stored as one robot's single submap: were its 100 frames one place, every
    # held-out frame's nearest frame would be right whatever the heads did to it
    data = replace(route(), submaps=np.zeros(FRAMES, np.int64))
    split = split_for_job(replace(data, submaps=route().submaps), 3)
    config = HeadsConfig(local_dim=64, global_dim=64, alpha=0.5)
    active, forgetful = LoopNetHeads(config).eval(), forgetful_heads(data, config)
    gate = compare_on_held_out(active, forgetful, data, split.held_out, 2)
    assert gate["new"] < 0.5 < gate["active"] and gate["not_worse"] is False
    sizes = np.array([7] * 30 + [3] * 5 + [9] * 26)  # a route, a place, a route
    codes = held_out.place_submaps(sizes)
    assert len(set(codes[:30])) == 30 and len(set(codes[35:])) == 26
    assert len(set(codes[30:35])) == 1 and not np.isin(codes[30:35], codes[:30]).any()
    monkeypatch.setattr(held_out, "PLACE_SUBMAP_FRAMES", FRAMES)  # the drive as one place
    blind = compare_on_held_out(active, forgetful, data, split.held_out, 2)
    assert blind["active"] == blind["new"] == 1.0 and blind["not_worse"] is True


def test_average_precision_of_one_ranking_by_hand() -> None:
    itself = -np.inf
    similarity = np.array([itself, 0.9, 0.8, 0.7, 0.6])
    # right frames ranked 1st and 4th: (1/1 + 2/4) / 2
    assert _average_precision(similarity, np.array([0, 1, 0, 0, 1], bool)) == 0.75
    # a tie counts against the right frame: ranked 2nd
    assert _average_precision(np.array([itself, 0.5, 0.5]), np.array([0, 1, 0], bool)) == 0.5
    assert _average_precision(similarity, np.zeros(5, bool)) == 0.0


def test_the_gate_sees_a_worse_neighbourhood_when_the_nearest_frame_stays_right() -> None:
    # nearest-frame accuracy saturates at 1.0 on a single route; the ranking of the rest of
    # a held-out frame's neighbourhood still shows the damage
    data = route()
    split = split_for_job(data, 3)
    config = HeadsConfig(local_dim=64, global_dim=64, alpha=0.5)
    noisy = LoopNetHeads(config).eval()  # the dims no place lies on weigh 8 times more
    places = np.unique(np.abs(np.hstack([data.local, data.global_])).argmax(axis=1))
    scale = np.full(128, 8.0, np.float32)
    scale[places] = 1.0
    with torch.no_grad():
        noisy.fusion.project_local.weight.mul_(torch.from_numpy(scale[None, :64]))
        noisy.fusion.project_global.weight.mul_(torch.from_numpy(scale[None, 64:]))
    gate = compare_on_held_out(LoopNetHeads(config).eval(), noisy, data, split.held_out, 2)
    assert gate["active"] == gate["new"] == 1.0
    assert gate["map_new"] < gate["map_active"] and gate["not_worse"] is False


def test_submaps_inside_a_held_out_stretch_stay_nameable() -> None:
    # no shot comes from them, but the classifier starts from their frames' mean
    data = route()
    split = split_for_job(data, 3)
    trained = train_heads(
        data,
        HeadsConfig(local_dim=64, global_dim=64, alpha=0.5),
        TrainingConfig(shots=3, epochs=10),
        shot_idx=split.shots,
        validation_idx=split.validation,
    )
    assert trained.metrics["validation_frames"] == len(split.validation)
    with torch.no_grad():
        logits = trained.heads.classify(
            torch.from_numpy(data.local[HELD]), torch.from_numpy(data.global_[HELD])
        )
    named = np.asarray(trained.heads.class_labels)[logits.argmax(dim=1).numpy()]
    assert np.mean(named == data.submaps[HELD]) >= 0.9


def test_the_gate_judges_an_evenly_spread_share_of_a_large_hold_out(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    data = route()
    split = split_for_job(data, 3)
    config = HeadsConfig(local_dim=64, global_dim=64, alpha=0.5)
    heads = LoopNetHeads(config).eval()
    full = compare_on_held_out(heads, heads, data, split.held_out, 2)
    monkeypatch.setattr(held_out, "JUDGED_FRAMES", 4)
    capped = compare_on_held_out(heads, heads, data, split.held_out, 2)
    assert full["judged_frames"] == len(HELD) and capped["judged_frames"] == 4
    assert capped["frames"] == len(HELD) and capped["not_worse"] is True
    assert held_out._evenly(np.arange(20), 4).tolist() == [0, 6, 12, 19]


def test_a_second_robots_frame_finding_its_pair_partners_place_is_right() -> None:
    # robot "b" revisits the places of robot "a" in a submap of its own; each b frame is
    # a's frame of its place plus a small change, so its nearest other frame is a's.
    rng = np.random.default_rng(3)
    a = rng.normal(size=(40, 128)).astype(np.float32)
    b = a[10:20] + 0.05 * rng.normal(size=(10, 128)).astype(np.float32)
    vectors = np.concatenate([a, b])
    data = TrainingData(
        vectors[:, :64],
        vectors[:, 64:],
        np.array([i // 5 for i in range(40)] + [100] * 10),
        np.concatenate([np.arange(40), np.arange(10) * 10]),  # b's frames far apart in time
        np.array(["a"] * 40 + ["b"] * 10),
    )
    heads = LoopNetHeads(HeadsConfig(local_dim=64, global_dim=64, hidden_dim=32)).eval()
    held = np.arange(40, 50)
    pairs = np.stack([np.arange(40, 50), np.arange(10, 20)], axis=1)
    without = held_out.held_out_scores(heads, data, held, window=2)
    with_pairs = held_out.held_out_scores(heads, data, held, window=2, same_place=pairs)
    assert without.accuracy <= 0.2 and with_pairs.accuracy == 1.0
