"""The heads: meaningful before training, real trainable modules, and saved faithfully."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from service.ml.heads import HeadsConfig, LoopNetHeads


def unit(rows: int, dim: int, seed: int) -> torch.Tensor:
    return F.normalize(
        torch.randn(rows, dim, generator=torch.Generator().manual_seed(seed)), dim=-1
    )


@pytest.mark.parametrize("alpha", [0.0, 0.3, 0.7, 1.0])
def test_untrained_similarity_blends_the_branch_cosines(alpha: float) -> None:
    heads = LoopNetHeads(HeadsConfig(local_dim=8, global_dim=12, alpha=alpha)).eval()
    d1, d2, r1, r2 = unit(1, 8, 1), unit(1, 8, 2), unit(1, 12, 3), unit(1, 12, 4)
    with torch.no_grad():
        cosine = float((heads.embed(d1, r1) * heads.embed(d2, r2)).sum())
    a, b = alpha**2, (1 - alpha) ** 2
    expected = (a * float((d1 * d2).sum()) + b * float((r1 * r2).sum())) / (a + b)
    assert cosine == pytest.approx(expected, abs=1e-5)


def test_embeddings_are_unit_vectors() -> None:
    heads = LoopNetHeads(HeadsConfig(local_dim=8, global_dim=12)).eval()
    with torch.no_grad():
        embedded = heads.embed(unit(5, 8, 0), unit(5, 12, 1))
    assert embedded.shape == (5, 20)
    assert torch.allclose(embedded.norm(dim=-1), torch.ones(5), atol=1e-6)


def test_every_head_parameter_is_trainable_and_receives_gradient() -> None:
    heads = LoopNetHeads(HeadsConfig(local_dim=8, global_dim=12), class_labels=[10, 11, 12])
    local, global_ = unit(6, 8, 0), unit(6, 12, 1)
    optimiser = torch.optim.SGD(heads.parameters(), lr=0.1)

    def loss() -> torch.Tensor:
        embedded = heads.embed(local, global_)
        logits = heads.classify(local, global_)
        return F.cross_entropy(logits, torch.tensor([0, 1, 2, 0, 1, 2])) + embedded[0] @ embedded[1]

    # The similarity MLP's last layer starts at zero (pass-through), so its first layer only
    # receives gradient once the last layer has moved: one step, then every parameter does.
    loss().backward()
    optimiser.step()
    optimiser.zero_grad()
    loss().backward()
    for name, parameter in heads.named_parameters():
        assert parameter.grad is not None and parameter.grad.abs().sum() > 0, name


def test_untrained_heads_have_no_classifier() -> None:
    heads = LoopNetHeads(HeadsConfig(local_dim=8, global_dim=12))
    assert heads.predict_submap(unit(1, 8, 0), unit(1, 12, 0)) is None
    with pytest.raises(RuntimeError, match="no trained classification head"):
        heads.classify(unit(1, 8, 0), unit(1, 12, 0))


def test_save_and_load_round_trip(tmp_path: Path) -> None:
    heads = LoopNetHeads(HeadsConfig(local_dim=8, global_dim=12, alpha=0.5), class_labels=[4, 9])
    with torch.no_grad():
        for parameter in heads.parameters():
            parameter.add_(0.01 * torch.randn_like(parameter))
    heads.save(tmp_path / "v2.pt")
    loaded = LoopNetHeads.load(tmp_path / "v2.pt")
    local, global_ = unit(3, 8, 5), unit(3, 12, 6)
    with torch.no_grad():
        assert torch.allclose(heads.eval().embed(local, global_), loaded.embed(local, global_))
    prediction = loaded.predict_submap(local[:1], global_[:1])
    assert prediction is not None and prediction.submap_id in (4, 9)
    assert 0.0 < prediction.probability <= 1.0


def test_alpha_out_of_range_is_refused() -> None:
    with pytest.raises(ValueError, match="alpha"):
        HeadsConfig(local_dim=8, global_dim=12, alpha=1.5)


def test_an_untrained_fusion_concatenates_and_a_changed_one_multiplies() -> None:
    """The block-identity shortcut gives the product's exact values, and is dropped as soon
    as a projection changes (an optimiser step, ``load_state_dict``)."""
    config = HeadsConfig(local_dim=8, global_dim=24, alpha=0.7)
    heads = LoopNetHeads(config).eval()
    local, global_ = torch.randn(5, 8), torch.randn(5, 24)
    with torch.inference_mode():
        assert heads.fusion.is_block_identity()
        fast = heads.embed(local, global_)
    heads.fusion._blocks = False  # force the products
    heads.fusion._blocks_checked = (-1,)
    with torch.no_grad():
        slow = heads.similarity(
            0.7 * heads.fusion.project_local(local)
            + 0.3 * heads.fusion.project_global(global_)
            + heads.fusion.bias
        )
    assert torch.equal(fast, slow)
    with torch.inference_mode():
        assert heads.fusion.is_block_identity()  # checked again, and cached
    changed = LoopNetHeads(config)
    with torch.no_grad():
        changed.fusion.project_global.weight.mul_(2.0)
    heads.load_state_dict(changed.state_dict())
    with torch.inference_mode():
        assert not heads.fusion.is_block_identity()
        assert not torch.allclose(heads.embed(local, global_), fast)
    # while autograd records, the products run (the projections must get gradients)
    trainable = LoopNetHeads(config)
    trainable.embed(local, global_).sum().backward()
    assert trainable.fusion.project_global.weight.grad is not None
