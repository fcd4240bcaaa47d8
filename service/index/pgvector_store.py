"""An atlas's vectors in PostgreSQL with pgvector: one table per atlas and model version.

The table lives beside the frames, in the same database: a frame's vector is inserted in the
frame's own transaction (no second copy to keep in step: every replica finds it once the
transaction commits), its row is deleted with the frame (a foreign key with ``ON DELETE
CASCADE``), backups are ``pg_dump`` and replicas are PostgreSQL's own. Re-embedding for another
model version fills that version's table beside the active one; activating the version switches
the table every replica searches together with the heads.

Columns: the frame id, and what the service filters on (robot, submap, capture time) copied
from the frame row, so a filtered search is one SQL query the HNSW scan filters as it goes.
Vectors are ``vector(d)`` (float32), or ``halfvec(d)`` above 2000 dimensions (HNSW's limit for
``vector``). Search is by inner product on unit vectors (``<#>``, cosine):

- an atlas smaller than ``exact_below`` frames, or a search restricted to at most that many
  listed frames, is exact (a scan of the rows, not the index);
- otherwise the HNSW index with ``hnsw.iterative_scan = strict_order``: a filter that drops
  most candidates makes the scan continue until ``k`` rows pass it (up to
  ``hnsw.max_scan_tuples``); an answer still shorter than asked is repeated exactly, so a
  filtered search never comes back silently short.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
from sqlalchemy import text
from sqlalchemy.orm import Session, sessionmaker

from service.index.atlas_index import Hit
from service.index.journal import Change, ChangeJournal
from service.index.pg_copy import copy_rows, insert_rows
from service.index.pgvector_sql import (
    PgVectorPolicy,
    VectorFilter,
    available,
    drop_atlas_tables,
    ensure_extension,
    literal,
    parse,
    table_name,
    where_clauses,
)

__all__ = [
    "PgVectorPolicy",
    "PgVectorStore",
    "VectorFilter",
    "available",
    "drop_atlas_tables",
    "ensure_extension",
    "table_name",
]

ESTIMATED_ABOVE = 100_000  # tables larger than this are sized by the planner's estimate
HALFVEC_ABOVE = 2000  # HNSW indexes vector(d) up to 2,000 dimensions, halfvec(d) up to 4,000


class PgVectorStore:
    """The vectors of one atlas under one model version, in their own table."""

    def __init__(
        self,
        sessions: sessionmaker[Session],
        atlas_id: int,
        version: int,
        dim: int,
        policy: PgVectorPolicy | None = None,
        *,
        linked: bool = True,
    ) -> None:
        """``linked``: rows reference ``frames`` (deleted with them, filter columns copied from
        them); unlinked tables (benchmarks) take robots and times from the caller."""
        self.sessions = sessions
        self.atlas_id, self.version, self.dim = atlas_id, version, dim
        self.policy = policy or PgVectorPolicy()
        self.linked = linked
        self.table = table_name(atlas_id, version)
        self.kind = "halfvec" if dim > HALFVEC_ABOVE else "vector"
        self._size: tuple[float, int] | None = None  # (when counted, count)
        # this process's adds and removals, numbered, as AtlasIndex journals them (caches of
        # the held vectors follow them); other replicas' writes are not in it
        self._journal = ChangeJournal()  # this process's adds and removals, as the FAISS index's

    # ----- schema --------------------------------------------------------------------------

    def create(self, *, indexes: bool = True) -> None:
        """Create the table and (unless ``indexes`` is False: a bulk load builds them after,
        with :meth:`create_indexes`) its indexes if missing; idempotent, safe across replicas."""
        frame_ref = "REFERENCES frames(id) ON DELETE CASCADE" if self.linked else ""
        with self.sessions.begin() as session:
            session.execute(text("SELECT pg_advisory_xact_lock(hashtext(:t))"), {"t": self.table})
            session.execute(
                text(
                    f"CREATE TABLE IF NOT EXISTS {self.table} ("
                    f" frame_id integer PRIMARY KEY {frame_ref},"
                    " robot_id text NOT NULL, submap_id integer, ts double precision,"
                    f" embedding {self.kind}({self.dim}) NOT NULL)"
                )
            )
            if indexes:
                self._create_indexes(session)

    def create_indexes(self) -> None:
        with self.sessions.begin() as session:
            self._create_indexes(session)

    def _create_indexes(self, session: Session) -> None:
        p = self.policy
        session.execute(
            text(
                f"CREATE INDEX IF NOT EXISTS {self.table}_hnsw ON {self.table} USING hnsw"
                f" (embedding {self.kind}_ip_ops) WITH (m = {p.m},"
                f" ef_construction = {p.ef_construction})"
            )
        )
        session.execute(
            text(f"CREATE INDEX IF NOT EXISTS {self.table}_robot ON {self.table} (robot_id, ts)")
        )

    def drop(self) -> None:
        with self.sessions.begin() as session:
            session.execute(text(f"DROP TABLE IF EXISTS {self.table}"))

    # ----- writes --------------------------------------------------------------------------

    def add(
        self,
        ids: np.ndarray,
        vectors: np.ndarray,
        robots: list[str],
        *,
        session: Session | None = None,
        times: np.ndarray | None = None,
        submaps: np.ndarray | None = None,
    ) -> int:
        """Insert ``vectors`` under frame ``ids`` (ids already held are skipped); in the caller's
        transaction when ``session`` is given, so the vector commits with its frame."""
        vectors = np.ascontiguousarray(vectors, dtype=np.float32)
        ids = np.asarray(ids, dtype=np.int64)
        if vectors.shape != (len(ids), self.dim):
            raise ValueError(f"expected {len(ids)} x {self.dim} vectors, got {vectors.shape}")
        if len(ids) == 0:
            return 0
        with self._transaction(session) as s:
            added = insert_rows(
                s,
                self.table,
                self.kind,
                self.dim,
                self.linked,
                ids,
                vectors,
                robots,
                times,
                submaps,
            )
        self._counted(added, 1, ids, vectors)
        return added

    def load(
        self,
        ids: np.ndarray,
        vectors: np.ndarray,
        robots: list[str],
        times: np.ndarray | None = None,
    ) -> None:
        """Bulk load into an empty unlinked table: binary COPY straight into it (benchmarks;
        build the HNSW index after with :meth:`create_indexes`)."""
        with self.sessions.begin() as session:
            copy_rows(session, self.table, self.kind, ids, vectors, robots, times, None)
        self._size = None

    def remove(self, ids: np.ndarray, *, session: Session | None = None) -> int:
        ids = np.asarray(ids, dtype=np.int64)
        if len(ids) == 0:
            return 0
        with self._transaction(session) as s:
            result = s.execute(
                text(f"DELETE FROM {self.table} WHERE frame_id = ANY(:ids)"), {"ids": ids.tolist()}
            )
            removed = int(getattr(result, "rowcount", 0) or 0)
        self._counted(-removed, -1, ids, None)
        return removed

    def journal_removal(self, ids: np.ndarray) -> None:
        """Note frames whose rows their deletion took (``ON DELETE CASCADE``), for the caches
        that follow :meth:`changes_since`."""
        self._counted(-len(ids), -1, np.asarray(ids, dtype=np.int64), None)

    @contextlib.contextmanager
    def _transaction(self, session: Session | None) -> Iterator[Session]:
        if session is not None:
            yield session
            return
        with self.sessions.begin() as own:
            yield own

    def _counted(self, change: int, sign: int, ids: np.ndarray, vectors: np.ndarray | None) -> None:
        if self._size is not None:
            self._size = (self._size[0], self._size[1] + change)
        self._journal.note(sign, ids, None if vectors is None else self.stored_like(ids, vectors))

    @property
    def generation(self) -> int:
        """How many adds and removals this process made through this object."""
        return self._journal.generation

    def changes_since(self, generation: int) -> list[Change] | None:
        """This process's adds (+1, ids, vectors) and removals (-1, ids, None) after
        ``generation``; None when the journal no longer reaches back that far."""
        return self._journal.since(generation)

    def stored_like(self, ids: np.ndarray, added: np.ndarray) -> np.ndarray:
        """What :meth:`vectors` returns for ``ids`` just added as ``added`` (float16-rounded
        for ``halfvec``), without reading them back."""
        added = np.asarray(added, dtype=np.float32)
        if self.kind == "halfvec":
            return added.astype(np.float16).astype(np.float32)
        return added.copy()

    # ----- reads ---------------------------------------------------------------------------

    @property
    def size(self) -> int:
        """How many vectors the table holds (cached ``size_ttl`` seconds: other replicas'
        adds show after that; estimated above ``ESTIMATED_ABOVE``)."""
        now = time.monotonic()
        if self._size is None or now - self._size[0] > self.policy.size_ttl:
            with self.sessions() as session:
                # a large table's planner estimate (kept by autovacuum and index builds) is
                # close enough for what size decides; counting 1M rows is not free
                count = int(
                    session.scalar(
                        text("SELECT reltuples FROM pg_class WHERE oid = to_regclass(:t)"),
                        {"t": self.table},
                    )
                    or 0
                )
                if count < ESTIMATED_ABOVE:
                    count = int(session.scalar(text(f"SELECT count(*) FROM {self.table}")) or 0)
            self._size = (now, count)
        return self._size[1]

    @property
    def exact(self) -> bool:
        return self.size < self.policy.exact_below

    def describe(self) -> str:
        how = "exact" if self.exact else f"HNSW ef_search={self.policy.ef_search}"
        return f"pgvector {self.kind}({self.dim}) {how}"

    def ids(self) -> np.ndarray:
        with self.sessions() as session:
            return np.fromiter(
                session.scalars(text(f"SELECT frame_id FROM {self.table}")), np.int64
            )

    def vectors(self, ids: np.ndarray) -> np.ndarray:
        """The stored vectors of ``ids``, in that order (float32)."""
        ids = np.asarray(ids, dtype=np.int64)
        if len(ids) == 0:
            return np.zeros((0, self.dim), np.float32)
        with self.sessions() as session:
            rows = session.execute(
                text(
                    f"SELECT frame_id, CAST(embedding AS text) FROM {self.table}"
                    " WHERE frame_id = ANY(:ids)"
                ),
                {"ids": ids.tolist()},
            ).all()
        found = {int(i): parse(e) for i, e in rows}
        missing = [int(i) for i in ids if int(i) not in found]
        if missing:
            raise KeyError(f"frames not held: {missing[:5]}")
        return np.stack([found[int(i)] for i in ids]).astype(np.float32)

    def missing_frames(self, session: Session) -> list[int]:
        """The atlas's frames without a row here (to embed), in id order."""
        return [
            int(i)
            for i in session.scalars(
                text(
                    f"SELECT f.id FROM frames f LEFT JOIN {self.table} v ON v.frame_id = f.id"
                    " WHERE f.atlas_id = :atlas AND v.frame_id IS NULL ORDER BY f.id"
                ),
                {"atlas": self.atlas_id},
            )
        ]

    def entries(self) -> tuple[np.ndarray, np.ndarray]:
        """Every frame id held and its vector (a snapshot's export)."""
        ids = np.sort(self.ids())
        return ids, self.vectors(ids)

    def search(
        self,
        vector: np.ndarray,
        k: int,
        robot_id: str | None = None,
        *,
        include: np.ndarray | None = None,
        exclude: np.ndarray | None = None,
        where: VectorFilter | None = None,
    ) -> list[Hit]:
        """The ``k`` most similar frames to one unit ``vector`` (see the module doc).

        ``robot_id``: only that robot's frames; ``include``: only those frame ids;
        ``exclude``: never those; ``where``: the filters SQL applies itself."""
        query = np.asarray(vector, dtype=np.float32).reshape(self.dim)
        if include is not None:
            include = np.asarray(include, dtype=np.int64)
            if exclude is not None and len(exclude):
                include = np.setdiff1d(include, exclude)
                exclude = None
            if len(include) == 0:
                return []
        conditions, params = where_clauses(robot_id, include, exclude, where)
        params.update(q=literal(query), k=int(k))
        exact = (include is not None and len(include) <= self.policy.exact_below) or self.exact
        with self.sessions() as session:
            ef = self.policy.filtered_ef_search if conditions else self.policy.ef_search
            rows = self._run(session, conditions, params, exact, ef)
            if len(rows) < k and not exact:  # the scan gave up early: ask exactly
                rows = self._run(session, conditions, params, True, ef)
        return [Hit(int(i), -float(d)) for i, d in rows]

    def _run(
        self,
        session: Session,
        conditions: list[str],
        params: dict[str, Any],
        exact: bool,
        ef_search: int,
    ) -> list[Any]:
        where_sql = (" WHERE " + " AND ".join(conditions)) if conditions else ""
        distance = f"embedding <#> CAST(:q AS {self.kind})"
        # "+ 0" hides the ORDER BY from the HNSW index: the planner scans rows exactly
        order = f"({distance}) + 0" if exact else distance
        if not exact:
            p = self.policy
            session.execute(
                text(
                    "SELECT set_config('hnsw.ef_search', :ef, true),"
                    " set_config('hnsw.iterative_scan', 'strict_order', true),"
                    " set_config('hnsw.max_scan_tuples', :mst, true)"
                ),
                {"ef": str(max(ef_search, int(params["k"]))), "mst": str(p.max_scan_tuples)},
            )
        return list(
            session.execute(
                text(
                    f"SELECT frame_id, {distance} AS d FROM {self.table}{where_sql}"
                    f" ORDER BY {order} LIMIT :k"
                ),
                params,
            ).all()
        )

    # ----- what the FAISS index's builders also call ---------------------------------------

    @contextlib.contextmanager
    def bulk(self) -> Iterator[None]:
        yield

    def training_ids(self, ids: np.ndarray) -> None:
        return None

    def prepare(self, size: int, sample: np.ndarray) -> bool:
        return False

    def wait_rebuilt(self) -> None:
        return None

    def set_robots(self, robot_of: dict[int, str]) -> None:
        return None  # the table holds them
