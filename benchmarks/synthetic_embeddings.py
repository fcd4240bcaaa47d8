"""Synthetic place-recognition embeddings with the structure of real ones, generated in chunks.

Real LoopNet embeddings are not i.i.d. Gaussian: frames come in places (a submap is a few
consecutive frames of one place), every embedding shares a common direction (ImageNet features
of street scenes all look alike), and the place-to-place variation lives in far fewer
dimensions than the vector has. The generator reproduces those three properties:

    centre_p = normalise(mean_weight * m + (z_p * sigma) @ B)      one per place
    frame    = normalise(centre_p + 2 frame_noise g @ B + isotropic e)   ``per_place`` per place
    query    = like a frame of a random place, with fresh noise       (a revisit)

``m`` a fixed unit vector, ``B`` a random orthonormal basis of rank ``rank`` (256 at most),
``sigma_i`` decaying as ``i**-0.75`` (a CNN-like spectrum: 90% of the variance in ~145
dimensions), ``z_p`` standard normal, ``g`` and ``e`` normal with unit expected norm (``e`` in
all ``dim`` dimensions). With the defaults, frames of one place have cosine 0.82 +- 0.02, frames
of different places 0.26 +- 0.22. Every chunk is a pure function of the
seed and the chunk number, so a 1M x 1408 set (5.6 GB) never has to sit in memory at once.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np


def unit_rows(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


@dataclass(frozen=True)
class ClusteredEmbeddings:
    """``n`` embeddings of ``n / per_place`` places in ``dim`` dimensions (see module doc)."""

    n: int
    dim: int
    seed: int = 0
    per_place: int = 10
    rank: int = 256
    decay: float = 0.75
    mean_weight: float = 1.2
    frame_noise: float = 0.22
    isotropic: float = 0.15
    chunk: int = 50_000  # a multiple of per_place: no place straddles two chunks

    def _basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        rng = np.random.default_rng([self.seed, 0])
        rank = min(self.rank, self.dim)
        basis, _ = np.linalg.qr(rng.standard_normal((self.dim, rank)))
        sigma = (np.arange(1, rank + 1) ** -self.decay).astype(np.float32)
        sigma *= 2.0 / np.linalg.norm(sigma)  # place spread comparable to the shared mean
        mean = unit_rows(rng.standard_normal((1, self.dim)))[0]
        return basis.T.astype(np.float32), sigma, mean

    def _latents(self, chunk_number: int, count: int) -> np.ndarray:
        """Place latents ``z`` of one chunk's places (a pure function of the chunk number)."""
        rng = np.random.default_rng([self.seed, 1, chunk_number])
        return rng.standard_normal((count, min(self.rank, self.dim)), dtype=np.float32)

    def _centres(self, places: np.ndarray, basis: np.ndarray, sigma: np.ndarray, mean: np.ndarray):
        per_chunk = self.chunk // self.per_place
        z = np.empty((len(places), len(sigma)), np.float32)
        for number in np.unique(places // per_chunk):
            mine = places // per_chunk == number
            z[mine] = self._latents(int(number), per_chunk)[places[mine] % per_chunk]
        return unit_rows(self.mean_weight * mean + (z * sigma) @ basis)

    def _frames(self, centres: np.ndarray, basis: np.ndarray, rng: np.random.Generator):
        n = len(centres)
        g = rng.standard_normal((n, basis.shape[0]), dtype=np.float32) / np.sqrt(basis.shape[0])
        e = rng.standard_normal((n, self.dim), dtype=np.float32) / np.sqrt(self.dim)
        return unit_rows(centres + self.frame_noise * (g @ basis) * 2 + self.isotropic * e)

    def chunks(self) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """(ids, vectors) in chunks of ``chunk`` frames; ids are 0..n-1, places consecutive."""
        if self.chunk % self.per_place:
            raise ValueError("chunk must be a multiple of per_place")
        basis, sigma, mean = self._basis()
        for number, start in enumerate(range(0, self.n, self.chunk)):
            ids = np.arange(start, min(start + self.chunk, self.n), dtype=np.int64)
            places = np.unique(ids // self.per_place)
            centres = self._centres(places, basis, sigma, mean)
            rng = np.random.default_rng([self.seed, 2, number])
            yield ids, self._frames(centres[ids // self.per_place - places[0]], basis, rng)

    def queries(self, count: int) -> tuple[np.ndarray, np.ndarray]:
        """(place of each query, ``count`` query vectors): revisits of random places."""
        rng = np.random.default_rng([self.seed, 3])
        places = rng.choice(max(1, self.n // self.per_place), size=count, replace=False)
        basis, sigma, mean = self._basis()
        return places, self._frames(self._centres(places, basis, sigma, mean), basis, rng)

    def training_sample(self, count: int) -> np.ndarray:
        """The first ``count`` frames (places are i.i.d., so a prefix is a fair sample)."""
        parts, held = [], 0
        for _, vectors in self.chunks():
            parts.append(vectors[: count - held])
            held += len(parts[-1])
            if held >= count:
                break
        return np.concatenate(parts)
