"""A listwise loss over verified revisit pairs, with hard negatives from the atlas.

The learned whitening (:mod:`service.ml.pair_whitening`) uses the pairs only through their
covariance. This step uses them as a ranking task, what the paper's contrastive head is for:
each side of a training pair should find its partner ahead of the atlas's most similar wrong
places. It fine-tunes the starting transform ``y = normalize((x - mean) @ P0)`` as

    y = normalize(((x - mean) @ P0) @ A),    A starting at the identity,

minimising an InfoNCE loss (each side against its partner and its ``negatives`` hardest wrong
frames, mined from the current embedding of every atlas frame and re-mined at every check)
plus ``anchor * ||A - I||^2 / kept``: with tens of pairs the transform may move, not wander.
Training stops early on validation pairs kept out of the loss (their mean reciprocal rank,
scored by the caller) and keeps the best check, the start included, so a run that finds
nothing returns the starting transform. The vectors are precomputed and only ``A`` is
trained, so a job takes seconds on a CPU; the result is a :class:`PairWhitening` again, and
folds into the heads' fusion layer as the whitening does.

Wrong frames: any atlas frame outside the asking frame's own neighbourhood and outside its
partner's (same robot within ``window`` frames in its sequence), the exclusions of the gate's
pair scores (:func:`service.ml.adaptation.pair_scores`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from service.ml.pair_whitening import PairWhitening

Scorer = Callable[[np.ndarray], float]  # unit embeddings of every atlas frame -> higher better
MINE_BLOCK = 1 << 24  # similarities held at once while mining


@dataclass(frozen=True)
class PairLossConfig:
    """How the transform is fine-tuned on the pairs.

    Attributes:
        temperature: of the softmax over the partner and the negatives.
        negatives: hardest wrong frames per asking frame.
        steps: most full-batch Adam steps.
        learning_rate: Adam's.
        anchor: weight of ``||A - I||^2 / kept`` (the pull towards the starting transform).
        rank: of ``A - I`` (:class:`Turn`); None: a full matrix.
        check_every: steps between validation checks (and hard-negative mining).
        patience: checks without a better validation score before stopping.
        batch: asking frames per step, drawn anew each step (None: all of them): bounds a
            step's cost on a large atlas.
        seed: of the batches and the low-rank start.
    """

    temperature: float = 0.05
    negatives: int = 16
    steps: int = 40
    learning_rate: float = 1e-3
    anchor: float = 1.0
    rank: int | None = None
    check_every: int = 5
    patience: int = 4
    batch: int | None = 256
    seed: int = 0

    def __post_init__(self) -> None:
        if self.temperature <= 0:
            raise ValueError(f"temperature must be positive, got {self.temperature}")
        if self.negatives < 1:
            raise ValueError(f"negatives must be at least 1, got {self.negatives}")
        if self.steps < 0 or self.check_every < 1 or self.patience < 1:
            raise ValueError("steps >= 0, check_every >= 1 and patience >= 1 are required")
        if self.rank is not None and self.rank < 1:
            raise ValueError(f"rank must be at least 1, got {self.rank}")
        if self.learning_rate <= 0 or self.anchor < 0:
            raise ValueError("learning_rate must be positive and anchor not negative")


@dataclass
class PairLossResult:
    """The fine-tuned transform and what the run did."""

    transform: PairWhitening
    metrics: dict[str, Any]


@dataclass(frozen=True)
class Places:
    """Which frames are one place: each frame's robot code and rank in its robot's sequence,
    and how many frames apart one robot's frames still show the same place."""

    codes: np.ndarray
    rank: np.ndarray
    window: int

    def near(self, rows: np.ndarray) -> np.ndarray:
        """``len(rows) x n`` mask: frames of each row's robot within ``window`` of it."""
        same = (self.codes[None, :] == self.codes[rows, None]) & (
            np.abs(self.rank[None, :] - self.rank[rows, None]) <= self.window
        )
        return np.asarray(same, dtype=bool)


def hard_negatives(
    embeddings: np.ndarray, askers: np.ndarray, partners: np.ndarray, places: Places, count: int
) -> np.ndarray:
    """``len(askers) x count`` rows of the atlas most similar to each asking frame, outside its
    own place and its partner's (fewer wrong frames than ``count``: the list repeats)."""
    n = len(embeddings)
    count = min(count, n)
    block = max(1, MINE_BLOCK // max(n, 1))
    chosen = np.empty((len(askers), count), np.int64)
    for start in range(0, len(askers), block):
        ask, partner = askers[start : start + block], partners[start : start + block]
        similarity = embeddings[ask] @ embeddings.T
        similarity[places.near(ask) | places.near(partner)] = -np.inf
        top = np.argpartition(-similarity, count - 1, axis=1)[:, :count]
        order = np.argsort(-np.take_along_axis(similarity, top, axis=1), axis=1)
        top = np.take_along_axis(top, order, axis=1)
        # a list with fewer wrong frames than ``count`` repeats its best rather than a right one
        allowed = np.isfinite(np.take_along_axis(similarity, top, axis=1))
        top = np.where(allowed, top, top[:, :1])
        chosen[start : start + block] = top
    return chosen


def listwise_loss(
    embedded: torch.Tensor,
    askers: torch.Tensor,
    partners: torch.Tensor,
    negatives: torch.Tensor,
    temperature: float,
) -> torch.Tensor:
    """InfoNCE: mean over asking frames of ``-log softmax`` of the partner's similarity among
    the partner's and the negatives' (rows of ``embedded``, unit vectors)."""
    ask = embedded[askers]
    positive = (ask * embedded[partners]).sum(-1, keepdim=True)
    wrong = torch.einsum("pd,pmd->pm", ask, embedded[negatives])
    logits = torch.cat([positive, wrong], dim=1) / temperature
    return F.cross_entropy(logits, torch.zeros(len(logits), dtype=torch.long))


class Turn(torch.nn.Module):
    """The trained map ``A = I + L R^T`` (rank ``rank``; None: ``A = I + M``, every entry
    free), starting at the identity (``L = 0``, ``M = 0``): a low rank is the cheaper and the
    stronger pull towards the start on a large atlas."""

    def __init__(self, kept: int, rank: int | None) -> None:
        super().__init__()
        self.full: torch.nn.Parameter | None = None
        if rank is None or rank >= kept:
            self.full = torch.nn.Parameter(torch.zeros(kept, kept))
            rank = 0
        self.left = torch.nn.Parameter(torch.zeros(kept, rank))
        self.right = torch.nn.Parameter(torch.randn(kept, rank) / np.sqrt(kept))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.full is not None:
            return x + x @ self.full
        return x + (x @ self.left) @ self.right.T

    def penalty(self) -> torch.Tensor:
        """``||A - I||_F^2``."""
        if self.full is not None:
            return self.full.pow(2).sum()
        return torch.trace((self.left.T @ self.left) @ (self.right.T @ self.right))

    def matrix(self) -> np.ndarray:
        """``A`` as a ``kept x kept`` array."""
        with torch.no_grad():
            change = self.full if self.full is not None else self.left @ self.right.T
            return (torch.eye(len(change)) + change).numpy()


def batch_loss(
    base: torch.Tensor,
    turn: Turn,
    askers: np.ndarray,
    partners: np.ndarray,
    negatives: np.ndarray,
    config: PairLossConfig,
) -> torch.Tensor:
    """:func:`listwise_loss` of ``askers`` (rows of ``base``), embedding each row involved once."""
    rows, inverse = np.unique(
        np.concatenate([askers, partners, negatives.ravel()]), return_inverse=True
    )
    count = len(askers)
    out = F.normalize(turn(base[torch.from_numpy(rows)]), dim=-1)
    return listwise_loss(
        out,
        torch.from_numpy(inverse[:count]),
        torch.from_numpy(inverse[count : 2 * count]),
        torch.from_numpy(inverse[2 * count :].reshape(negatives.shape)),
        config.temperature,
    )


def both_ways(pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each side of ``P x 2`` pairs as an asking frame, with the other as its partner."""
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    return np.concatenate([pairs[:, 0], pairs[:, 1]]), np.concatenate([pairs[:, 1], pairs[:, 0]])


def fine_tune(
    vectors: np.ndarray,
    start: PairWhitening,
    train: np.ndarray,
    places: Places,
    score: Scorer | None,
    config: PairLossConfig | None = None,
) -> PairLossResult:
    """Fine-tune ``start`` on ``train`` (``P x 2`` rows of ``vectors``, the atlas's fused
    inputs) with :func:`listwise_loss`; ``score`` judges the embedding of every atlas frame at
    each check (e.g. the validation pairs' mean reciprocal rank) and the best check is kept.
    ``score`` None: ``config.steps`` steps, the last kept (a run whose length an earlier
    run with validation chose)."""
    config = config or PairLossConfig()
    started = time.perf_counter()
    torch.manual_seed(config.seed)
    generator = np.random.default_rng(config.seed)
    base = torch.from_numpy(
        ((np.asarray(vectors, np.float32) - start.mean) @ start.projection).astype(np.float32)
    )
    kept = base.shape[1]
    turn = Turn(kept, config.rank)
    optimiser = torch.optim.Adam(turn.parameters(), lr=config.learning_rate)
    askers, partners = both_ways(train)

    def embed_all() -> np.ndarray:
        with torch.no_grad():
            return F.normalize(turn(base), dim=-1).numpy()

    def judge(embedded: np.ndarray) -> float:
        return score(embedded) if score is not None else float(step)

    step = 0
    embedded = embed_all()
    best_score, best_step, best = judge(embedded), 0, turn.matrix()
    first_score, checks_without_gain, losses = best_score, 0, []
    while step < config.steps and checks_without_gain < config.patience and len(askers):
        negatives = hard_negatives(embedded, askers, partners, places, config.negatives)
        for _ in range(min(config.check_every, config.steps - step)):
            batch = np.arange(len(askers))
            if config.batch is not None and config.batch < len(askers):
                batch = np.sort(generator.choice(len(askers), config.batch, replace=False))
            optimiser.zero_grad()
            loss = batch_loss(base, turn, askers[batch], partners[batch], negatives[batch], config)
            loss = loss + config.anchor * turn.penalty() / kept
            torch.autograd.backward(loss)
            optimiser.step()
            losses.append(float(loss.detach()))
            step += 1
        embedded = embed_all()
        current = judge(embedded)
        if current > best_score:
            best_score, best_step, best = current, step, turn.matrix()
            checks_without_gain = 0
        else:
            checks_without_gain += 1
    projection = start.projection @ best
    tuned = PairWhitening(
        mean=start.mean,
        projection=np.ascontiguousarray(projection, np.float32),
        shrinkage=start.shrinkage,
        pairs=start.pairs,
    )
    metrics = {
        "pair_loss_steps": step,
        "pair_loss_best_step": best_step,
        **(
            {
                "pair_loss_validation_start": round(first_score, 4),
                "pair_loss_validation_best": round(best_score, 4),
            }
            if score is not None
            else {}
        ),
        "pair_loss_first": round(losses[0], 4) if losses else None,
        "pair_loss_last": round(losses[-1], 4) if losses else None,
        "pair_loss_seconds": round(time.perf_counter() - started, 3),
    }
    return PairLossResult(tuned, metrics)


def identity_start(vectors: np.ndarray, pairs: int) -> PairWhitening:
    """The calibrated fused input itself, centred: a start for the pair loss without whitening
    (its cosines are those of the centred input)."""
    x = np.asarray(vectors, np.float32)
    dim = x.shape[1]
    return PairWhitening(
        mean=x.mean(0), projection=np.eye(dim, dtype=np.float32), shrinkage=1.0, pairs=pairs
    )
