"""The SQL side of the pgvector store and its tuning: table names, the extension, filters, the text form
of vectors, and :class:`PgVectorPolicy` (see :mod:`service.index.pgvector_store`)."""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

import numpy as np
from sqlalchemy import Engine, text
from sqlalchemy.orm import Session


@dataclass(frozen=True)
class VectorFilter:
    """Restrictions the store applies in SQL: one robot's frames (or all but one robot's),
    one submap, a capture-time window."""

    robot_id: str | None = None
    other_robots: bool = False  # True: every robot but ``robot_id``
    submap_id: int | None = None
    since: float | None = None
    until: float | None = None


def table_name(atlas_id: int, version: int) -> str:
    return f"loopnet_vectors_a{int(atlas_id)}_v{int(version)}"


def available(engine: Engine) -> bool:
    """Whether ``engine`` is PostgreSQL with pgvector installed or installable."""
    if engine.dialect.name != "postgresql":
        return False
    with engine.connect() as connection:
        found = connection.execute(
            text("SELECT 1 FROM pg_available_extensions WHERE name = 'vector'")
        ).first()
    return found is not None


def ensure_extension(engine: Engine) -> None:
    with engine.begin() as connection:
        connection.execute(text("CREATE EXTENSION IF NOT EXISTS vector"))


def drop_atlas_tables(session: Session, atlas_id: int) -> None:
    """Drop every version's table of an atlas (the atlas is being deleted)."""
    pattern = f"loopnet_vectors_a{int(atlas_id)}_v%"
    names = session.scalars(
        text("SELECT tablename FROM pg_tables WHERE tablename LIKE :p"), {"p": pattern}
    ).all()
    for name in names:
        if re.fullmatch(r"loopnet_vectors_a\d+_v\d+", name):
            session.execute(text(f'DROP TABLE IF EXISTS "{name}"'))


def where_clauses(
    robot_id: str | None,
    include: np.ndarray | None,
    exclude: np.ndarray | None,
    where: VectorFilter | None,
) -> tuple[list[str], dict[str, Any]]:
    conditions: list[str] = []
    params: dict[str, Any] = {}
    if robot_id is not None:
        conditions.append("robot_id = :robot")
        params["robot"] = robot_id
    if include is not None:
        conditions.append("frame_id = ANY(:include)")
        params["include"] = include.tolist()
    if exclude is not None and len(exclude):
        conditions.append("NOT (frame_id = ANY(:exclude))")
        params["exclude"] = np.asarray(exclude, dtype=np.int64).tolist()
    if where is not None:
        if where.robot_id is not None:
            conditions.append("robot_id <> :wrobot" if where.other_robots else "robot_id = :wrobot")
            params["wrobot"] = where.robot_id
        if where.submap_id is not None:
            conditions.append("submap_id = :submap")
            params["submap"] = where.submap_id
        if where.since is not None:
            conditions.append("ts >= :since")
            params["since"] = where.since
        if where.until is not None:
            conditions.append("ts <= :until")
            params["until"] = where.until
    return conditions, params


def literal(vector: np.ndarray) -> str:
    """pgvector's text form of a vector: ``[x,y,...]`` (float32 round-trips with 9 digits)."""
    return "[" + ",".join(f"{x:.9g}" for x in vector.tolist()) + "]"


def parse(literal: str) -> np.ndarray:
    return np.array(literal.strip("[]").split(","), dtype=np.float32)


@dataclass(frozen=True)
class PgVectorPolicy:
    """Tuning of the pgvector store.

    Attributes:
        exact_below: atlases with fewer frames (and searches over fewer listed frames) are
            searched exactly.
        ef_search: HNSW candidate list per unfiltered query (recall against latency; see
            benchmarks/RESULTS.md, *Issue 28: vector stores*).
        filtered_ef_search: the same for a filtered query (robot, frames, time): its nearest
            allowed frames are further from the query in the graph, so it needs more.
        max_scan_tuples: how far an iterative scan may go before giving up (then exact).
        m, ef_construction: HNSW build parameters.
        size_ttl: seconds the frame count is cached (it only picks exact or HNSW search).
    """

    exact_below: int = 10_000
    ef_search: int = 100
    filtered_ef_search: int = 400
    max_scan_tuples: int = 50_000
    m: int = 16
    ef_construction: int = 64
    size_ttl: float = 5.0
