"""Dynamic micro-batching: concurrent callers of a batched function share one call.

The first caller to arrive opens a batch and leads it: it waits up to the window (or until the
batch is full), closes the batch, runs the batched function in its own thread and hands each
member its own result. Callers that arrive while a batch is open join it; once it is closed the
next caller opens a new one, so batches run side by side (the service's inference gate bounds
how many). A caller thus waits at most the window plus its batch's inference.

If the batched call raises, every member is retried alone, so an input that fails fails only
its own caller, with its own exception.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Generic, TypeVar

T = TypeVar("T")
R = TypeVar("R")


@dataclass
class _Batch(Generic[T, R]):
    items: list[T] = field(default_factory=list)
    results: list[R] = field(default_factory=list)
    errors: list[BaseException | None] = field(default_factory=list)
    full: threading.Event = field(default_factory=threading.Event)
    done: threading.Event = field(default_factory=threading.Event)


@dataclass
class BatchStats:
    batches: int = 0
    items: int = 0
    largest: int = 0


class MicroBatcher(Generic[T, R]):
    """Calls ``run(items) -> results`` (same length and order) on batches of concurrent items.

    Args:
        run: the batched function.
        window_s: longest time a batch stays open for more callers; 0 runs every call alone.
        max_batch: a batch closes as soon as it holds this many items.
    """

    def __init__(
        self, run: Callable[[list[T]], Sequence[R]], window_s: float, max_batch: int
    ) -> None:
        if window_s < 0 or max_batch < 1:
            raise ValueError(f"need window_s >= 0 and max_batch >= 1, got {window_s}, {max_batch}")
        self._run = run
        self.window_s = window_s
        self.max_batch = max_batch
        self._lock = threading.Lock()
        self._open: _Batch[T, R] | None = None
        self.stats = BatchStats()

    def submit(self, item: T) -> R:
        """``run([item])[0]``, computed together with whatever other callers submit meanwhile."""
        if self.window_s == 0 or self.max_batch == 1:
            return self._run([item])[0]
        with self._lock:
            batch = self._open
            leader = batch is None
            if batch is None:
                batch = self._open = _Batch()
            position = len(batch.items)
            batch.items.append(item)
            if len(batch.items) >= self.max_batch:
                self._open = None
                batch.full.set()
        if leader:
            batch.full.wait(self.window_s)
            with self._lock:
                if self._open is batch:
                    self._open = None
            self._execute(batch)
        else:
            batch.done.wait()
        error = batch.errors[position]
        if error is not None:
            raise error
        return batch.results[position]

    def _execute(self, batch: _Batch[T, R]) -> None:
        items = batch.items  # closed: nobody appends any more
        try:
            try:
                results = list(self._run(items))
                if len(results) != len(items):
                    raise RuntimeError(f"batched call gave {len(results)} results for {len(items)}")
                batch.results, batch.errors = results, [None] * len(items)
            except Exception:
                if len(items) == 1:
                    raise
                self._run_one_by_one(batch)
        except BaseException as exc:  # the lone item's own error, or an interrupt
            batch.results, batch.errors = [], [exc] * len(items)
        finally:
            with self._lock:
                self.stats.batches += 1
                self.stats.items += len(items)
                self.stats.largest = max(self.stats.largest, len(items))
            batch.done.set()

    def _run_one_by_one(self, batch: _Batch[T, R]) -> None:
        results: list[R] = []
        errors: list[BaseException | None] = []
        for item in batch.items:
            try:
                results.append(self._run([item])[0])
                errors.append(None)
            except Exception as exc:  # noqa: BLE001 - handed to the caller it belongs to
                results.append(None)  # type: ignore[arg-type]
                errors.append(exc)
        batch.results, batch.errors = results, errors
