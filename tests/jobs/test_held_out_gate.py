"""The retraining job's not-worse check: active and new heads compared on held-out frames."""

from __future__ import annotations

import numpy as np
import torch

from service.jobs.retraining import _verdict, compare_on_held_out
from service.ml.heads import HeadsConfig, LoopNetHeads
from service.ml.training import TrainingData, split_shots


def places(seed: int = 0) -> TrainingData:
    """Three submaps whose frames cluster around their own centre in both branches."""
    rng = np.random.default_rng(seed)
    submaps = np.repeat(np.arange(3), 12)
    centres_local, centres_global = rng.normal(size=(3, 8)), rng.normal(size=(3, 16))
    local = centres_local[submaps] + 0.2 * rng.normal(size=(36, 8))
    global_ = centres_global[submaps] + 0.2 * rng.normal(size=(36, 16))
    return TrainingData(
        local.astype(np.float32), global_.astype(np.float32), submaps, np.arange(36)
    )


def test_a_version_that_scrambles_the_places_is_worse() -> None:
    data = places()
    shots, held_out = split_shots(data.submaps, 3)
    config = HeadsConfig(local_dim=8, global_dim=16, alpha=0.5)
    active = LoopNetHeads(config).eval()  # untrained: D and R side by side, places separate
    scrambled = LoopNetHeads(config).eval()
    with torch.no_grad():  # a projection that keeps one noise direction only
        generator = torch.Generator().manual_seed(1)
        scrambled.fusion.project_local.weight.zero_()
        scrambled.fusion.project_global.weight.zero_()
        scrambled.fusion.bias.copy_(torch.randn(24, generator=generator))
    gate = compare_on_held_out(active, scrambled, data, shots, held_out)
    assert gate["frames"] == len(held_out) == 27
    assert gate["active"] == 1.0 and gate["new"] < gate["active"]
    assert gate["not_worse"] is False and gate["change"] < 0
    assert _verdict(gate, activated=False).startswith("was not activated: worse")
    assert _verdict(gate, activated=True).startswith("is active, forced")

    same = compare_on_held_out(active, LoopNetHeads(config).eval(), data, shots, held_out)
    assert same["not_worse"] is True and same["change"] == 0
    assert (
        _verdict(same, activated=True) == "is active (held-out retrieval accuracy 1.000 -> 1.000)"
    )
