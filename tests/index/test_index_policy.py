"""The index type follows the atlas's size; every type keeps the service's guarantees."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from service.index import AtlasIndex, IndexPolicy, ivf_nlist

DIM = 32
# Exact up to 100 frames at 32-d (100 x 32 x 4 bytes), so a few thousand frames reach the IVF.
SMALL = IndexPolicy(flat_max_bytes=100 * DIM * 4, nprobe=8, background=False)


def clustered(n: int, seed: int = 0, per_place: int = 5) -> np.ndarray:
    """Unit vectors in places of ``per_place`` frames around random centres (like frames of a
    submap), so nearest neighbours are well defined but not trivially far apart."""
    rng = np.random.default_rng(seed)
    centres = rng.normal(size=(n // per_place + 1, DIM))
    x = centres[np.arange(n) // per_place] + 0.3 * rng.normal(size=(n, DIM))
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def filled(n: int, policy: IndexPolicy = SMALL, robots: int = 1) -> tuple[AtlasIndex, np.ndarray]:
    index = AtlasIndex(DIM, policy=policy)
    data = clustered(n)
    for start in range(0, n, 500):  # in chunks, as a rebuild from the database adds them
        ids = np.arange(start, min(start + 500, n))
        index.add(ids + 1000, data[ids], [f"r{i % robots}" for i in ids])
    return index, data


def exact_top1(data: np.ndarray, queries: np.ndarray) -> np.ndarray:
    return np.argmax(queries @ data.T, axis=1) + 1000


def test_policy_picks_the_finest_codes_that_fit_the_budget() -> None:
    assert IndexPolicy().quantizer(256) == "SQfp16"
    assert IndexPolicy().quantizer(1408) == "SQ8"  # the default budget favours recall
    policy = IndexPolicy(bytes_per_frame=1100)
    assert policy.quantizer(256) == "SQfp16"  # 512 + 8 bytes
    assert policy.quantizer(1024) == "SQ8"
    assert policy.quantizer(1408) == "SQ6"  # 1056 + 8 bytes
    assert policy.quantizer(4096) == "SQ4"
    assert policy.flat_max(256) == 32768
    assert ivf_nlist(1_000_000) == 1024 and ivf_nlist(100_000) == 256
    assert ivf_nlist(1_000_000, per_sqrt=4.0) == 4096
    assert ivf_nlist(1000) == 16  # never fewer than 39 training vectors per list ... or 16 lists


def test_small_atlas_is_exact_and_large_one_approximate() -> None:
    small, _ = filled(100)
    assert small.exact
    large, _ = filled(3000)
    assert not large.exact and large.size == 3000
    assert large.describe().startswith(f"IVF{ivf_nlist(3000)},SQfp16")


def test_approximate_index_finds_the_exact_neighbours() -> None:
    index, data = filled(3000)
    queries = clustered(3000, seed=0)[::30] + 0.05 * np.random.default_rng(9).normal(
        size=(100, DIM)
    ).astype(np.float32)
    queries /= np.linalg.norm(queries, axis=1, keepdims=True)
    found = np.array([index.search(q, 1)[0].frame_id for q in queries])
    assert np.mean(found == exact_top1(data, queries)) >= 0.95


def test_growth_retrains_the_inverted_file() -> None:
    index, _ = filled(1000)
    first = index.describe()
    for start in range(1000, 6000, 500):
        ids = np.arange(start, start + 500) + 1000
        index.add(ids, clustered(500, seed=start), ["r"] * 500)
    assert index.size == 6000
    assert index.describe() != first  # more lists for the larger atlas
    assert sorted(index.ids().tolist()) == list(range(1000, 7000))


def test_removal_idempotent_add_and_shrinking_back_to_exact() -> None:
    index, data = filled(3000)
    assert index.add(np.array([1000, 1001]), data[:2], ["r0", "r0"]) == 0  # already held
    assert index.remove(np.arange(1000, 1010)) == 10
    assert index.size == 2990
    assert all(h.frame_id >= 1010 for h in index.search(data[0], 5))
    assert not set(range(1000, 1010)) & set(index.ids().tolist())
    index.remove(np.arange(1010, 3960))  # 40 left: below half the exact threshold
    assert index.exact and sorted(index.ids().tolist()) == list(range(3960, 4000))
    assert index.search(data[2990], 1)[0].frame_id == 3990


def test_filtered_search_reaches_a_rare_robots_frames() -> None:
    index, data = filled(3000, robots=1)
    rare = np.arange(1000, 4000, 97)  # 31 frames spread over the atlas, another robot's
    index.set_robots({int(i): "rare" for i in rare})
    hits = index.search(data[5], 10, robot_id="rare")
    assert len(hits) == 10 and {h.frame_id for h in hits} <= set(rare.tolist())
    best = rare[np.argmax(data[rare - 1000] @ data[5])]
    assert hits[0].frame_id == best  # every rare frame was scored, not only the probed lists
    assert index.search(data[5], 5, robot_id="nobody") == []


@pytest.mark.parametrize("n", [100, 3000])
def test_save_load_round_trip_is_identical(tmp_path: Path, n: int) -> None:
    index, data = filled(n)
    index.save(tmp_path / "a.faiss")
    loaded = AtlasIndex.load(tmp_path / "a.faiss", DIM, SMALL)
    assert loaded.exact == index.exact
    assert sorted(loaded.ids().tolist()) == sorted(index.ids().tolist())
    for q in data[::37]:
        assert loaded.search(q, 5) == index.search(q, 5)


def test_building_twice_gives_the_same_answers() -> None:
    a, data = filled(3000)
    b, _ = filled(3000)
    for q in data[::53]:
        assert a.search(q, 5) == b.search(q, 5)


def test_background_rebuild_keeps_serving_and_replays_changes() -> None:
    policy = IndexPolicy(flat_max_bytes=100 * DIM * 4, nprobe=8, background=True)
    index, data = filled(1000, policy)
    index.wait_rebuilt()
    assert not index.exact
    before = index.describe()
    grow = clustered(4000, seed=7)
    index.add(np.arange(5000, 9000), grow, ["r0"] * 4000)  # 5000 frames: calls for more lists
    # while the new index trains, the old one answers, and changes are logged
    assert index.search(data[3], 1)[0].frame_id == 1003
    index.remove(np.array([1003]))
    index.add(np.array([20_000]), data[3:4], ["r0"])
    index.wait_rebuilt()
    assert index.describe() != before
    assert index.size == 5000
    ids = set(index.ids().tolist())
    assert 1003 not in ids and 20_000 in ids
    assert index.search(data[3], 1)[0].frame_id == 20_000


def test_background_and_foreground_builds_agree() -> None:
    background = IndexPolicy(flat_max_bytes=100 * DIM * 4, nprobe=8, background=True)
    a, data = filled(3000, background)
    a.wait_rebuilt()
    b, _ = filled(3000)
    assert a.describe() == b.describe()
    for q in data[::61]:
        hits_a, hits_b = a.search(q, 1), b.search(q, 1)
        assert hits_a[0].frame_id == hits_b[0].frame_id
        assert abs(hits_a[0].similarity - hits_b[0].similarity) < 1e-3


def test_bulk_load_rebuilds_once_at_its_final_size(monkeypatch: pytest.MonkeyPatch) -> None:
    """Adds inside bulk() pass every size threshold without a rebuild; leaving it rebuilds
    once, to the type the final size calls for, and searches as a chunk-by-chunk fill does."""
    rebuilds: list[int] = []
    original = AtlasIndex._start_rebuild

    def counted(self: AtlasIndex, size: int) -> None:
        rebuilds.append(size)
        original(self, size)

    monkeypatch.setattr(AtlasIndex, "_start_rebuild", counted)
    chunked, data = filled(6000)
    assert len(rebuilds) >= 2  # flat -> IVF, then more lists as it grew
    rebuilds.clear()
    bulk = AtlasIndex(DIM, policy=SMALL)
    with bulk.bulk():
        for start in range(0, 6000, 500):
            ids = np.arange(start, start + 500)
            bulk.add(ids + 1000, data[ids], ["r0"] * 500)
        assert bulk.exact and not rebuilds
    assert rebuilds == [6000]
    assert bulk.describe() == chunked.describe() and bulk.size == 6000
    queries = data[::50] + 0.05 * clustered(120, seed=1)
    found = np.array([bulk.search(q, 1)[0].frame_id for q in queries])
    assert (found == exact_top1(data, queries)).mean() >= 0.9


def test_fewer_lists_per_square_root() -> None:
    assert ivf_nlist(1_000_000, per_sqrt=0.5) == 512
    index, _ = filled(
        3000, IndexPolicy(flat_max_bytes=100 * DIM * 4, lists_per_sqrt=0.5, background=False)
    )
    assert index.describe().startswith(f"IVF{ivf_nlist(3000, 0.5)},")
