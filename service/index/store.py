"""One interface over the two vector stores, and which one a deployment uses.

- ``faiss`` (:class:`~service.index.atlas_index.AtlasIndex`): an in-process index per atlas,
  cached in a file and kept in step with the database by the change feed. One machine.
- ``pgvector`` (:class:`~service.index.pgvector_store.PgVectorStore`): a table per atlas and
  model version in the PostgreSQL database, written in each frame's own transaction. A fleet.

``LOOPNET_VECTOR_STORE=auto`` picks pgvector when the database is PostgreSQL and the ``vector``
extension is installed or available, else FAISS.
"""

from __future__ import annotations

import logging
from contextlib import AbstractContextManager
from typing import Protocol

import numpy as np
from sqlalchemy import Engine
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session, sessionmaker

from service.index.atlas_index import Hit
from service.index.pgvector_store import PgVectorStore, available, ensure_extension
from service.ml.active_model import ActiveModel

log = logging.getLogger(__name__)

FAISS, PGVECTOR = "faiss", "pgvector"


class VectorStore(Protocol):
    """What the service asks of an atlas's vectors, whichever store holds them."""

    dim: int

    @property
    def size(self) -> int: ...

    @property
    def exact(self) -> bool: ...

    @property
    def generation(self) -> int: ...

    def describe(self) -> str: ...

    def ids(self) -> np.ndarray: ...

    def add(self, ids: np.ndarray, vectors: np.ndarray, robots: list[str]) -> int: ...

    def remove(self, ids: np.ndarray) -> int: ...

    def search(
        self,
        vector: np.ndarray,
        k: int,
        robot_id: str | None = None,
        *,
        include: np.ndarray | None = None,
        exclude: np.ndarray | None = None,
    ) -> list[Hit]: ...

    def vectors(self, ids: np.ndarray) -> np.ndarray: ...

    def stored_like(self, ids: np.ndarray, added: np.ndarray) -> np.ndarray: ...

    def changes_since(
        self, generation: int
    ) -> list[tuple[int, np.ndarray, np.ndarray | None]] | None: ...

    def entries(self) -> tuple[np.ndarray, np.ndarray]: ...

    def set_robots(self, robot_of: dict[int, str]) -> None: ...

    def bulk(self) -> AbstractContextManager[None]: ...

    def training_ids(self, ids: np.ndarray) -> np.ndarray | None: ...

    def prepare(self, size: int, sample: np.ndarray) -> bool: ...

    def wait_rebuilt(self) -> None: ...


def resolve_kind(setting: str, engine: Engine) -> str:
    """The store ``setting`` (auto, faiss, pgvector) means on ``engine``; pgvector is made
    ready (``CREATE EXTENSION IF NOT EXISTS vector``). Raises RuntimeError when pgvector is
    asked for and the database cannot have it."""
    if setting == FAISS:
        return FAISS
    usable = available(engine)
    if setting == PGVECTOR and not usable:
        raise RuntimeError(
            "LOOPNET_VECTOR_STORE=pgvector needs a PostgreSQL database with the vector "
            "extension available (pgvector/pgvector image, or the postgresql-NN-pgvector package)"
        )
    if not usable:
        return FAISS
    try:
        ensure_extension(engine)
    except SQLAlchemyError as exc:  # available but not ours to create (no privilege)
        if setting == PGVECTOR:
            raise RuntimeError(f"cannot create the vector extension: {exc}") from exc
        log.warning("pgvector is available but the extension cannot be created (%s); FAISS", exc)
        return FAISS
    return PGVECTOR


def fill_version_table(
    setting: str,
    sessions: sessionmaker[Session],
    atlas_id: int,
    version: int,
    model: ActiveModel,
) -> int | None:
    """pgvector deployments: embed every stored frame with a new model version's ``model`` into
    that version's table, beside the active one, before the version is activated; the HNSW
    index is built after the load (faster than row by row). Replicas then swap heads and table
    together without embedding anything but the frames added meanwhile. Returns the rows
    written, or None on FAISS (nothing to do)."""
    from service.index.builder import add_stored_frames  # the builder imports this module

    if resolve_kind(setting, sessions.kw["bind"]) != PGVECTOR:
        return None
    store = PgVectorStore(sessions, atlas_id, version, model.dim)
    store.create(indexes=False)
    with sessions() as session:
        added = add_stored_frames(session, atlas_id, model, store)
    store.create_indexes()
    log.info("atlas %d: %d vectors of model version %d in its table", atlas_id, added, version)
    return added
