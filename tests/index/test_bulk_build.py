"""Re-embedding into an empty index trains the final inverted file first and adds straight into
its lists: the answers of the build through the exact stage, the journal restarted for the
caches that follow it, and a failed build leaves the serving index as it was."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from sqlalchemy.orm import Session, sessionmaker

import service.index.builder as builder
from service.index import AtlasIndex, IndexPolicy
from service.index.builder import add_stored_frames, iter_model_inputs
from service.ml.active_model import ActiveModel
from service.ml.heads import HeadsConfig, LoopNetHeads
from service.ml.pipeline import embed_vectors
from service.storage import repository as repo
from service.storage.db import make_engine, make_session_factory, transaction, upgrade_database
from service.storage.feature_store import global_vector_bytes
from service.storage.models import Frame, FrameFeatureRow
from tests.conftest import make_settings

LOCAL, GLOBAL, EMBED = 16, 48, 32
FRAMES = 3000
# Exact up to 100 frames, so 3,000 frames make an inverted file of 64 lists.
IVF = IndexPolicy(flat_max_bytes=100 * EMBED * 4, nprobe=8, background=False)


@pytest.fixture
def atlas(tmp_path: Path) -> Iterator[tuple[sessionmaker[Session], int]]:
    """An atlas of ``FRAMES`` stored frames in places of 5 (two robots), without CNN outputs
    beyond the two vectors re-embedding reads."""
    settings = make_settings(tmp_path / "data")
    settings.data_dir.mkdir(parents=True)
    upgrade_database(settings.resolved_database_url)
    engine = make_engine(settings.resolved_database_url)
    sessions = make_session_factory(engine)
    rng = np.random.default_rng(0)
    places = rng.standard_normal((FRAMES // 5, LOCAL + GLOBAL)).astype(np.float32)
    stored = np.repeat(places, 5, axis=0) + 0.3 * rng.standard_normal((FRAMES, LOCAL + GLOBAL))
    with transaction(sessions) as session:
        atlas = repo.create_atlas(session, name="campus", description="", feature_signature={})
        submap = repo.create_submap(session, atlas=atlas, name="a")
        frames = [
            Frame(
                atlas_id=atlas.id,
                submap_id=submap.id,
                robot_id=f"r{i % 2}",
                width=1,
                height=1,
                keypoint_count=0,
            )
            for i in range(FRAMES)
        ]
        session.add_all(frames)
        session.flush()
        session.add_all(
            FrameFeatureRow(
                frame_id=frame.id,
                descriptor_dim=LOCAL,
                global_dim=GLOBAL,
                keypoints=b"",
                descriptors=b"",
                scores=b"",
                local_vector=np.ascontiguousarray(row[:LOCAL], "<f4").tobytes(),
                global_vector=global_vector_bytes(np.abs(row[LOCAL:])),
            )
            for frame, row in zip(frames, stored, strict=True)
        )
        atlas_id = atlas.id
    yield sessions, atlas_id
    engine.dispose()


@pytest.fixture
def model() -> ActiveModel:
    heads = LoopNetHeads(HeadsConfig(LOCAL, GLOBAL, embed_dim=EMBED)).eval()
    generator = torch.Generator().manual_seed(0)
    with torch.no_grad():  # away from the PCA-free initialisation, like trained heads
        for parameter in heads.parameters():
            parameter.add_(0.1 * torch.randn(parameter.shape, generator=generator))
    return ActiveModel(heads)


def through_exact_stage(
    session: Session, atlas_id: int, model: ActiveModel, index: AtlasIndex, *, bulk: bool
) -> None:
    """The build before ``prepare``: every frame into the exact index, in batches, then the
    rebuilds the sizes call for (once at the end with ``bulk``, at each threshold without)."""
    with index.bulk() if bulk else contextlib.nullcontext():
        for batch in iter_model_inputs(session, atlas_id, None):
            index.add(
                batch.ids, embed_vectors(model.heads, batch.local, batch.global_), batch.robots
            )
    index.wait_rebuilt()


def queries_of(index: AtlasIndex, count: int = 60) -> np.ndarray:
    ids = np.sort(index.ids())[:: len(index.ids()) // count]
    noisy = index.vectors(ids) + 0.05 * np.random.default_rng(1).standard_normal(
        (len(ids), index.dim)
    )
    return (noisy / np.linalg.norm(noisy, axis=1, keepdims=True)).astype(np.float32)


def rebuilds(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The sizes at which indexes start rebuilding from here on."""
    sizes: list[int] = []
    original = AtlasIndex._start_rebuild

    def counted(self: AtlasIndex, size: int) -> None:
        sizes.append(size)
        original(self, size)

    monkeypatch.setattr(AtlasIndex, "_start_rebuild", counted)
    return sizes


def test_prepared_build_answers_as_the_build_through_the_exact_stage(
    atlas: tuple[sessionmaker[Session], int], model: ActiveModel, monkeypatch: pytest.MonkeyPatch
) -> None:
    sessions, atlas_id = atlas
    prepared, staged = AtlasIndex(EMBED, policy=IVF), AtlasIndex(EMBED, policy=IVF)
    started = rebuilds(monkeypatch)
    with sessions() as session:
        assert add_stored_frames(session, atlas_id, model, prepared) == FRAMES
        assert started == []  # trained first: no exact stage to rebuild from
        through_exact_stage(session, atlas_id, model, staged, bulk=True)
    assert started == [FRAMES]
    assert not prepared.exact and prepared.describe() == staged.describe()
    assert np.array_equal(np.sort(prepared.ids()), np.sort(staged.ids()))
    for query in queries_of(staged):
        assert prepared.search(query, 5) == staged.search(query, 5)
        assert prepared.search(query, 3, robot_id="r1") == staged.search(query, 3, robot_id="r1")


def test_prepared_build_recalls_as_the_incremental_one(
    atlas: tuple[sessionmaker[Session], int], model: ActiveModel
) -> None:
    sessions, atlas_id = atlas
    prepared, incremental = AtlasIndex(EMBED, policy=IVF), AtlasIndex(EMBED, policy=IVF)
    with sessions() as session:
        add_stored_frames(session, atlas_id, model, prepared)
        through_exact_stage(session, atlas_id, model, incremental, bulk=False)
    assert prepared.describe() == incremental.describe()
    ids = np.sort(incremental.ids())
    vectors = incremental.vectors(ids)
    queries = queries_of(incremental)
    exact = ids[np.argmax(queries @ vectors.T, axis=1)]
    for index in (prepared, incremental):
        found = np.array([index.search(q, 1)[0].frame_id for q in queries])
        assert (found == exact).mean() >= 0.95


def test_exact_build_is_the_incremental_one(
    atlas: tuple[sessionmaker[Session], int], model: ActiveModel
) -> None:
    sessions, atlas_id = atlas
    bulk, incremental = AtlasIndex(EMBED), AtlasIndex(EMBED)  # 32 MiB: exact at this size
    with sessions() as session:
        add_stored_frames(session, atlas_id, model, bulk)
        through_exact_stage(session, atlas_id, model, incremental, bulk=False)
    assert bulk.exact and incremental.exact
    for query in queries_of(incremental):
        assert bulk.search(query, 5) == incremental.search(query, 5)


def test_one_large_add_to_an_empty_index_builds_the_inverted_file_directly(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """As a restore or a calibration job adds every frame at once."""
    vectors = np.random.default_rng(0).standard_normal((3000, EMBED)).astype(np.float32)
    vectors /= np.linalg.norm(vectors, axis=1, keepdims=True)
    at_once, in_bulk = AtlasIndex(EMBED, policy=IVF), AtlasIndex(EMBED, policy=IVF)
    started = rebuilds(monkeypatch)
    at_once.add(np.arange(3000)[::-1], vectors[::-1], ["r"] * 3000)  # any order: same sample
    assert started == [] and not at_once.exact
    with in_bulk.bulk():
        in_bulk.add(np.arange(3000), vectors, ["r"] * 3000)
    assert started == [3000]
    for query in vectors[::97]:
        assert at_once.search(query, 5) == in_bulk.search(query, 5)


def test_the_journal_restarts_after_a_build_and_follows_what_comes_next(
    atlas: tuple[sessionmaker[Session], int], model: ActiveModel
) -> None:
    sessions, atlas_id = atlas
    index = AtlasIndex(EMBED, policy=IVF)
    first, rest = list(range(1, 2001)), list(range(2001, FRAMES + 1))
    with sessions() as session:
        add_stored_frames(session, atlas_id, model, index, frame_ids=first)
        assert not index.exact and index.changes_since(0) is None  # a cache reloads
        built = index.generation
        assert built > 0 and index.changes_since(built) == []
        add_stored_frames(session, atlas_id, model, index, frame_ids=rest)  # as a follower adds
    changes = index.changes_since(built)
    assert changes is not None and {sign for sign, _, _ in changes} == {1}
    added = np.concatenate([ids for _, ids, _ in changes])
    assert added.tolist() == rest
    vectors = np.concatenate([v for _, _, v in changes if v is not None])
    np.testing.assert_array_equal(index.stored_like(added, vectors), index.vectors(added))
    index.remove(np.array([5]))
    assert [c[0] for c in index.changes_since(built) or []][-1] == -1


def test_a_failed_build_leaves_the_serving_index_answering(
    atlas: tuple[sessionmaker[Session], int], model: ActiveModel, monkeypatch: pytest.MonkeyPatch
) -> None:
    sessions, atlas_id = atlas
    serving = AtlasIndex(EMBED, policy=IVF)
    with sessions() as session:
        add_stored_frames(session, atlas_id, model, serving)
    queries = queries_of(serving)
    before = [serving.search(q, 5) for q in queries]

    calls = 0

    def failing(*args: Any, **kwargs: Any) -> np.ndarray:
        nonlocal calls
        calls += 1
        if calls > 1:  # the sample embeds, the first batch fails
            raise RuntimeError("worker lost")
        return embed_vectors(*args, **kwargs)

    monkeypatch.setattr(builder, "embed_vectors", failing)
    rebuilt = AtlasIndex(EMBED, policy=IVF)  # a retraining's new index, beside the serving one
    with sessions() as session, pytest.raises(RuntimeError, match="worker lost"):
        add_stored_frames(session, atlas_id, model, rebuilt)
    assert [serving.search(q, 5) for q in queries] == before
    assert serving.size == FRAMES


def test_a_failed_k_means_leaves_the_index_empty_and_usable(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    index = AtlasIndex(EMBED, policy=IVF)
    vectors = np.random.default_rng(0).standard_normal((400, EMBED)).astype(np.float32)
    vectors /= np.linalg.norm(vectors, axis=1, keepdims=True)

    def untrainable(self: IndexPolicy, dim: int, size: int) -> Any:
        raise MemoryError("k-means")

    with monkeypatch.context() as patch:
        patch.setattr(IndexPolicy, "new_ivf", untrainable)
        with pytest.raises(MemoryError):
            index.prepare(400, vectors)
    assert index.exact and index.size == 0
    index.add(np.arange(50), vectors[:50], ["r"] * 50)
    assert index.search(vectors[7], 1)[0].frame_id == 7


def test_a_failed_background_rebuild_keeps_the_old_index_serving(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    index = AtlasIndex(EMBED, policy=IndexPolicy(flat_max_bytes=100 * EMBED * 4, background=True))
    vectors = np.random.default_rng(0).standard_normal((400, EMBED)).astype(np.float32)
    vectors /= np.linalg.norm(vectors, axis=1, keepdims=True)
    index.add(np.arange(90), vectors[:90], ["r"] * 90)

    def untrainable(self: IndexPolicy, dim: int, size: int) -> Any:
        class Broken:
            is_trained = False

            def train(self, _: np.ndarray) -> None:
                raise MemoryError("k-means")

        return Broken()

    monkeypatch.setattr(IndexPolicy, "new_ivf", untrainable)
    index.add(np.arange(90, 400), vectors[90:], ["r"] * 310)  # past the threshold: a rebuild
    index.wait_rebuilt()
    assert index.exact and index.size == 400
    assert all(index.search(vectors[i], 1)[0].frame_id == i for i in (3, 150, 399))
