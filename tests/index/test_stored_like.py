"""The vectors the index holds for frames just added, found without the id map over every frame,
are exactly what reading them back gives: flat and inverted file."""

from __future__ import annotations

import numpy as np
import pytest

from service.index import AtlasIndex, IndexPolicy


def unit(rng: np.random.Generator, n: int, d: int) -> np.ndarray:
    v = rng.standard_normal((n, d)).astype(np.float32)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


@pytest.mark.parametrize("flat_max_bytes", [1 << 30, 64 * 4 * 100])
def test_stored_like_equals_reading_back(flat_max_bytes: int) -> None:
    rng = np.random.default_rng(0)
    policy = IndexPolicy(flat_max_bytes=flat_max_bytes, background=False, train_per_list=8)
    index = AtlasIndex(64, policy=policy)
    index.add(np.arange(2000), unit(rng, 2000, 64), ["r"] * 2000)
    generation = index.generation
    added = unit(rng, 5, 64)
    ids = np.arange(5000, 5005)
    index.add(ids, added, ["r"] * 5)
    assert index.exact == (flat_max_bytes > 1 << 20)
    changes = index.changes_since(generation)
    assert changes is not None and [c[0] for c in changes] == [1]
    np.testing.assert_array_equal(changes[0][1], ids)
    np.testing.assert_array_equal(index.stored_like(ids, changes[0][2]), index.vectors(ids))
