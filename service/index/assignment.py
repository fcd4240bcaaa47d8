"""Which inverted list a vector joins: its nearest centroid by inner product, scored with bf16
products where the CPU computes them natively.

faiss scores every centroid with float32 products; bf16 products (AVX512-BF16) run several
times faster where the CPU has them. Their scores, rounded to bf16, pick each vector's best two
lists and float32 dot products choose between the two: the list of float32 scoring but for near
ties below bf16's resolution (how often, and how near: benchmarks/RESULTS.md, "Figures behind
choices in the code").
Adds and :meth:`~service.index.atlas_index.AtlasIndex.stored_like` assign with the same
:class:`ListAssigner`, so a frame is always found in the list it was added to.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from service.ml.precision import cpu_has_native_bf16

BLOCK = 4096  # vectors scored at a time: their scores (BLOCK x lists) stay in the cache


class ListAssigner:
    """Assigns vectors to the lists of one trained inverted file (``index``)."""

    def __init__(self, index: Any) -> None:
        self.index = index
        self._quantizer = index.quantizer
        self._centroids: np.ndarray = index.quantizer.reconstruct_n(0, index.nlist)
        self._bf16: torch.Tensor | None = None
        if cpu_has_native_bf16() and index.nlist >= 2:
            self._bf16 = torch.from_numpy(self._centroids).t().bfloat16().contiguous()

    def assign(self, vectors: np.ndarray) -> np.ndarray:
        """The list number (int64) of each float32 row of ``vectors``."""
        if self._bf16 is None:
            lists: np.ndarray = self._quantizer.search(vectors, 1)[1][:, 0]
            return lists.astype(np.int64)
        out = np.empty(len(vectors), np.int64)
        for start in range(0, len(vectors), BLOCK):
            out[start : start + BLOCK] = self._nearest(vectors[start : start + BLOCK], self._bf16)
        return out

    def _nearest(self, block: np.ndarray, bf16: torch.Tensor) -> np.ndarray:
        """bf16 scores for the best two lists, float32 dot products to choose between them."""
        scores = torch.mm(torch.from_numpy(block).bfloat16(), bf16).float().numpy()
        rows = np.arange(len(block))
        first = scores.argmax(axis=1)  # numpy's argmax: faster than torch's here
        scores[rows, first] = -np.inf
        second = scores.argmax(axis=1)
        exact_first = np.einsum("ij,ij->i", self._centroids[first], block)
        exact_second = np.einsum("ij,ij->i", self._centroids[second], block)
        nearest: np.ndarray = np.where(exact_second > exact_first, second, first)
        return nearest
