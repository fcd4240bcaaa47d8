"""The FAISS index of one atlas: ids are frame ids, inner product on unit embeddings (cosine).

The database is the source of truth; the index file under the data directory is a cache that
``reconcile`` brings back in step with the database after a restart or a crash.

The index type follows the atlas's size (:class:`IndexPolicy`, figures in
``benchmarks/RESULTS.md``, *Search at scale*): exact search (``IndexFlatIP``) while its vectors
fit ``flat_max_bytes``, then an inverted file with scalar-quantised codes
(``IndexIVFScalarQuantizer``) whose precision is the finest that fits the per-frame memory
budget. The inverted file is trained on the atlas's own vectors when the atlas crosses that
size and retrained when it has grown about fourfold since (its list count no longer fits its
size), in a background thread while the current index keeps serving. A bulk load into an empty
index (re-embedding an atlas) trains the final inverted file first, on a sample of the frames
(:meth:`AtlasIndex.training_ids`, :meth:`AtlasIndex.prepare`), so its adds go straight into the
lists: no exact stage, no rebuild. Vectors join their lists by bf16 scoring where the CPU has
it (:mod:`service.index.assignment`). Both types keep what the service relies on: ids = frame
ids, removal, idempotent adds, save/load, and filtered search through an ``IDSelector`` (with
an exhaustive pass over the filtered frames when the probed lists hold too few of them).
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import faiss
import numpy as np

from service.index.assignment import ListAssigner
from service.index.faiss_parts import (
    IndexPolicy,
    add_vectors,
    assigner_of,
    flat_index,
    id_selector,
    quantizer_name,
)
from service.index.journal import Change, ChangeJournal

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Hit:
    frame_id: int
    similarity: float


class AtlasIndex:
    """Inner-product search over an atlas's frame embeddings, with robot filters."""

    def __init__(
        self, dim: int, index: faiss.Index | None = None, policy: IndexPolicy | None = None
    ) -> None:
        self.dim = dim
        self.policy = policy or IndexPolicy()
        # faiss's SWIG classes are only partly typed: treat the index as Any.
        self._index: Any = index if index is not None else flat_index(dim)
        if self._index.d != dim:
            raise ValueError(f"index has dimension {self._index.d}, expected {dim}")
        self._robot_of: dict[int, str] = {}
        self._assigner: ListAssigner | None = None  # the inverted file's, made on first use
        self._lock = threading.RLock()
        # While a rebuild runs: the adds and removals to replay on the new index.
        self._log: list[tuple[str, np.ndarray, np.ndarray | None]] | None = None
        self._rebuilder: threading.Thread | None = None
        self._bulk = 0  # open bulk() blocks: rebuilds wait until the last one closes
        # Every add and removal, numbered: caches of the held vectors follow them cheaply.
        self._journal = ChangeJournal()

    @property
    def generation(self) -> int:
        """How many adds and removals this index object has seen."""
        return self._journal.generation

    def changes_since(self, generation: int) -> list[Change] | None:
        """The adds (+1, ids, the vectors added) and removals (-1, ids, None) after
        ``generation``, oldest first; None when the journal no longer reaches back that far
        (also across a bulk load into an empty index: see :meth:`bulk`)."""
        with self._lock:
            return self._journal.since(generation)

    def vectors(self, ids: np.ndarray) -> np.ndarray:
        """The stored vectors of held frame ``ids`` (decoded codes for the inverted file)."""
        with self._lock:
            return self._reconstruct(np.asarray(ids, dtype=np.int64))

    def stored_like(self, ids: np.ndarray, added: np.ndarray) -> np.ndarray:
        """What :meth:`vectors` returns for ``ids`` just added as ``added``, without the
        inverted file's id map over every frame: each frame is found in the list its added
        vector was assigned to (the same :class:`ListAssigner` assigns it again)."""
        ids = np.asarray(ids, dtype=np.int64)
        added = np.ascontiguousarray(added, dtype=np.float32)
        with self._lock:
            ivf, assigner = self._ivf(), self._current_assigner()
            if ivf is None or assigner is None:
                return added.copy()  # the flat index keeps the vectors themselves
            lists = assigner.assign(added)
            out = np.empty_like(added)
            for row, (frame, list_no) in enumerate(zip(ids, lists, strict=True)):
                size = ivf.invlists.list_size(int(list_no))
                held = faiss.rev_swig_ptr(ivf.invlists.get_ids(int(list_no)), size)
                where = np.flatnonzero(held == frame)
                if not len(where):  # not where expected (a rebuild moved it): the slow way
                    out[row] = self._reconstruct(np.array([frame]))[0]
                    continue
                ivf.reconstruct_from_offset(int(list_no), int(where[0]), faiss.swig_ptr(out[row]))
            return out

    @property
    def size(self) -> int:
        return int(self._index.ntotal)

    @property
    def exact(self) -> bool:
        """Whether searches are exact (a flat index) rather than approximate."""
        return self._ivf() is None

    def describe(self) -> str:
        """The index type in words, for logs and benchmarks."""
        ivf = self._ivf()
        if ivf is None:
            return "Flat (exact)"
        return f"IVF{ivf.nlist},{quantizer_name(ivf)} nprobe={min(self.policy.nprobe, ivf.nlist)}"

    def _ivf(self) -> Any | None:
        """The inverted-file index, or None while the index is flat."""
        return self._index if isinstance(self._index, faiss.IndexIVF) else None

    def ids(self) -> np.ndarray:
        """The frame ids held, as int64 (unsorted)."""
        with self._lock:
            ivf = self._ivf()
            if ivf is None:
                return faiss.vector_to_array(self._index.id_map).astype(np.int64)
            lists = ivf.invlists
            parts = [
                faiss.rev_swig_ptr(lists.get_ids(i), lists.list_size(i)).copy()
                for i in range(ivf.nlist)
                if lists.list_size(i)
            ]
            return np.concatenate(parts).astype(np.int64) if parts else np.zeros(0, np.int64)

    def add(self, ids: np.ndarray, vectors: np.ndarray, robots: list[str]) -> int:
        """Add ``N`` unit ``vectors`` under frame ``ids`` taken by ``robots``.

        Idempotent: ids already held are skipped, so a frame caught up by reconciliation and
        added by its own ingest call is indexed once. Returns how many were added. An add that
        takes the atlas past a size threshold of the policy starts a rebuild of the index.
        """
        vectors = np.ascontiguousarray(vectors, dtype=np.float32)
        if vectors.shape != (len(ids), self.dim):
            raise ValueError(f"expected {len(ids)} x {self.dim} vectors, got {vectors.shape}")
        with self._lock:
            new = np.array([int(i) not in self._robot_of for i in ids], dtype=bool)
            if not new.any():
                return 0
            new_ids = np.asarray(ids, dtype=np.int64)[new]
            added = vectors if new.all() else vectors[new]
            if not self._bulk and self._preparable():  # one large add (a restore): no exact stage
                self._prepare_from(new_ids, added)
            self._regrow(new_ids, added)
            kept = [robot for robot, is_new in zip(robots, new, strict=True) if is_new]
            self._robot_of.update(zip(new_ids.tolist(), kept, strict=True))
            self._journal.note(1, new_ids, added)
            return int(new.sum())

    def set_robots(self, robot_of: dict[int, str]) -> None:
        """Attach robot ids to frames loaded from a file (the file holds vectors only)."""
        with self._lock:
            self._robot_of.update(robot_of)

    def remove(self, ids: np.ndarray) -> int:
        if len(ids) == 0:
            return 0
        with self._lock:
            ids = np.asarray(ids, dtype=np.int64)
            removed = int(self._index.remove_ids(ids))
            for i in ids:
                self._robot_of.pop(int(i), None)
            self._journal.note(-1, ids)
            if self._log is not None:
                self._log.append(("remove", ids, None))
            elif not self._bulk:
                self._regrow_if_due()
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
            if robot_id is not None:
                own = np.array(
                    [i for i, r in self._robot_of.items() if r == robot_id], dtype=np.int64
                )
                include = own if include is None else np.intersect1d(include, own)
            if include is not None:
                if exclude is not None and len(exclude):
                    include = np.setdiff1d(include, exclude)
                if len(include) == 0:
                    return []
            k = min(k, self.size)
            if include is not None:
                wanted = min(k, len(include))
            elif exclude is not None:
                wanted = max(min(k, self.size - len(exclude)), 0)
            else:
                wanted = k
            similarities, ids = self._search(query, k, id_selector(include, exclude), wanted)
        return [
            Hit(int(i), float(s)) for i, s in zip(ids[0], similarities[0], strict=True) if i >= 0
        ]

    def _search(
        self, query: np.ndarray, k: int, selector: Any, wanted: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Search, restricted by ``selector`` (None: every frame).

        On the inverted file a filtered search first visits ``nprobe`` lists; if they hold fewer
        than ``wanted`` allowed frames (a rare robot's frames spread over the atlas) it searches
        every list, which scores exactly the allowed frames' codes.
        """
        ivf = self._ivf()
        if ivf is None:
            params = None if selector is None else faiss.SearchParameters(sel=selector)  # type: ignore[call-arg]
            return self._index.search(query, k, params=params)  # type: ignore[no-any-return]
        nprobe = min(self.policy.nprobe, ivf.nlist)
        params = faiss.SearchParametersIVF(nprobe=nprobe, sel=selector)  # type: ignore[call-arg]
        similarities, ids = self._index.search(query, k, params=params)
        if int((ids[0] >= 0).sum()) < wanted and nprobe < ivf.nlist:
            params = faiss.SearchParametersIVF(nprobe=ivf.nlist, sel=selector)  # type: ignore[call-arg]
            similarities, ids = self._index.search(query, k, params=params)
        return similarities, ids

    # ----- choosing the type by size -------------------------------------------------------

    def _regrow(self, ids: np.ndarray, vectors: np.ndarray) -> None:
        """Add ``vectors``; when the atlas's size calls for another index (exact to inverted
        file, or more lists), start rebuilding it from the held vectors."""
        add_vectors(self._index, ids, vectors, self._current_assigner())
        if self._log is not None:
            self._log.append(("add", ids, vectors.copy()))
        elif not self._bulk:
            self._regrow_if_due()

    @contextlib.contextmanager
    def bulk(self) -> Iterator[None]:
        """Adds inside go into the current index without rebuilding it; leaving the block
        rebuilds once, to the type the final size calls for. A bulk load (re-embedding an
        atlas) then trains k-means and assigns its vectors once, at the final size, instead of
        at every size threshold it passes (3 rebuilds of all vectors on the way to 1M); after
        :meth:`prepare` it does not rebuild at all.

        A block that begins on an empty index does not journal its changes (a copy of every
        vector, for nobody: no cache follows an empty index); leaving it restarts the journal,
        so :meth:`changes_since` any earlier generation is None and a cache reloads."""
        with self._lock:
            if not self._bulk and self.size == 0 and self._log is None:
                self._journal.paused = True
            self._bulk += 1
        try:
            yield
        finally:
            with self._lock:
                self._bulk -= 1
                if not self._bulk:
                    self._end_bulk()

    def _end_bulk(self) -> None:
        if self._journal.paused:
            self._journal.paused = False
            self._journal.restart()
        if self._log is None:
            self._regrow_if_due()

    def training_ids(self, ids: np.ndarray) -> np.ndarray | None:
        """The frames of ``ids`` whose vectors train the inverted file for that many frames
        (see :meth:`prepare`), or None when they are few enough for exact search."""
        ids = np.asarray(ids, dtype=np.int64)
        nlist = self.policy.wanted_nlist(self.dim, len(ids))
        return None if nlist is None else ids[self.policy.training_rows(ids, nlist)]

    def prepare(self, size: int, sample: np.ndarray) -> bool:
        """Make an empty index the inverted file ``size`` frames call for, trained on
        ``sample`` (the vectors of :meth:`training_ids`), so a bulk load's adds go straight into
        its lists: no exact stage to read back, no rebuild. Returns False, changing nothing,
        when the index holds frames, is rebuilding or is prepared already, when ``size``
        frames fit exact search, or when ``sample`` has fewer vectors than lists."""
        with self._lock:
            nlist = self.policy.wanted_nlist(self.dim, size)
            if not self._preparable() or nlist is None or len(sample) < nlist:
                return False
        target = self.policy.new_ivf(self.dim, size)
        # k-means outside the lock (but for add()'s one large add: nothing to serve yet)
        target.train(np.ascontiguousarray(sample, dtype=np.float32))
        with self._lock:
            if not self._preparable():  # frames came meanwhile: they go the usual way
                return False
            self._index = target
            return True

    def _preparable(self) -> bool:
        return self.size == 0 and self._log is None and self.exact

    def _prepare_from(self, ids: np.ndarray, vectors: np.ndarray) -> None:
        """:meth:`prepare` for ``ids`` about to be added to an empty index in one call."""
        nlist = self.policy.wanted_nlist(self.dim, len(ids))
        if nlist is not None:
            self.prepare(len(ids), vectors[self.policy.training_rows(ids, nlist)])

    def _start_rebuild(self, size: int) -> None:
        """Snapshot the held vectors (under the lock), then train and fill the new index.

        With ``policy.background`` the slow part (k-means, assigning every vector) runs in a
        thread while the current index keeps serving; adds and removals made meanwhile are
        logged and replayed on the new index before it replaces the old one. A foreground
        rebuild's result depends only on the sequence of adds and removals; a background one
        trains on the snapshot taken when it started, so a later threshold crossed meanwhile is
        handled by the next rebuild, and the codes can differ in the last digits.
        """
        ids = np.sort(self.ids())
        vectors = self._reconstruct(ids)
        target = (
            flat_index(self.dim)
            if self.policy.wanted_nlist(self.dim, size) is None
            else self.policy.new_ivf(self.dim, size)
        )
        self._log = []
        if not self.policy.background:
            self._finish_rebuild(target, ids, vectors)
            return
        self._rebuilder = threading.Thread(
            target=self._finish_rebuild, args=(target, ids, vectors), daemon=True
        )
        self._rebuilder.start()

    def _finish_rebuild(self, target: Any, ids: np.ndarray, vectors: np.ndarray) -> None:
        try:
            if not target.is_trained:
                nlist = faiss.extract_index_ivf(target).nlist
                target.train(vectors[self.policy.training_rows(ids, nlist)])
            assigner = assigner_of(target)
            add_vectors(target, ids, vectors, assigner)
        except Exception:
            log.exception("index rebuild failed; the current index keeps serving")
            with self._lock:
                self._log = None
            return
        with self._lock:
            for operation, op_ids, op_vectors in self._log or []:
                if operation == "add":
                    assert op_vectors is not None
                    add_vectors(target, op_ids, op_vectors, assigner)
                else:
                    target.remove_ids(op_ids)
            self._index, self._assigner, self._log = target, assigner, None
            log.info("index of %d frames rebuilt as %s", target.ntotal, self.describe())
            self._regrow_if_due()  # the atlas may have grown past the next threshold meanwhile

    def _current_assigner(self) -> ListAssigner | None:
        """The current inverted file's assigner (None while the index is flat)."""
        if self._assigner is None or self._assigner.index is not self._index:
            self._assigner = assigner_of(self._index)
        return self._assigner

    def _regrow_if_due(self) -> None:
        """Rebuild when the size calls for another type: exact to inverted file, twice the
        lists, or exact again once shrunk to half the threshold (so a size near it never
        flips back and forth)."""
        ivf, wanted = self._ivf(), self.policy.wanted_nlist(self.dim, self.size)
        if ivf is None:
            due = wanted is not None
        elif wanted is None:
            due = self.size <= self.policy.flat_max(self.dim) // 2
        else:
            due = wanted >= 2 * ivf.nlist
        if due:
            self._start_rebuild(self.size)

    def wait_rebuilt(self) -> None:
        """Block until rebuilds in progress (and any they chain) have replaced the index."""
        while (thread := self._rebuilder) is not None and thread.is_alive():
            thread.join()

    def _reconstruct(self, ids: np.ndarray) -> np.ndarray:
        """The stored vectors of ``ids`` (exact for flat, decoded codes for the inverted file)."""
        if len(ids) == 0:
            return np.zeros((0, self.dim), np.float32)
        ivf = self._ivf()
        if ivf is None:
            return self._index.reconstruct_batch(ids)  # type: ignore[no-any-return]
        ivf.set_direct_map_type(faiss.DirectMap.Hashtable)  # type: ignore[attr-defined]
        try:
            return ivf.reconstruct_batch(ids)  # type: ignore[no-any-return]
        finally:
            ivf.set_direct_map_type(faiss.DirectMap.NoMap)  # type: ignore[attr-defined]

    # ----- files -------------------------------------------------------------------------

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
    def load(cls, path: Path, dim: int, policy: IndexPolicy | None = None) -> AtlasIndex:
        return cls(dim, faiss.read_index(str(path)), policy)

    def to_bytes(self) -> bytes:
        """The index as the bytes of a FAISS file (what :meth:`save` writes)."""
        with self._lock:
            return bytes(faiss.serialize_index(self._index).tobytes())

    @classmethod
    def from_bytes(cls, data: bytes, policy: IndexPolicy | None = None) -> AtlasIndex:
        """An index from the bytes of a FAISS file; its dimension is the file's."""
        index = faiss.deserialize_index(np.frombuffer(data, np.uint8))
        return cls(int(index.d), index, policy)

    def entries(self) -> tuple[np.ndarray, np.ndarray]:
        """Every frame id held and its stored vector (decoded codes for the inverted file)."""
        with self._lock:
            ids = self.ids()
            return ids, self._reconstruct(ids)
