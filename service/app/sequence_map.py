"""One atlas's frames as sequence scoring sees them: their vectors (the index's), their
trajectories (each robot's frames in timestamp order, arrival order without one), the map's
similarity moments, and each frame's trajectory-contrasted vector with its moments
(:mod:`service.ml.sequences.contrast`).

Built from the database's frame rows and the loaded index, then kept in step with the index's
journal of adds and removals, per process: a cache of what the database and the index hold,
never state of its own, so every replica and every restart builds the same map.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator
from typing import TYPE_CHECKING

import numpy as np
from sqlalchemy.orm import Session

from service.app.trajectory_growth import GrowingTrajectories
from service.ml.sequences import MapMoments, Trajectories
from service.ml.sequences.contrast import contrasted_frames
from service.storage import repository as repo

if TYPE_CHECKING:
    from service.app.state import LoadedAtlas


class SequenceMap:
    """Frames at positions ``0..count-1``: ids, unit vectors, robots, timestamps; frames are
    appended in place (buffers grow by doubling), a removal rebuilds the map."""

    def __init__(
        self,
        index_key: int,
        generation: int,
        dim: int,
        max_gap_seconds: float | None,
        contrast_window: int = 0,
    ) -> None:
        self.index_key = index_key  # id() of the index object it follows
        self.generation = generation  # the index journal generation it reflects
        self.max_gap_seconds = max_gap_seconds
        self._ids = np.zeros(0, dtype=np.int64)
        self._vectors = np.zeros((0, dim), dtype=np.float32)
        self.count = 0
        self.robots: list[str] = []
        self.timestamps: list[float | None] = []
        self.position: dict[int, int] = {}
        self._by_id: tuple[np.ndarray, np.ndarray] | None = None  # ids sorted, their positions
        self.moments = MapMoments(dim)
        self.growth = GrowingTrajectories(max_gap_seconds)
        self.contrast_window = contrast_window  # 0: no contrasted vectors
        self._contrasted = np.zeros((0, dim), dtype=np.float32)
        self.contrast_moments = MapMoments(dim)

    @property
    def trajectories(self) -> Trajectories:
        return self.growth.trajectories

    @property
    def ids(self) -> np.ndarray:
        return self._ids[: self.count]

    @property
    def vectors(self) -> np.ndarray:
        return self._vectors[: self.count]

    @property
    def contrasted(self) -> np.ndarray:
        return self._contrasted[: self.count]

    def append(self, rows: list[tuple[int, str, float | None]], vectors: np.ndarray) -> None:
        """Frames ``(id, robot, timestamp)`` with their vectors, after the ones held."""
        if not rows:
            return
        first = self.count
        needed = self.count + len(rows)
        if needed > len(self._ids):
            capacity = max(needed, 2 * len(self._ids), 64)
            self._ids = np.resize(self._ids, capacity)
            grown = np.zeros((capacity, self._vectors.shape[1]), dtype=np.float32)
            grown[: self.count] = self.vectors
            self._vectors = grown
        self._ids[self.count : needed] = [row[0] for row in rows]
        self._vectors[self.count : needed] = vectors
        for offset, row in enumerate(rows):
            self.position[row[0]] = self.count + offset
        self.count = needed
        self._by_id = None
        in_order = len(rows) < 64 and all(self.growth.append(row[1], row[2]) for row in rows)
        self.robots += [row[1] for row in rows]
        self.timestamps += [row[2] for row in rows]
        self.moments.add(vectors)
        if not in_order:  # many at once, or a frame older than its robot's latest: rebuild
            self.growth = GrowingTrajectories.build(
                self.robots, self.timestamps, self.max_gap_seconds
            )
        if self.contrast_window:
            self._contrast_from(first if in_order else 0)

    def _contrast_from(self, first: int) -> None:
        """Contrast frames ``first..count-1`` (0: all, after the trajectories were rebuilt and
        any frame's context may have changed); frames before ``first`` keep theirs, which
        appending at the end of each robot's time order cannot change."""
        if len(self._contrasted) < len(self._vectors):
            grown = np.zeros_like(self._vectors)
            grown[:first] = self._contrasted[:first]
            self._contrasted = grown
        fresh = contrasted_frames(
            self.lookup, self.trajectories, np.arange(first, self.count), self.contrast_window
        )
        self._contrasted[first : self.count] = fresh
        if first == 0:
            self.contrast_moments = MapMoments.of(fresh)
        else:
            self.contrast_moments.add(fresh)

    def positions(self, frame_ids: np.ndarray | list[int]) -> np.ndarray:
        """Positions of ``frame_ids`` (-1 for frames the map does not hold), by binary search
        over the ids in order (a request looks up hundreds: the kept proposals)."""
        wanted = np.asarray(frame_ids, dtype=np.int64).reshape(-1)
        if not self.count or not len(wanted):
            return np.full(len(wanted), -1, dtype=np.int64)
        if self._by_id is None:
            ids = self.ids
            ordered = bool(np.all(ids[1:] > ids[:-1]))  # frames arrive in id order
            order = np.arange(self.count) if ordered else np.argsort(ids, kind="stable")
            self._by_id = (ids[order], order.astype(np.int64))
        keys, order = self._by_id
        at = np.minimum(np.searchsorted(keys, wanted), len(keys) - 1)
        return np.where(keys[at] == wanted, order[at], -1)

    def lookup(self, positions: np.ndarray) -> np.ndarray:
        rows: np.ndarray = np.take(self._vectors, positions, axis=0)
        return rows

    def contrasted_lookup(self, positions: np.ndarray) -> np.ndarray:
        rows: np.ndarray = np.take(self._contrasted, positions, axis=0)
        return rows


def _rows_and_vectors(
    session: Session, state: LoadedAtlas
) -> tuple[list[tuple[int, str, float | None]], np.ndarray]:
    """Every frame row the index holds and its index vector."""
    rows = repo.frame_times(session, atlas_id=state.atlas_id)
    held = set(state.index.ids().tolist())
    rows = [row for row in rows if row[0] in held]
    ids = np.array([row[0] for row in rows], dtype=np.int64)
    return rows, state.index.vectors(ids).astype(np.float32)


def _added_rows_and_vectors(
    session: Session, state: LoadedAtlas, ids: np.ndarray, added: np.ndarray
) -> tuple[list[tuple[int, str, float | None]], np.ndarray]:
    """The rows of frames the index has just added and the vectors it holds for them."""
    rows = repo.frame_times(session, atlas_id=state.atlas_id, frame_ids=ids.tolist())
    found = {row[0] for row in rows}
    keep = np.array([int(i) in found for i in ids], dtype=bool)
    vectors = state.index.stored_like(ids[keep], added[keep])
    order = np.argsort(ids[keep], kind="stable")  # rows come in id order
    return rows, vectors[order]


class SequenceMaps:
    """The :class:`SequenceMap` of each loaded atlas, brought up to date on use."""

    def __init__(self, max_gap_seconds: float | None, contrast_window: int = 0) -> None:
        self.max_gap_seconds = max_gap_seconds
        self.contrast_window = contrast_window
        self._maps: dict[int, SequenceMap] = {}
        self._lock = threading.Lock()

    @contextlib.contextmanager
    def hold(self, session: Session, state: LoadedAtlas) -> Iterator[SequenceMap]:
        """The atlas's map, current with its index, held (not changed) while in use."""
        with self._lock:
            yield self._current(session, state)

    def refresh(self, session: Session, state: LoadedAtlas) -> None:
        """Bring the atlas's map up to date now (the first use builds it)."""
        with self._lock:
            self._current(session, state)

    def _current(self, session: Session, state: LoadedAtlas) -> SequenceMap:
        cached = self._maps.get(state.atlas_id)
        generation = state.index.generation
        if cached is not None and cached.index_key == id(state.index):
            if cached.generation == generation:
                return cached
            changes = state.index.changes_since(cached.generation)
            if changes is not None and all(sign > 0 for sign, _, _ in changes):
                ids = np.concatenate([ids for _, ids, _ in changes])
                added = np.concatenate([v for _, _, v in changes if v is not None])
                new = np.array([int(i) not in cached.position for i in ids], dtype=bool)
                if new.any():
                    cached.append(*_added_rows_and_vectors(session, state, ids[new], added[new]))
                cached.generation = generation
                return cached
        fresh = SequenceMap(
            id(state.index),
            generation,
            state.index.dim,
            self.max_gap_seconds,
            self.contrast_window,
        )
        fresh.append(*_rows_and_vectors(session, state))
        self._maps[state.atlas_id] = fresh
        return fresh
