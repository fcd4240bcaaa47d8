"""The numbered record of an index's adds and removals, so that caches of its vectors (the
sequence scorer's map) follow it cheaply instead of reloading everything."""

from __future__ import annotations

import numpy as np

Change = tuple[int, np.ndarray, np.ndarray | None]  # +1 ids vectors (an add) or -1 ids None


class ChangeJournal:
    """The last :attr:`KEPT` changes, numbered by generation (not thread-safe: the index
    calls it under its own lock)."""

    KEPT = 1024

    def __init__(self) -> None:
        self._entries: list[Change] = []
        self._start = 0  # generation of the first entry
        self.paused = False  # inside a bulk block that began on an empty index

    @property
    def generation(self) -> int:
        """How many adds and removals the index has seen."""
        return self._start + len(self._entries)

    def since(self, generation: int) -> list[Change] | None:
        """The changes after ``generation``, oldest first; None when the journal no longer
        reaches back that far."""
        if generation < self._start or generation > self.generation:
            return None
        return list(self._entries[generation - self._start :])

    def note(self, sign: int, ids: np.ndarray, vectors: np.ndarray | None = None) -> None:
        """Record an add or removal (a copy: the caller's arrays may change)."""
        if self.paused:
            return
        self._entries.append((sign, ids.copy(), None if vectors is None else vectors.copy()))
        if len(self._entries) > self.KEPT:
            drop = len(self._entries) - self.KEPT // 2
            self._entries = self._entries[drop:]
            self._start += drop

    def restart(self) -> None:
        """Forget every change (after an unjournaled bulk load): any earlier generation
        answers None, so its caches reload."""
        self._start, self._entries = self.generation + 1, []
