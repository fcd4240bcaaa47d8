"""Learned whitening from verified revisit pairs (Radenović et al.'s "Lw", with shrinkage).

Two frames of one place seen under different conditions (a verified loop closure) differ by
what the condition changes: lighting, season, camera. Their differences span the directions a
place-recognition embedding should ignore. The fit

1. estimates the covariance of the matching pairs' differences ``C_S`` (the intra-pair
   covariance) and shrinks it towards ``mean(eig) * I`` (Ledoit-Wolf: the intensity estimated
   from the pairs themselves, so a few pairs move the space little and many move it more);
2. whitens it out: ``W = C_S^-1/2`` divides each direction by how much revisits vary along it;
3. decorrelates the atlas's frames in the whitened space (the principal axes of the whitened
   inter-frame covariance, all kept unless ``max_dims`` says otherwise).

The transform is ``y = normalize((x - mean) @ projection)``: linear up to the normalisation, so
it folds into the heads' fusion layer (:func:`fold_into_heads`) and a model version that uses
it needs no new inference code. With shrinkage 1 it is a rotation of the centred input: the
cosine ranking of the starting embedding, up to the centring.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from service.ml.aggregation import l2_normalize
from service.ml.heads import HeadsConfig, LoopNetHeads


@dataclass(frozen=True)
class PairWhiteningConfig:
    """How the intra-pair covariance is regularised and how many axes are kept.

    Attributes:
        shrinkage: weight of ``mean(eig) * I`` in the shrunk ``C_S``, in [0, 1]; None: the
            Ledoit-Wolf estimate from the pairs.
        max_dims: axes kept (strongest inter-frame variance first); None: all of them.
    """

    shrinkage: float | None = None
    max_dims: int | None = None

    def __post_init__(self) -> None:
        if self.shrinkage is not None and not 0.0 <= self.shrinkage <= 1.0:
            raise ValueError(f"shrinkage must lie in [0, 1], got {self.shrinkage}")
        if self.max_dims is not None and self.max_dims < 2:
            raise ValueError(f"max_dims must be at least 2, got {self.max_dims}")


@dataclass
class PairWhitening:
    """A fitted transform ``y = normalize((x - mean) @ projection)``.

    Attributes:
        mean: ``dim`` centre of the atlas's vectors.
        projection: ``dim x kept`` map (whitening of the pairs, then the decorrelating axes).
        shrinkage: the intensity used (Ledoit-Wolf's when the config left it unset).
        pairs: how many pairs it was fitted on.
    """

    mean: np.ndarray
    projection: np.ndarray
    shrinkage: float
    pairs: int

    @property
    def dim(self) -> int:
        return int(self.projection.shape[1])

    @classmethod
    def fit(
        cls, vectors: np.ndarray, pairs: np.ndarray, config: PairWhiteningConfig | None = None
    ) -> PairWhitening:
        """Fit on ``n x dim`` vectors (the atlas's frames) and ``P x 2`` row indices of
        matching pairs into them (``P >= 1``)."""
        return cls.fit_differences(vectors, pair_differences(vectors, pairs), config)

    @classmethod
    def fit_differences(
        cls,
        vectors: np.ndarray,
        differences: np.ndarray,
        config: PairWhiteningConfig | None = None,
    ) -> PairWhitening:
        """Fit on ``n x dim`` atlas frames and ``P x dim`` differences of matching pairs (which
        need not be among ``vectors``: an impostor probe refits on the frames it has not held
        out, with the job's pairs)."""
        config = config or PairWhiteningConfig()
        x = np.asarray(vectors, np.float64)
        differences = np.asarray(differences, np.float64)
        if len(differences) == 0:
            raise ValueError("learned whitening needs at least one pair")
        if len(x) < 2:
            raise ValueError(f"learned whitening needs at least 2 vectors, got {len(x)}")
        mean = x.mean(0)
        # every frame lies in mean + the span of the centred frames: on an atlas with fewer
        # frames than coordinates, work in that span (exactly the same cosines, far cheaper)
        basis = _span(x - mean)
        x = (x - mean) @ basis
        differences = differences @ basis
        intra = differences.T @ differences / len(differences)
        gamma = ledoit_wolf_shrinkage(differences) if config.shrinkage is None else config.shrinkage
        target = np.trace(intra) / len(intra)
        if target <= 0.0:
            raise ValueError("the pairs' frames are identical: nothing to learn from")
        shrunk = (1.0 - gamma) * intra + gamma * target * np.eye(len(intra))
        values, axes = np.linalg.eigh(shrunk)
        values = np.clip(values, target * 1e-6, None)
        whiten = (axes / np.sqrt(values)) @ axes.T * np.sqrt(target)  # C_S^-1/2, scale kept
        whitened = x @ whiten
        inter = whitened.T @ whitened / max(len(x) - 1, 1)
        inter_values, inter_axes = np.linalg.eigh(inter)
        order = np.argsort(inter_values)[::-1]
        kept = len(order) if config.max_dims is None else min(config.max_dims, len(order))
        projection = basis @ whiten @ inter_axes[:, order[:kept]]
        return cls(
            mean=mean.astype(np.float32),
            projection=np.ascontiguousarray(projection, np.float32),
            shrinkage=float(gamma),
            pairs=int(len(differences)),
        )

    def transform(self, vectors: np.ndarray) -> np.ndarray:
        """``n x dim`` -> ``n x kept`` unit vectors."""
        x = np.asarray(vectors, np.float32)
        return l2_normalize((x - self.mean) @ self.projection)


def pair_differences(vectors: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """``P x dim`` differences of the rows ``pairs`` (``P x 2``) name, in float64 as the
    whitening fits them."""
    x = np.asarray(vectors)
    rows = np.asarray(pairs, np.int64).reshape(-1, 2)
    differences: np.ndarray = x[rows[:, 0]].astype(np.float64) - x[rows[:, 1]].astype(np.float64)
    return differences


def _span(centred: np.ndarray) -> np.ndarray:
    """``dim x r`` orthonormal basis of the rows of ``centred`` (``r <= n - 1``), or the
    identity when the rows span (almost) every coordinate."""
    n, dim = centred.shape
    if n - 1 >= dim:
        return np.eye(dim)
    values, left = np.linalg.eigh(centred @ centred.T)
    keep = values > max(values.max(), 0.0) * 1e-10
    return np.asarray(centred.T @ left[:, keep] / np.sqrt(values[keep]))


def ledoit_wolf_shrinkage(samples: np.ndarray) -> float:
    """Ledoit and Wolf's (2004) optimal intensity for shrinking the second-moment matrix of
    ``P x dim`` zero-mean ``samples`` towards ``mean(eig) * I``, in [0, 1]."""
    z = np.asarray(samples, np.float64)
    count, dim = z.shape
    moment = z.T @ z / count
    target = np.trace(moment) / dim
    distance = float(np.sum((moment - target * np.eye(dim)) ** 2)) / dim
    if distance <= 0.0:
        return 1.0
    norms = np.einsum("ij,ij->i", z, z)
    # sum_k ||z_k z_k^T - S||_F^2 = sum_k ||z_k||^4 - count * ||S||_F^2
    spread = (float(np.sum(norms**2)) - count * float(np.sum(moment**2))) / count**2 / dim
    return float(min(max(spread, 0.0), distance) / distance)


def fold_into_heads(
    base: HeadsConfig, whitening: PairWhitening, *, hidden_dim: int | None = None
) -> LoopNetHeads:
    """Heads whose embedding is ``whitening`` of the fused input ``[alpha*D, (1-alpha)*R]``:
    the fusion maps are the projection's blocks, its bias the centring, the similarity head a
    pass-through, and no classifier (nothing here trains one)."""
    config = HeadsConfig(
        local_dim=base.local_dim,
        global_dim=base.global_dim,
        alpha=base.alpha,
        hidden_dim=hidden_dim or base.hidden_dim,
        embed_dim=whitening.dim,
    )
    if whitening.projection.shape[0] != base.local_dim + base.global_dim:
        raise ValueError(
            f"a {whitening.projection.shape[0]}-d whitening does not fit heads over "
            f"{base.local_dim} + {base.global_dim} inputs"
        )
    heads = LoopNetHeads(config)
    weights = torch.from_numpy(whitening.projection.T.copy())  # kept x dim
    with torch.no_grad():
        heads.fusion.project_local.weight.copy_(weights[:, : base.local_dim])
        heads.fusion.project_global.weight.copy_(weights[:, base.local_dim :])
        heads.fusion.bias.copy_(-(weights @ torch.from_numpy(whitening.mean)))
    return heads.eval()


def fused_inputs(base: HeadsConfig, local: np.ndarray, global_: np.ndarray) -> np.ndarray:
    """The fused input ``[alpha*D, (1-alpha)*R]`` the whitening is fitted on."""
    alpha = base.alpha
    return np.concatenate([alpha * local, (1.0 - alpha) * global_], axis=1).astype(np.float32)
