"""VLAD: residuals of a frame's descriptors to a small vocabulary, one block per word.

The vocabulary (K centroids) is learned by k-means on a sample of an atlas's stored
descriptors, so no label and no query is needed. A frame's vector is

    v_k = sum over descriptors x assigned to word k of (x - c_k)

each block L2-normalised (intra-normalisation: one bursty word cannot dominate), then the
signed square root of every coordinate (power normalisation), then the whole vector
L2-normalised. Detection scores are not used: every kept keypoint counts once.
"""

from __future__ import annotations

import faiss
import numpy as np
import torch

from service.ml.aggregation import l2_normalize


def fit_vocabulary(
    sample: np.ndarray, *, words: int = 64, seed: int = 0, iterations: int = 20
) -> np.ndarray:
    """``K x d`` float32 centroids of k-means on ``sample`` (``N x d``), deterministic per seed."""
    if words < 1:
        raise ValueError(f"a vocabulary needs at least one word, got {words}")
    data = np.ascontiguousarray(sample, np.float32)
    if len(data) < words:
        raise ValueError(f"{len(data)} descriptors cannot train a vocabulary of {words} words")
    kmeans = faiss.Kmeans(
        data.shape[1],
        words,
        niter=iterations,
        seed=seed,
        max_points_per_centroid=max(256, len(data) // words + 1),
        verbose=False,
    )
    kmeans.train(data)
    return np.ascontiguousarray(kmeans.centroids, np.float32)


class VladAggregator:
    """VLAD over fixed centroids: ``N x d`` descriptors -> ``K*d`` unit vector."""

    name = "vlad"

    def __init__(self, centroids: np.ndarray) -> None:
        if centroids.ndim != 2 or len(centroids) < 1:
            raise ValueError(f"centroids must be K x d, got shape {centroids.shape}")
        self.centroids = np.ascontiguousarray(centroids, np.float32)
        self._centroid_sq = (self.centroids**2).sum(1)

    @property
    def words(self) -> int:
        return len(self.centroids)

    @property
    def descriptor_dim(self) -> int:
        return int(self.centroids.shape[1])

    @property
    def dim(self) -> int:
        return self.words * self.descriptor_dim

    def assign(self, descriptors: np.ndarray) -> np.ndarray:
        """Index of the nearest centroid (Euclidean) of every descriptor."""
        scores = descriptors @ self.centroids.T - 0.5 * self._centroid_sq
        return np.asarray(scores.argmax(1), np.int64)

    def aggregate(self, descriptors: np.ndarray, scores: np.ndarray | None = None) -> np.ndarray:
        """The VLAD vector of one frame; a frame without descriptors gives the zero vector.

        A calibration aggregates every stored frame, so the two steps numpy is slow at go
        through torch: converting stored float16 descriptors (ten times faster) and summing
        each word's descriptors (a scatter instead of a one-hot product).
        """
        if descriptors.ndim != 2 or descriptors.shape[1] != self.descriptor_dim:
            raise ValueError(
                f"descriptors must be N x {self.descriptor_dim}, got {descriptors.shape}"
            )
        if len(descriptors) == 0:
            return np.zeros(self.dim, np.float32)
        x = _as_float32(descriptors)
        words = self.assign(x.numpy())
        blocks = torch.zeros(self.centroids.shape).index_add_(0, torch.from_numpy(words), x)
        counts = np.bincount(words, minlength=self.words).astype(np.float32)
        residuals = blocks.numpy() - counts[:, None] * self.centroids
        flat = l2_normalize(residuals, axis=1).reshape(-1)
        return l2_normalize(np.sign(flat) * np.sqrt(np.abs(flat)))

    def state(self) -> dict[str, np.ndarray]:
        return {"centroids": self.centroids}


def _as_float32(descriptors: np.ndarray) -> torch.Tensor:
    """``descriptors`` as a float32 tensor (stored blobs are read-only: those are copied first,
    as torch only wraps writable arrays)."""
    return torch.from_numpy(np.require(descriptors, requirements=("C", "W"))).to(torch.float32)
