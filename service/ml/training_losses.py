"""The losses a retraining minimises on unit embeddings: contrastive pairs (Hadsell et al.
2006), each frame finding its own second view, and the distillation that keeps the rest."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch
import torch.nn.functional as F

if TYPE_CHECKING:
    from service.ml.heads import LoopNetHeads
    from service.ml.training import TrainingData
    from service.ml.training_config import TrainingConfig


def contrastive_loss(
    embeddings: torch.Tensor, positives: torch.Tensor, negatives: torch.Tensor, margin: float
) -> torch.Tensor:
    """Mean of ``d^2`` over the positive pairs plus mean of ``max(0, m - d)^2`` over the
    negative ones (boolean ``n x n`` masks, e.g. from :func:`contrastive_pairs`)."""
    distances = torch.cdist(embeddings, embeddings).clamp_min(1e-9)
    loss = embeddings.new_zeros(())
    if positives.any():
        loss = loss + distances[positives].pow(2).mean()
    if negatives.any():
        loss = loss + F.relu(margin - distances[negatives]).pow(2).mean()
    return loss


def frame_loss(first: torch.Tensor, second: torch.Tensor, temperature: float) -> torch.Tensor:
    """Cross-entropy of each frame's first view finding its own second view among all frames."""
    logits = F.normalize(first, dim=-1) @ F.normalize(second, dim=-1).T / temperature
    return F.cross_entropy(logits, torch.arange(len(first)))


def keep_loss(embeddings: torch.Tensor, start: torch.Tensor, pairs: torch.Tensor) -> torch.Tensor:
    """Mean squared change of the cosines of ``pairs`` (a boolean ``n x n`` mask) from the
    ``start`` cosines: a distillation of the starting heads on the pairs training does not pull
    together, so pushing some places apart cannot reshape the rest of the space freely."""
    if not pairs.any():
        return embeddings.new_zeros(())
    return (embeddings @ embeddings.T - start)[pairs].pow(2).mean()


def contrastive_pairs(
    data: TrainingData, idx: np.ndarray, window: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Boolean ``n x n`` masks of positive and negative pairs among the frames ``idx``.

    Positives: two frames of one submap and one robot at most ``window`` frames apart in the
    robot's sequence (its every frame counts, shots or not), and frames of one submap from
    different robots (a revisit labelled with its submap: nothing tells which of its frames it
    sees). Negatives: frames of different submaps that are different places by sequence too
    (other robots, or one robot's frames at least the impostor gap apart). Neighbours on
    either side of a submap boundary are neither, and so are a submap's far frames: nothing
    forces them together or apart. ``window`` 0 is the first design: every pair of a submap
    positive, every pair of different submaps negative.
    """
    submaps = data.submaps[idx]
    same_submap = submaps[:, None] == submaps[None, :]
    if window == 0:
        positives, negatives = same_submap.copy(), ~same_submap
    else:
        codes, rank, gap = (part[idx] for part in data.sequence)
        same_robot = codes[:, None] == codes[None, :]
        apart = np.abs(rank[:, None] - rank[None, :])
        positives = same_submap & ((apart <= window) | ~same_robot)
        negatives = ~same_submap & (~same_robot | (apart >= gap[:, None]))
    np.fill_diagonal(positives, False)
    return torch.from_numpy(positives), torch.from_numpy(negatives)


def augment(x: torch.Tensor, config: TrainingConfig, generator: torch.Generator) -> torch.Tensor:
    """Noise and feature dropout on stored (unit) vectors, then back to unit length."""
    if config.noise_std > 0:
        x = x + config.noise_std * torch.randn(x.shape, generator=generator)
    if config.feature_dropout > 0:
        keep = torch.rand(x.shape, generator=generator) >= config.feature_dropout
        x = x * keep
    return F.normalize(x, dim=-1)


def losses(
    heads: LoopNetHeads,
    local: torch.Tensor,
    global_: torch.Tensor,
    targets: torch.Tensor,
    pairs: tuple[torch.Tensor, torch.Tensor],
    config: TrainingConfig,
) -> tuple[torch.Tensor, torch.Tensor]:
    fused = heads.fusion(local, global_)
    assert heads.classifier is not None
    classification = F.cross_entropy(heads.classifier(fused), targets)
    contrastive = contrastive_loss(heads.similarity(fused), *pairs, config.margin)
    return classification, contrastive
