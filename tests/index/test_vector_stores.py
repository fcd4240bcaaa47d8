"""Every behaviour the service asks of a vector store, against both: the FAISS ``AtlasIndex``
and ``PgVectorStore`` (the embedded PostgreSQL with pgvector of tests/services.py)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from sqlalchemy import create_engine, text
from sqlalchemy.orm import sessionmaker

from service.index import AtlasIndex
from service.index.pgvector_store import PgVectorPolicy, PgVectorStore, VectorFilter
from service.index.store import VectorStore


def vectors(n: int, dim: int, seed: int = 0) -> np.ndarray:
    x = np.random.default_rng(seed).normal(size=(n, dim)).astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


@pytest.fixture
def pg_sessions(pgvector_url: str) -> Iterator[sessionmaker[Any]]:
    engine = create_engine(pgvector_url)
    yield sessionmaker(engine)
    engine.dispose()


@pytest.fixture(params=["faiss", "pgvector"])
def make_store(request: pytest.FixtureRequest) -> Any:
    """A factory of empty stores of one kind: ``make_store(dim, version=1, **policy)``."""
    if request.param == "faiss":
        return lambda dim, version=1, **_: AtlasIndex(dim)
    sessions = request.getfixturevalue("pg_sessions")

    def make(dim: int, version: int = 1, **policy: Any) -> PgVectorStore:
        store = PgVectorStore(sessions, 1, version, dim, PgVectorPolicy(**policy), linked=False)
        store.create()
        return store

    return make


def ids_of(hits: list[Any]) -> list[int]:
    return [h.frame_id for h in hits]


def test_search_returns_cosine_similarity_best_first(make_store: Any) -> None:
    store: VectorStore = make_store(16)
    data = vectors(50, 16)
    assert store.add(np.arange(100, 150), data, ["a"] * 50) == 50
    hits = store.search(data[7], 3)
    assert hits[0].frame_id == 107 and abs(hits[0].similarity - 1.0) < 1e-5
    assert hits[0].similarity >= hits[1].similarity >= hits[2].similarity
    assert abs(hits[1].similarity - float(data[hits[1].frame_id - 100] @ data[7])) < 1e-5
    exact = np.argsort(-(data @ data[7]))[:10] + 100
    assert ids_of(store.search(data[7], 10)) == exact.tolist()


def test_filters_exclusions_and_removals(make_store: Any) -> None:
    store: VectorStore = make_store(8)
    data = vectors(6, 8, 1)
    store.add(np.arange(6), data, ["a", "b", "a", "b", "a", "b"])
    assert set(ids_of(store.search(data[0], 10, robot_id="b"))) == {1, 3, 5}
    assert store.search(data[0], 10, robot_id="nobody") == []
    assert set(ids_of(store.search(data[0], 10, include=np.array([0, 1, 2])))) == {0, 1, 2}
    only = store.search(data[0], 10, include=np.array([0, 1, 2]), exclude=np.array([0]))
    assert set(ids_of(only)) == {1, 2}
    assert 0 not in ids_of(store.search(data[0], 10, exclude=np.array([0, 4])))
    assert store.search(data[0], 10, include=np.array([], np.int64)) == []
    assert store.remove(np.array([1, 3])) == 2
    assert ids_of(store.search(data[0], 10, robot_id="b")) == [5]
    assert store.size == 4 and sorted(store.ids().tolist()) == [0, 2, 4, 5]


def test_adding_an_id_twice_keeps_the_first(make_store: Any) -> None:
    store: VectorStore = make_store(8)
    data = vectors(3, 8, 3)
    assert store.add(np.arange(3), data, ["r"] * 3) == 3
    assert store.add(np.array([2, 3]), vectors(2, 8, 4), ["r", "s"]) == 1
    assert store.size == 4
    assert store.search(data[2], 1)[0].similarity > 0.9999


def test_k_larger_than_the_store_and_an_empty_store(make_store: Any) -> None:
    store: VectorStore = make_store(4)
    assert store.search(np.ones(4, np.float32) / 2, 5) == []
    store.add(np.array([9]), vectors(1, 4), ["r"])
    assert len(store.search(np.ones(4, np.float32) / 2, 5)) == 1


def test_export_and_import_answer_alike(make_store: Any) -> None:
    """A snapshot's export (every id and vector) imported into a fresh store."""
    store: VectorStore = make_store(8)
    data = vectors(40, 8, 5)
    store.add(np.arange(40) * 3, data, ["r"] * 40)
    ids, held = store.entries()
    assert sorted(ids.tolist()) == (np.arange(40) * 3).tolist()
    copy: VectorStore = make_store(8, version=2)
    copy.add(ids, held, ["r"] * len(ids))
    for q in data[:5]:
        assert ids_of(copy.search(q, 5)) == ids_of(store.search(q, 5))
    np.testing.assert_allclose(store.vectors(ids[:3]), held[:3], atol=1e-6)


def test_journal_of_adds_and_removals(make_store: Any) -> None:
    """What the sequence maps follow: this process's changes since a generation."""
    store: VectorStore = make_store(8)
    start = store.generation
    data = vectors(4, 8, 6)
    store.add(np.arange(4), data, ["r"] * 4)
    store.remove(np.array([1]))
    changes = store.changes_since(start)
    assert changes is not None and [sign for sign, _, _ in changes] == [1, -1]
    np.testing.assert_allclose(changes[0][2], store.stored_like(np.arange(4), data), atol=1e-6)


@pytest.fixture
def big(pg_sessions: sessionmaker[Any]) -> tuple[PgVectorStore, np.ndarray]:
    """3,000 frames of 3 robots over 300 s, searched through HNSW (exact below 100)."""
    store = PgVectorStore(
        pg_sessions, 7, 1, 32, PgVectorPolicy(exact_below=100, ef_search=10), linked=False
    )
    store.create()
    data = vectors(3000, 32, 9)
    ids = np.arange(3000)
    store.add(ids, data, [f"r{i % 3}" for i in ids], times=ids * 0.1)
    return store, data


def test_hnsw_filtered_search_returns_k_results(big: tuple[PgVectorStore, np.ndarray]) -> None:
    """Iterative scans: a filter that drops most candidates still yields k answers."""
    store, data = big
    assert not store.exact
    for q in data[:20]:
        hits = store.search(q, 10, where=VectorFilter(since=100.0, until=110.0))
        assert len(hits) == 10 and all(1000 <= h.frame_id <= 1100 for h in hits)
        own = store.search(q, 10, where=VectorFilter(robot_id="r1"))
        assert len(own) == 10 and all(h.frame_id % 3 == 1 for h in own)
    tiny = store.search(data[0], 10, where=VectorFilter(since=0.0, until=0.35))
    assert sorted(ids_of(tiny)) == [0, 1, 2, 3]  # fewer allowed than k: all of them


def test_halfvec_above_2000_dimensions(pg_sessions: sessionmaker[Any]) -> None:
    store = PgVectorStore(pg_sessions, 8, 1, 2048, linked=False)
    store.create()
    data = vectors(5, 2048, 10)
    store.add(np.arange(5), data, ["r"] * 5)
    assert store.kind == "halfvec" and store.search(data[3], 1)[0].frame_id == 3
    with pg_sessions() as session:
        kind = session.scalar(
            text(
                "SELECT format_type(atttypid, atttypmod) FROM pg_attribute"
                f" WHERE attrelid = '{store.table}'::regclass AND attname = 'embedding'"
            )
        )
    assert kind == "halfvec(2048)"
