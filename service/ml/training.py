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
from typing import Any, Literal

import numpy as np
import torch
import torch.nn.functional as F
from pydantic import ConfigDict, Field
from pydantic.dataclasses import dataclass as pydantic_dataclass

from service.ml.fusion import weighted_branches
from service.ml.heads import ClassificationHead, HeadsConfig, LoopNetHeads
from service.ml.impostors import sequence_positions

TrainablePart = Literal["fusion", "similarity", "classifier"]
TRAINABLE_PARTS: tuple[TrainablePart, ...] = ("fusion", "similarity", "classifier")
MAX_SEED = 2**64 - 1


@pydantic_dataclass(frozen=True, config=ConfigDict(extra="forbid"))
class TrainingConfig:
    """Parameters of one retraining run, with their bounds: the API's job parameters are this
    schema, so a value either side accepts, both do."""

    shots: int = Field(default=5, ge=1, le=100, description="Training frames (shots) per submap.")
    epochs: int = Field(
        default=100, ge=1, le=2000, description="Most epochs; early stopping may end sooner."
    )
    learning_rate: float = Field(default=3e-3, gt=0, le=1)
    weight_decay: float = Field(default=1e-4, ge=0, le=1)
    classification_weight: float = Field(
        default=1.0, ge=0, le=100, description="Cross-entropy weight."
    )
    contrastive_weight: float = Field(
        default=1.0, ge=0, le=100, description="Contrastive loss weight."
    )
    margin: float = Field(
        default=1.0, gt=0, le=2, description="Contrastive margin m (unit-sphere distance)."
    )
    embed_dim: int | None = Field(
        default=None,
        ge=2,
        le=4096,
        description="Size of the trained fused embedding; unset: the active heads' fused "
        "input size, so training starts from the active embedding itself.",
    )
    train: tuple[TrainablePart, ...] = Field(
        default_factory=lambda: TRAINABLE_PARTS,
        min_length=1,
        description="Which layers are trained; the others keep their initialisation.",
    )
    noise_std: float = Field(
        default=0.01, ge=0, le=1, description="Gaussian noise on stored vectors."
    )
    feature_dropout: float = Field(
        default=0.1, ge=0, lt=1, description="Feature dropout on stored vectors."
    )
    patience: int = Field(
        default=15, ge=1, le=1000, description="Epochs without validation gain before stopping."
    )
    seed: int = Field(default=0, ge=0)
    # Frame-level term: two augmented views of each shot must find each other among all the
    # shots (instance discrimination), so pulling a submap together cannot merge its frames.
    # Off by default: it did not stop map-only retraining from lowering Recall@1 on every K
    # (see benchmarks/RESULTS.md); the job's held-out not-worse check is the safeguard.
    frame_weight: float = Field(
        default=0.0, ge=0, le=100, description="Weight of the frame-level (instance) term."
    )
    frame_temperature: float = Field(
        default=0.1, gt=0, le=10, description="Temperature of the frame-level term."
    )
    keep_weight: float = Field(
        default=0.0,
        ge=0,
        le=100,
        description="Weight of the term that keeps the trained cosines of the shots' "
        "non-positive pairs near the starting heads' (against forgetting); 0: off.",
    )
    positive_window: int = Field(
        default=2,
        ge=0,
        le=1000,
        description="Contrastive positives: frames of one submap at most this many frames "
        "apart in their robot's sequence; 0: the first design (every pair of a submap "
        "positive, every pair of different submaps negative).",
    )

    def __post_init__(self) -> None:
        if self.classification_weight == 0 and self.contrastive_weight == 0:
            raise ValueError("at least one loss weight must be positive")
        if self.seed > MAX_SEED:  # not a schema bound: JSON Schema would round it to a float
            raise ValueError(f"seed must be in 0..{MAX_SEED} (64 bits, what torch accepts)")

    def check_fits(self, base: HeadsConfig) -> None:
        """Refuse an ``embed_dim`` the atlas's features cannot fill: the fusion starts from a
        PCA of the fused input, which has only ``local_dim + global_dim`` directions."""
        fused_input = base.local_dim + base.global_dim
        if self.embed_dim is not None and self.embed_dim > fused_input:
            raise ValueError(
                f"embed_dim {self.embed_dim} exceeds the atlas's fused input size {fused_input} "
                f"({base.local_dim} local + {base.global_dim} global)"
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


def _augment(x: torch.Tensor, config: TrainingConfig, generator: torch.Generator) -> torch.Tensor:
    """Noise and feature dropout on stored (unit) vectors, then back to unit length."""
    if config.noise_std > 0:
        x = x + config.noise_std * torch.randn(x.shape, generator=generator)
    if config.feature_dropout > 0:
        keep = torch.rand(x.shape, generator=generator) >= config.feature_dropout
        x = x * keep
    return F.normalize(x, dim=-1)


def _losses(
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


def keep_loss(embeddings: torch.Tensor, start: torch.Tensor, pairs: torch.Tensor) -> torch.Tensor:
    """Mean squared change of the cosines of ``pairs`` (a boolean ``n x n`` mask) from the
    ``start`` cosines: a distillation of the starting heads on the pairs training does not pull
    together, so pushing some places apart cannot reshape the rest of the space freely."""
    if not pairs.any():
        return embeddings.new_zeros(())
    return (embeddings @ embeddings.T - start)[pairs].pow(2).mean()


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
        classification, contrastive = _losses(
            heads,
            _augment(local[train_idx], config, generator),
            _augment(global_[train_idx], config, generator),
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
                    _augment(local[train_idx], config, generator),
                    _augment(global_[train_idx], config, generator),
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
