from __future__ import annotations

from pathlib import Path

import numpy as np

from service.index import AtlasIndex


def vectors(n: int, dim: int, seed: int = 0) -> np.ndarray:
    x = np.random.default_rng(seed).normal(size=(n, dim)).astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def test_search_returns_cosine_similarity_best_first() -> None:
    index = AtlasIndex(16)
    data = vectors(50, 16)
    index.add(np.arange(100, 150), data, ["a"] * 50)
    hits = index.search(data[7], 3)
    assert hits[0].frame_id == 107 and abs(hits[0].similarity - 1.0) < 1e-5
    assert hits[0].similarity >= hits[1].similarity >= hits[2].similarity
    assert abs(hits[1].similarity - float(data[hits[1].frame_id - 100] @ data[7])) < 1e-5


def test_robot_filter_and_removal() -> None:
    index = AtlasIndex(8)
    data = vectors(6, 8, 1)
    index.add(np.arange(6), data, ["a", "b", "a", "b", "a", "b"])
    assert {h.frame_id for h in index.search(data[0], 10, robot_id="b")} == {1, 3, 5}
    assert index.search(data[0], 10, robot_id="nobody") == []
    assert index.remove(np.array([1, 3])) == 2
    assert {h.frame_id for h in index.search(data[0], 10, robot_id="b")} == {5}
    assert index.size == 4


def test_k_larger_than_index_and_empty_index() -> None:
    index = AtlasIndex(4)
    assert index.search(np.ones(4, np.float32) / 2, 5) == []
    index.add(np.array([9]), vectors(1, 4), ["r"])
    assert len(index.search(np.ones(4, np.float32) / 2, 5)) == 1


def test_save_and_load(tmp_path: Path) -> None:
    index = AtlasIndex(8)
    data = vectors(10, 8, 2)
    index.add(np.arange(10), data, ["r"] * 10)
    index.save(tmp_path / "a.faiss")
    loaded = AtlasIndex.load(tmp_path / "a.faiss", 8)
    assert sorted(loaded.ids().tolist()) == list(range(10))
    assert loaded.search(data[4], 1)[0].frame_id == 4


def test_adding_an_id_twice_indexes_it_once() -> None:
    index = AtlasIndex(8)
    data = vectors(3, 8, 3)
    assert index.add(np.arange(3), data, ["r"] * 3) == 3
    assert index.add(np.array([2, 3]), vectors(2, 8, 4), ["r", "s"]) == 1
    assert index.size == 4
    assert index.search(data[2], 1)[0].similarity > 0.9999  # the first vector of id 2 kept
