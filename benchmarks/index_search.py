"""Exact against approximate FAISS indexes at 10k, 100k and 1M frames (synthetic embeddings).

For every size and dimension it builds each index kind from the same clustered vectors (see
``synthetic_embeddings.py``), then times single queries (one at a time, as the service asks
them) and compares their answers with exact search:

- recall@1: the exact nearest frame is ranked first; recall@5: share of the exact top 5 found
  in the top 5;
- p50 / p95 latency of one query, k = 5;
- bytes per frame of the serialized index (``faiss.write_index``) and build time (train + add).

    nice -n 10 python benchmarks/index_search.py --dims 256 --sizes 10000 100000 1000000
    nice -n 10 python benchmarks/index_search.py --dims 1408 --kinds flat ivf-sq8 ivf-sq6

``--kinds auto`` times the service's own ``AtlasIndex`` (its type chosen by size). Exact ground
truth is computed chunk by chunk, so a 1M x 1408 set is never held in memory; the Flat index
itself is skipped where it would exceed ``--flat-max-gb``. FAISS runs with ``--threads``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import faiss
import numpy as np
from synthetic_embeddings import ClusteredEmbeddings

from service.index import AtlasIndex, IndexPolicy, ivf_nlist

K = 5


@dataclass
class Kind:
    """An index kind: a factory string (by size) and the search-time settings to sweep."""

    name: str
    factory: Callable[[int], str]
    sweep: list[dict[str, int]] = field(default_factory=lambda: [{}])
    train_per_list: int = 64  # training vectors per inverted list (faiss warns below 39)

    def params(self, setting: dict[str, int], nlist: int) -> Any:
        if "nprobe" in setting:
            return faiss.SearchParametersIVF(nprobe=min(setting["nprobe"], nlist))  # type: ignore[call-arg]
        if "efSearch" in setting:
            return faiss.SearchParametersHNSW(efSearch=setting["efSearch"])  # type: ignore[attr-defined]
        return None


NPROBES = [{"nprobe": p} for p in (8, 16, 32, 64)]
KINDS = {
    "flat": Kind("flat", lambda n: "IDMap2,Flat"),
    "hnsw-sq8": Kind(
        "hnsw-sq8",
        lambda n: "IDMap2,HNSW32,SQ8",
        [{"efSearch": e} for e in (32, 64, 128)],
    ),
    "ivf-flat": Kind("ivf-flat", lambda n: f"IVF{ivf_nlist(n)},Flat", NPROBES),
    "ivf-sq8": Kind("ivf-sq8", lambda n: f"IVF{ivf_nlist(n)},SQ8", NPROBES),
    "ivf-sqfp16": Kind("ivf-sqfp16", lambda n: f"IVF{ivf_nlist(n)},SQfp16", NPROBES),
    "ivf-sq6": Kind("ivf-sq6", lambda n: f"IVF{ivf_nlist(n)},SQ6", NPROBES),
}


@dataclass
class Row:
    dim: int
    frames: int
    kind: str
    setting: str
    recall_at_1: float
    recall_at_5: float
    p50_ms: float
    p95_ms: float
    bytes_per_frame: float
    build_s: float


def exact_top_k(data: ClusteredEmbeddings, queries: np.ndarray, k: int) -> np.ndarray:
    """Exact top-k ids by inner product, chunk by chunk (never the whole set in memory)."""
    best_s = np.full((len(queries), k), -np.inf, np.float32)
    best_i = np.full((len(queries), k), -1, np.int64)
    for ids, vectors in data.chunks():
        s = queries @ vectors.T
        s_all = np.concatenate([best_s, s], axis=1)
        i_all = np.concatenate([best_i, np.broadcast_to(ids, s.shape)], axis=1)
        order = np.argsort(-s_all, axis=1, kind="stable")[:, :k]
        best_s = np.take_along_axis(s_all, order, 1)
        best_i = np.take_along_axis(i_all, order, 1)
    return best_i


def factory_string(kind: Kind, n: int, dim: int) -> str:
    return kind.factory(n).replace("{m}", str(dim // 8))


def build_index(kind: Kind, data: ClusteredEmbeddings) -> tuple[Any, float]:
    """The trained and filled index, and its build time in seconds (generation not timed)."""
    index = faiss.index_factory(
        data.dim, factory_string(kind, data.n, data.dim), faiss.METRIC_INNER_PRODUCT
    )
    elapsed = 0.0
    if not index.is_trained:
        nlist = ivf_nlist(data.n)
        sample = data.training_sample(min(data.n, kind.train_per_list * nlist))
        start = time.perf_counter()
        index.train(sample)
        elapsed += time.perf_counter() - start
        del sample
    for ids, vectors in data.chunks():
        start = time.perf_counter()
        index.add_with_ids(vectors, ids)
        elapsed += time.perf_counter() - start
    return index, elapsed


def build_auto(
    data: ClusteredEmbeddings, policy: IndexPolicy | None = None
) -> tuple[AtlasIndex, float]:
    """The service's ``AtlasIndex``, filled as ``add_stored_frames`` fills an empty one: the
    inverted file trained first on the sample of its final size, then the chunks added inside
    ``bulk()``. Build time is the index's (train + add), not the generation of the vectors."""
    index, elapsed = AtlasIndex(data.dim, policy=policy), 0.0
    with index.bulk():
        sample = index.training_ids(np.arange(data.n))
        if sample is not None:
            vectors = np.concatenate([v[np.isin(ids, sample)] for ids, v in data.chunks()])
            start = time.perf_counter()
            index.prepare(data.n, vectors)
            elapsed += time.perf_counter() - start
        for ids, vectors in data.chunks():
            start = time.perf_counter()
            index.add(ids, vectors, ["r"] * len(ids))
            elapsed += time.perf_counter() - start
    start = time.perf_counter()
    index.wait_rebuilt()
    return index, elapsed + time.perf_counter() - start


def serialized_bytes(index: Any) -> int:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "index.faiss"
        faiss.write_index(index, str(path))
        return path.stat().st_size


def time_queries(search: Callable[[np.ndarray], np.ndarray], queries: np.ndarray):
    search(queries[0])  # warm-up
    found, times = [], []
    for q in queries:
        start = time.perf_counter()
        found.append(search(q))
        times.append((time.perf_counter() - start) * 1000.0)
    return np.stack(found), np.array(times)


def score(found: np.ndarray, exact: np.ndarray) -> tuple[float, float]:
    r1 = float(np.mean(found[:, 0] == exact[:, 0]))
    r5 = float(
        np.mean([len(set(f[:K]) & set(e[:K])) / K for f, e in zip(found, exact, strict=True)])
    )
    return r1, r5


def bench_kind(
    kind_name: str,
    data: ClusteredEmbeddings,
    queries: np.ndarray,
    exact: np.ndarray,
    policy: IndexPolicy | None = None,
) -> list[Row]:
    rows = []
    if kind_name == "auto":
        atlas_index, build_s = build_auto(data, policy)
        with tempfile.TemporaryDirectory() as tmp:
            atlas_index.save(Path(tmp) / "index.faiss")
            size = (Path(tmp) / "index.faiss").stat().st_size / data.n

        def search_auto(q: np.ndarray) -> np.ndarray:
            ids = [h.frame_id for h in atlas_index.search(q, K)]
            return np.array(ids + [-1] * (K - len(ids)))

        found, times = time_queries(search_auto, queries)
        r1, r5 = score(found, exact)
        rows.append(
            Row(
                data.dim,
                data.n,
                "auto",
                atlas_index.describe(),
                r1,
                r5,
                float(np.percentile(times, 50)),
                float(np.percentile(times, 95)),
                size,
                build_s,
            )
        )
        return rows
    kind = KINDS[kind_name]
    index, build_s = build_index(kind, data)
    size = serialized_bytes(index) / data.n
    nlist = ivf_nlist(data.n)
    for setting in kind.sweep:
        params = kind.params(setting, nlist)

        def search(q: np.ndarray, params: Any = params, index: Any = index) -> np.ndarray:
            _, ids = index.search(q[None], K, params=params)
            return ids[0]

        found, times = time_queries(search, queries)
        r1, r5 = score(found, exact)
        label = factory_string(kind, data.n, data.dim)
        label += "".join(f" {k}={v}" for k, v in setting.items())
        rows.append(
            Row(
                data.dim,
                data.n,
                kind.name,
                label,
                r1,
                r5,
                float(np.percentile(times, 50)),
                float(np.percentile(times, 95)),
                size,
                build_s,
            )
        )
        print(_format(rows[-1]), flush=True)
    del index
    return rows


def _format(row: Row) -> str:
    return (
        f"| {row.dim} | {row.frames:,} | {row.setting} | {row.recall_at_1:.3f} | "
        f"{row.recall_at_5:.3f} | {row.p50_ms:.2f} | {row.p95_ms:.2f} | "
        f"{row.bytes_per_frame:,.0f} | {row.build_s:.1f} |"
    )


def add_policy_arguments(parser: argparse.ArgumentParser) -> None:
    """Flags for the inverted file's training (the service's ``IndexPolicy``, defaults
    as there), for the benchmarks that build the service's own index."""
    defaults = IndexPolicy()
    parser.add_argument("--lists-per-sqrt", type=float, default=defaults.lists_per_sqrt)
    parser.add_argument("--train-per-list", type=int, default=defaults.train_per_list)
    parser.add_argument("--kmeans-iterations", type=int, default=defaults.kmeans_iterations)


def policy_from(args: argparse.Namespace, **fixed: Any) -> IndexPolicy:
    """The ``IndexPolicy`` of :func:`add_policy_arguments`' flags (and ``fixed`` fields)."""
    return IndexPolicy(
        lists_per_sqrt=args.lists_per_sqrt,
        train_per_list=args.train_per_list,
        kmeans_iterations=args.kmeans_iterations,
        **fixed,
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    parser.add_argument("--dims", type=int, nargs="+", default=[256, 1408])
    parser.add_argument(
        "--kinds",
        nargs="+",
        default=["flat", "hnsw-sq8", "ivf-sq8", "ivf-sqfp16", "auto"],
        choices=[*KINDS, "auto"],
    )
    parser.add_argument("--queries", type=int, default=300)
    parser.add_argument("--threads", type=int, default=1, help="FAISS OpenMP threads")
    parser.add_argument("--flat-max-gb", type=float, default=6.0)
    parser.add_argument(
        "--hnsw-max-frames",
        type=int,
        default=100_000,
        help="HNSW builds slowly on 2 cores; skip it above this size",
    )
    parser.add_argument("--json", type=Path, help="append the rows to this JSON-lines file")
    add_policy_arguments(parser)
    args = parser.parse_args()
    policy = policy_from(args)

    faiss.omp_set_num_threads(args.threads)
    print(
        f"machine: {platform.machine()}, {os.cpu_count()} cores, faiss {faiss.__version__}, "
        f"{args.threads} FAISS thread(s), load average {os.getloadavg()[0]:.1f}, "
        f"{args.queries} queries, k={K}; auto: {policy}"
    )
    print(
        "| dim | frames | index | recall@1 | recall@5 | p50 ms | p95 ms | bytes/frame | build s |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for dim in args.dims:
        for n in args.sizes:
            data = ClusteredEmbeddings(n, dim)
            _, queries = data.queries(args.queries)
            exact = exact_top_k(data, queries, K)
            for kind in args.kinds:
                if kind == "flat" and n * dim * 4 > args.flat_max_gb * 1e9:
                    print(f"| {dim} | {n:,} | flat skipped: over --flat-max-gb |")
                    continue
                if kind == "hnsw-sq8" and n > args.hnsw_max_frames:
                    print(f"| {dim} | {n:,} | hnsw skipped: over --hnsw-max-frames |")
                    continue
                rows = bench_kind(kind, data, queries, exact, policy)
                if kind == "auto":
                    print(_format(rows[0]), flush=True)
                if args.json:
                    with args.json.open("a") as out:
                        for row in rows:
                            out.write(json.dumps(asdict(row)) + "\n")


if __name__ == "__main__":
    main()
