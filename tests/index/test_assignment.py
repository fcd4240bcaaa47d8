"""Lists chosen with bf16 scores are float32 scoring's but for near ties; without native bf16,
faiss's own assignment."""

from __future__ import annotations

from typing import Any

import faiss
import numpy as np
import pytest

import service.index.assignment as assignment
from service.index.assignment import ListAssigner


def trained(n: int = 20_000, dim: int = 64, nlist: int = 64) -> tuple[Any, np.ndarray]:
    rng = np.random.default_rng(0)
    centres = rng.standard_normal((n // 10, dim))
    x = np.repeat(centres, 10, axis=0) + 0.5 * rng.standard_normal((n, dim))
    x = (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)
    index = faiss.index_factory(dim, f"IVF{nlist},SQfp16", faiss.METRIC_INNER_PRODUCT)
    index.train(x[::4])
    return index, x


def test_bf16_lists_are_float32_ones_but_for_near_ties() -> None:
    index, x = trained()
    scores, exact = index.quantizer.search(x, 2)
    lists = ListAssigner(index).assign(x)
    differ = lists != exact[:, 0]
    assert differ.mean() <= 0.01
    assert (scores[differ, 0] - scores[differ, 1] < 0.005).all()  # only near ties move
    centroids = index.quantizer.reconstruct_n(0, index.nlist)
    chosen = np.einsum("ij,ij->i", centroids[lists], x)
    assert (scores[:, 0] - chosen < 0.005).all()


def test_without_native_bf16_the_lists_are_faiss_own(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(assignment, "cpu_has_native_bf16", lambda: False)
    index, x = trained()
    _, exact = index.quantizer.search(x, 1)
    np.testing.assert_array_equal(ListAssigner(index).assign(x), exact[:, 0])


def test_a_vector_is_assigned_alike_alone_and_in_a_block() -> None:
    index, x = trained()
    assigner = ListAssigner(index)
    together = assigner.assign(x[:5000])
    alone = np.array([assigner.assign(x[i : i + 1])[0] for i in range(0, 5000, 7)])
    np.testing.assert_array_equal(alone, together[::7])
