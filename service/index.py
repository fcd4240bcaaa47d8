"""The FAISS index of one atlas: ids are frame ids, inner product on unit embeddings (cosine).

The database is the source of truth; the index file under the data directory is a cache that
``reconcile`` brings back in step with the database after a restart or a crash.
"""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import faiss
import numpy as np


@dataclass(frozen=True)
class Hit:
    frame_id: int
    similarity: float


class AtlasIndex:
    """Exact inner-product search over an atlas's frame embeddings, with robot filters."""

    def __init__(self, dim: int, index: faiss.Index | None = None) -> None:
        self.dim = dim
        # faiss's SWIG classes are only partly typed: treat the index as Any.
        self._index: Any = index if index is not None else faiss.IndexIDMap2(faiss.IndexFlatIP(dim))
        if self._index.d != dim:
            raise ValueError(f"index has dimension {self._index.d}, expected {dim}")
        self._robot_of: dict[int, str] = {}
        self._lock = threading.RLock()

    @property
    def size(self) -> int:
        return int(self._index.ntotal)

    def ids(self) -> np.ndarray:
        """The frame ids held, as int64 (unsorted)."""
        with self._lock:
            return faiss.vector_to_array(self._index.id_map).astype(np.int64)

    def add(self, ids: np.ndarray, vectors: np.ndarray, robots: list[str]) -> int:
        """Add ``N`` unit ``vectors`` under frame ``ids`` taken by ``robots``.

        Idempotent: ids already held are skipped, so a frame caught up by reconciliation and
        added by its own ingest call is indexed once. Returns how many were added.
        """
        vectors = np.ascontiguousarray(vectors, dtype=np.float32)
        if vectors.shape != (len(ids), self.dim):
            raise ValueError(f"expected {len(ids)} x {self.dim} vectors, got {vectors.shape}")
        with self._lock:
            new = np.array([int(i) not in self._robot_of for i in ids], dtype=bool)
            if not new.any():
                return 0
            new_ids = np.asarray(ids, dtype=np.int64)[new]
            self._index.add_with_ids(vectors[new], new_ids)
            kept = [robot for robot, is_new in zip(robots, new, strict=True) if is_new]
            self._robot_of.update(zip(new_ids.tolist(), kept, strict=True))
            return int(new.sum())

    def set_robots(self, robot_of: dict[int, str]) -> None:
        """Attach robot ids to frames loaded from a file (the file holds vectors only)."""
        with self._lock:
            self._robot_of.update(robot_of)

    def remove(self, ids: np.ndarray) -> int:
        if len(ids) == 0:
            return 0
        with self._lock:
            removed = int(self._index.remove_ids(np.asarray(ids, dtype=np.int64)))
            for i in ids:
                self._robot_of.pop(int(i), None)
            return removed

    def search(
        self,
        vector: np.ndarray,
        k: int,
        robot_id: str | None = None,
        *,
        include: np.ndarray | None = None,
        exclude: np.ndarray | None = None,
    ) -> list[Hit]:
        """The ``k`` most similar frames to one unit ``vector``.

        Optionally only one robot's frames, only the frame ids in ``include``, and never those
        in ``exclude``.
        """
        query = np.ascontiguousarray(vector, dtype=np.float32).reshape(1, self.dim)
        with self._lock:
            if self.size == 0:
                return []
            params = None
            if robot_id is not None:
                own = np.array(
                    [i for i, r in self._robot_of.items() if r == robot_id], dtype=np.int64
                )
                include = own if include is None else np.intersect1d(include, own)
            selector: Any = None
            if include is not None:
                if exclude is not None and len(exclude):
                    include = np.setdiff1d(include, exclude)
                if len(include) == 0:
                    return []
                selector = faiss.IDSelectorBatch(np.ascontiguousarray(include, np.int64))
            elif exclude is not None and len(exclude):
                dropped = faiss.IDSelectorBatch(np.ascontiguousarray(exclude, np.int64))
                selector = faiss.IDSelectorNot(dropped)
                selector.referenced = dropped  # keep the wrapped selector alive
            if selector is not None:
                params = faiss.SearchParameters(sel=selector)  # type: ignore[call-arg]
            k = min(k, self.size)
            similarities, ids = self._index.search(query, k, params=params)
        return [
            Hit(int(i), float(s)) for i, s in zip(ids[0], similarities[0], strict=True) if i >= 0
        ]

    def save(self, path: Path) -> None:
        """Write the index atomically (temporary file, then rename)."""
        path.parent.mkdir(parents=True, exist_ok=True)
        # a name of its own per process and thread: replicas sharing a data directory may
        # save the same index at once, and must never interleave their bytes in one file
        tmp = path.with_name(f"{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
        with self._lock:
            faiss.write_index(self._index, str(tmp))
        tmp.replace(path)

    @classmethod
    def load(cls, path: Path, dim: int) -> AtlasIndex:
        return cls(dim, faiss.read_index(str(path)))
