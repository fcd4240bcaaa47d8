"""Few-shot retraining of LoopNet's heads from stored per-frame features (never from images).

Both heads learn together on K frames ("shots") per submap:

- the classification head with cross-entropy over the atlas's submaps;
- the similarity head with a contrastive loss of margin ``m`` (Hadsell et al. 2006) on the
  unit embeddings: temporal neighbours are pulled together and different places pushed at
  least ``m`` apart (Euclidean distance on the unit sphere, so ``m`` = 1 means cosine <= 0.5);
  see :func:`contrastive_pairs` for which pairs are which. Pulling a whole submap together
  (the first design) merged its far frames and pushed apart neighbours on either side of a
  submap boundary, and map-only retraining lowered Recall@1 (benchmarks/RESULTS.md).

Fusion starts from a PCA of the atlas's stored features (centred, ``embed_dim`` components), the
classifier from the shots' per-submap mean embeddings (prototypes), and the similarity head as a
pass-through. The frames that are not shots are the validation set: after every epoch their
classifier and nearest-shot accuracies are measured (their loss breaks ties), and the best
epoch's weights are kept (epoch 0, the initialisation, included), so training never leaves
validation accuracy worse than it found it.
"""

from __future__ import annotations

import copy
import functools
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from service.ml.fusion import weighted_branches
from service.ml.heads import ClassificationHead, HeadsConfig, LoopNetHeads
from service.ml.impostors import sequence_positions
from service.ml.training_config import TRAINABLE_PARTS, TrainablePart, TrainingConfig
from service.ml.training_losses import (
    augment,
    contrastive_loss,
    contrastive_pairs,
    frame_loss,
    keep_loss,
    losses,
)


@dataclass
class TrainingData:
    """Stored vectors of an atlas's frames: ``N x D`` local, ``N x C`` global, submap labels.

    ``frame_ids`` order each robot's frames (ingest order, as the impostor model reads it);
    ``robots`` names each frame's robot (None: one robot's sequence).
    """

    local: np.ndarray
    global_: np.ndarray
    submaps: np.ndarray
    frame_ids: np.ndarray
    robots: np.ndarray | None = None

    @functools.cached_property
    def sequence(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per frame: robot code, rank in that robot's sequence, and the gap beyond which two
        of its frames are different places (:func:`service.ml.impostors.sequence_positions`);
        computed once, though every epoch's validation asks for it."""
        robots = self.robots if self.robots is not None else np.zeros(len(self.submaps))
        return sequence_positions([str(r) for r in robots], np.asarray(self.frame_ids))


@dataclass
class TrainingResult:
    heads: LoopNetHeads
    metrics: dict[str, Any]
    history: list[dict[str, float]] = field(default_factory=list)


class TrainingCancelled(Exception):
    """Raised when ``should_stop`` asks a run to stop; nothing is saved."""


ProgressCallback = Callable[[float, str], None]


def split_shots(submaps: np.ndarray, shots: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices of K shots per submap (spread evenly over its frames) and of the rest.

    Frames are taken in stored order (ingest order), so the shots cover each submap's span. A
    submap of two or more frames always keeps one out of the shots: without any validation
    frame, early stopping and best-epoch keeping have nothing to judge by, and a run over all
    epochs overfits the shots (benchmarks/RESULTS.md has the measurement).
    """
    train: list[int] = []
    for submap in np.unique(submaps):
        members = np.flatnonzero(submaps == submap)
        take = min(shots, max(len(members) - 1, 1))
        if len(members) <= take:
            train.extend(members.tolist())
        else:
            picks = np.linspace(0, len(members) - 1, take).round().astype(int)
            train.extend(members[np.unique(picks)].tolist())
    train_idx = np.array(sorted(train), dtype=np.int64)
    val_idx = np.setdiff1d(np.arange(len(submaps)), train_idx)
    return train_idx, val_idx


PCA_SAMPLE = 20_000  # frames that estimate the PCA; more changes little and costs O(n d^2)


def pca_init(heads: LoopNetHeads, local: np.ndarray, global_: np.ndarray, seed: int = 0) -> None:
    """Set the fusion maps to the top principal directions of ``[alpha*D, (1-alpha)*R]``.

    Centring removes the component every frame shares (aggregated DISK descriptors of all
    frames are close to one another), which the block-identity start keeps. Directions come
    from a randomised truncated SVD (``torch.svd_lowrank``) of at most ``PCA_SAMPLE`` frames.
    """
    config = heads.config
    alpha = config.alpha
    if len(local) > PCA_SAMPLE:
        pick = np.random.default_rng(seed).choice(len(local), PCA_SAMPLE, replace=False)
        local, global_ = local[pick], global_[pick]
    stacked = torch.from_numpy(weighted_branches(local, global_, alpha).astype(np.float32))
    mean = stacked.mean(dim=0)
    rows = min(config.fused_dim, *stacked.shape)
    torch.manual_seed(seed)  # svd_lowrank starts from a random subspace
    _, singular_values, v = torch.svd_lowrank(stacked - mean, q=rows, niter=4)
    rank = int((singular_values > 1e-6 * singular_values.max().clamp_min(1e-30)).sum())
    basis = np.zeros((config.fused_dim, stacked.shape[1]))
    basis[:rank] = v[:, :rank].T.numpy()
    basis_t = torch.from_numpy(basis).float()
    with torch.no_grad():
        fusion = heads.fusion
        fusion.project_local.weight.copy_(basis_t[:, : config.local_dim])
        fusion.project_global.weight.copy_(basis_t[:, config.local_dim :])
        fusion.bias.copy_(-(basis_t @ mean))


VALIDATION_LOSS_SAMPLE = 1024  # validation frames in the (quadratic) contrastive term


@torch.no_grad()
def evaluate(
    heads: LoopNetHeads,
    data: TrainingData,
    reference_idx: np.ndarray,
    query_idx: np.ndarray,
    config: TrainingConfig | None = None,
) -> dict[str, float]:
    """Accuracies of the ``query_idx`` frames, from one forward pass over the frames involved.

    ``retrieval_accuracy``: the nearest reference frame (by embedding) is in the right submap;
    ``classifier_accuracy``: the classifier names the right submap. With ``config``, also the
    validation ``loss`` (weighted cross-entropy + contrastive on a fixed sample of frames).
    """
    if len(query_idx) == 0:
        return {}
    involved = np.concatenate([reference_idx, query_idx])
    fused = heads.fusion(
        torch.from_numpy(data.local[involved]), torch.from_numpy(data.global_[involved])
    )
    embeddings = heads.similarity(fused)
    references, queries = embeddings[: len(reference_idx)], embeddings[len(reference_idx) :]
    nearest = reference_idx[(queries @ references.T).argmax(dim=1).numpy()]
    truth = data.submaps[query_idx]
    metrics = {"retrieval_accuracy": float(np.mean(data.submaps[nearest] == truth))}
    if heads.classifier is None:
        return metrics
    logits = heads.classifier(fused[len(reference_idx) :])
    labels = np.asarray(heads.class_labels)
    metrics["classifier_accuracy"] = float(np.mean(labels[logits.argmax(dim=1).numpy()] == truth))
    if config is not None:
        index_of = {label: i for i, label in enumerate(heads.class_labels)}
        targets = torch.tensor([index_of[int(t)] for t in truth], dtype=torch.long)
        sample = query_idx[:VALIDATION_LOSS_SAMPLE]
        loss = config.classification_weight * F.cross_entropy(logits, targets)
        loss += config.contrastive_weight * contrastive_loss(
            queries[: len(sample)],
            *contrastive_pairs(data, sample, config.positive_window),
            config.margin,
        )
        metrics["loss"] = loss.item()
    return metrics


def train_heads(
    data: TrainingData,
    base: HeadsConfig,
    config: TrainingConfig,
    *,
    progress: ProgressCallback | None = None,
    should_stop: Callable[[], bool] | None = None,
    shot_idx: np.ndarray | None = None,
    validation_idx: np.ndarray | None = None,
) -> TrainingResult:
    """Train new heads for an atlas from its stored vectors.

    Args:
        data: every frame of the atlas (D, R, submap ids).
        base: dimensions and alpha of the untrained model; ``config.embed_dim`` sets the
            trained model's fused size (unset: ``base``'s fused input size, so the PCA start
            is a rotation of the centred active embedding and loses nothing: a calibrated
            atlas's branches are centred, and epoch 0 ranks as the active version does).
        shot_idx: the training frames (indices into ``data``); None: ``config.shots`` per
            submap by :func:`split_shots`.
        validation_idx: the frames that pick the best epoch; None: every frame not a shot
            (the job keeps its held-out stretches out of both, see :mod:`service.ml.held_out`).
        progress: called with (fraction 0..1, message) once per epoch.
        should_stop: polled once per epoch; True raises :class:`TrainingCancelled`.
    """
    started = time.perf_counter()
    labels = sorted(int(s) for s in np.unique(data.submaps))
    if len(labels) < 2:
        raise ValueError("retraining needs at least two submaps with frames")
    torch.manual_seed(config.seed)
    generator = torch.Generator().manual_seed(config.seed)
    heads_config = HeadsConfig(
        local_dim=base.local_dim,
        global_dim=base.global_dim,
        alpha=base.alpha,
        hidden_dim=base.hidden_dim,
        embed_dim=config.embed_dim or base.local_dim + base.global_dim,
    )
    heads = LoopNetHeads(heads_config, class_labels=labels)
    pca_init(heads, data.local, data.global_, seed=config.seed)

    if shot_idx is None:
        train_idx, val_idx = split_shots(data.submaps, config.shots)
    else:
        train_idx = np.unique(np.asarray(shot_idx, dtype=np.int64))
        val_idx = np.setdiff1d(np.arange(len(data.submaps)), train_idx)
    if validation_idx is not None:
        val_idx = np.setdiff1d(np.asarray(validation_idx, dtype=np.int64), train_idx)
    label_index = {label: i for i, label in enumerate(labels)}
    targets = torch.tensor([label_index[int(s)] for s in data.submaps], dtype=torch.long)
    local = torch.from_numpy(data.local)
    global_ = torch.from_numpy(data.global_)
    pairs = contrastive_pairs(data, train_idx, config.positive_window)
    # a submap without shots (inside a held-out stretch) starts from its frames' mean, so the
    # classifier can still name it; no gradient ever comes from those frames
    unshot = np.flatnonzero(~np.isin(data.submaps, data.submaps[train_idx]))
    start_idx = np.concatenate([train_idx, unshot])
    _init_prototypes(heads, local[start_idx], global_[start_idx], targets[start_idx], len(labels))
    before = evaluate(heads, data, train_idx, val_idx)

    parts = {
        "fusion": heads.fusion,
        "similarity": heads.similarity,
        "classifier": heads.classifier,
    }
    for name, module in parts.items():
        assert module is not None
        module.requires_grad_(name in config.train)
    trainable = [p for p in heads.parameters() if p.requires_grad]
    optimiser = torch.optim.AdamW(
        trainable, lr=config.learning_rate, weight_decay=config.weight_decay
    )

    def validation_score() -> tuple[float, float]:
        """(mean validation accuracy, -validation loss): accuracy first, loss breaks ties."""
        metrics = evaluate(heads, data, train_idx, val_idx, config)
        loss = metrics.pop("loss")
        return float(np.mean(list(metrics.values()))), -loss

    keep: tuple[torch.Tensor, torch.Tensor] | None = None
    if config.keep_weight > 0:  # the starting heads' cosines of the shots' non-positive pairs
        with torch.no_grad():
            start_embeddings = heads.embed(local[train_idx], global_[train_idx])
            keep = (
                start_embeddings @ start_embeddings.T,
                ~pairs[0] & ~torch.eye(len(train_idx), dtype=torch.bool),
            )
    history: list[dict[str, float]] = []
    best_state = copy.deepcopy(heads.state_dict())
    best_score = validation_score() if len(val_idx) else (0.0, 0.0)
    since_best, epochs_run, best_epoch = 0, 0, 0
    for epoch in range(config.epochs):
        if should_stop is not None and should_stop():
            raise TrainingCancelled(f"cancelled at epoch {epoch}")
        heads.train()
        optimiser.zero_grad()
        classification, contrastive = losses(
            heads,
            augment(local[train_idx], config, generator),
            augment(global_[train_idx], config, generator),
            targets[train_idx],
            pairs,
            config,
        )
        loss = config.classification_weight * classification
        loss = loss + config.contrastive_weight * contrastive
        if keep is not None:  # on the shots as stored: augmented cosines are lower
            current = heads.embed(local[train_idx], global_[train_idx])
            loss = loss + config.keep_weight * keep_loss(current, *keep)
        if config.frame_weight > 0 and len(train_idx) > 1:
            first, second = (
                heads.embed(
                    augment(local[train_idx], config, generator),
                    augment(global_[train_idx], config, generator),
                )
                for _ in range(2)
            )
            loss = loss + config.frame_weight * frame_loss(first, second, config.frame_temperature)
        torch.autograd.backward(loss)
        optimiser.step()
        heads.eval()
        epochs_run = epoch + 1
        record = {
            "epoch": epochs_run,
            "loss": loss.item(),
            "classification_loss": classification.item(),
            "contrastive_loss": contrastive.item(),
        }
        if len(val_idx):
            score = validation_score()
            record.update({"val_accuracy": score[0], "val_loss": -score[1]})
            accuracy_gain = score[0] - best_score[0]
            if accuracy_gain > 1e-9 or (
                abs(accuracy_gain) <= 1e-9 and score[1] > best_score[1] + 1e-6
            ):
                best_score, since_best, best_epoch = score, 0, epochs_run
                best_state = copy.deepcopy(heads.state_dict())
            else:
                since_best += 1
        else:
            best_state, best_epoch = copy.deepcopy(heads.state_dict()), epochs_run
        history.append(record)
        if progress is not None:
            progress(epochs_run / config.epochs, f"epoch {epochs_run}: loss {record['loss']:.4f}")
        if len(val_idx) and since_best >= config.patience:
            break

    heads.load_state_dict(best_state)
    heads.eval()
    after = evaluate(heads, data, train_idx, val_idx)
    metrics: dict[str, Any] = {
        "submaps": len(labels),
        "frames": len(data.submaps),
        "shots": int(len(train_idx)),
        "validation_frames": int(len(val_idx)),
        "epochs_run": epochs_run,
        "best_epoch": best_epoch,
        "early_stopped": epochs_run < config.epochs,
        "train_seconds": round(time.perf_counter() - started, 3),
        "first_loss": history[0]["loss"],
        "final_loss": history[-1]["loss"],
        "validation_before": before,
        "validation_after": after,
        "config": asdict(config),
    }
    return TrainingResult(heads=heads, metrics=metrics, history=history)


def _init_prototypes(
    heads: LoopNetHeads,
    local: torch.Tensor,
    global_: torch.Tensor,
    targets: torch.Tensor,
    classes: int,
) -> None:
    """Start each class weight at its shots' mean normalised fused feature (scaled)."""
    classifier: ClassificationHead | None = heads.classifier
    assert classifier is not None
    with torch.no_grad():
        fused = F.normalize(heads.fusion(local, global_), dim=-1)
        prototypes = torch.zeros(classes, fused.shape[1])
        prototypes.index_add_(0, targets, fused)
        classifier.linear.weight.copy_(10.0 * F.normalize(prototypes, dim=-1))
        classifier.linear.bias.zero_()


# what the jobs, the harness and the tests use, wherever it is defined
__all__ = [
    "TRAINABLE_PARTS",
    "TrainablePart",
    "TrainingCancelled",
    "TrainingConfig",
    "TrainingData",
    "TrainingResult",
    "contrastive_loss",
    "contrastive_pairs",
    "frame_loss",
    "keep_loss",
    "pca_init",
    "split_shots",
    "train_heads",
]
