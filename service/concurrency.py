"""Admission control for inference: a bounded number of CNN passes and a bounded wait queue.

Decoding an upload and running the CNNs takes from a tenth of a second to seconds of CPU. Under
more load than the machine can serve, an unbounded queue only turns every request into a
time-out. The gate lets at most ``workers`` inferences run at once and at most ``queue`` more
wait (first come, first served); a request beyond that, or one that waited longer than
``wait_timeout_s``, is refused at once with :class:`~service.errors.Overloaded` (HTTP 503) and a
``Retry-After`` estimated from the recent inference time and the work ahead of it.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

from service.errors import Overloaded
from service.metrics import ADMISSION_WAIT_SECONDS

EWMA_WEIGHT = 0.2  # weight of the newest inference time in the running mean


def default_workers(torch_threads: int | None) -> int:
    """Concurrent inferences that fill the cores without oversubscribing them: cores divided
    by the intra-op threads each inference uses (torch's default uses every core: 1 worker)."""
    cores = os.cpu_count() or 1
    threads = torch_threads or _torch_threads()
    return max(1, cores // max(1, threads))


def _torch_threads() -> int:
    import torch

    return int(torch.get_num_threads())


@dataclass(frozen=True)
class GateStats:
    workers: int
    queue: int
    running: int
    waiting: int
    admitted: int
    refused: int
    mean_inference_ms: float | None


class InferenceGate:
    """At most ``workers`` holders of :meth:`slot` at once, at most ``queue`` waiting, FIFO."""

    def __init__(self, workers: int, queue: int, wait_timeout_s: float) -> None:
        if workers < 1 or queue < 0 or wait_timeout_s <= 0:
            raise ValueError(
                f"need workers >= 1, queue >= 0, wait_timeout_s > 0; got {workers}, {queue}, "
                f"{wait_timeout_s}"
            )
        self.workers = workers
        self.queue = queue
        self.wait_timeout_s = wait_timeout_s
        self._cond = threading.Condition()
        self._running = 0
        self._waiting: deque[object] = deque()
        self._admitted = 0
        self._refused = 0
        self._mean_s: float | None = None

    @contextmanager
    def slot(self) -> Iterator[None]:
        """Hold one of the ``workers`` slots for the block, or raise :class:`Overloaded`."""
        arrived = time.perf_counter()
        try:
            self._enter()
        finally:
            ADMISSION_WAIT_SECONDS.observe(time.perf_counter() - arrived)
        start = time.perf_counter()
        try:
            yield
        finally:
            self._leave(time.perf_counter() - start)

    def _enter(self) -> None:
        with self._cond:
            if self._running < self.workers and not self._waiting:
                self._running += 1
                self._admitted += 1
                return
            if len(self._waiting) >= self.queue:
                self._refused += 1
                raise Overloaded(
                    f"inference is saturated: {self._running} running and "
                    f"{len(self._waiting)} waiting (limits {self.workers} and {self.queue})",
                    retry_after_s=self._retry_after_locked(),
                )
            ticket = object()
            self._waiting.append(ticket)
            try:
                admitted = self._cond.wait_for(
                    lambda: self._waiting[0] is ticket and self._running < self.workers,
                    timeout=self.wait_timeout_s,
                )
            finally:
                self._waiting.remove(ticket)
                self._cond.notify_all()  # the next ticket may now be at the head
            if not admitted:
                self._refused += 1
                raise Overloaded(
                    f"no inference slot became free within {self.wait_timeout_s:g} s",
                    retry_after_s=self._retry_after_locked(),
                )
            self._running += 1
            self._admitted += 1

    def _leave(self, seconds: float) -> None:
        with self._cond:
            self._running -= 1
            if self._mean_s is None:
                self._mean_s = seconds
            else:
                self._mean_s += EWMA_WEIGHT * (seconds - self._mean_s)
            self._cond.notify_all()

    def _retry_after_locked(self) -> int:
        """Whole seconds until the work ahead has likely drained (at least 1)."""
        ahead = self._running + len(self._waiting)
        mean = self._mean_s if self._mean_s is not None else 1.0
        return max(1, math.ceil(mean * ahead / self.workers))

    def stats(self) -> GateStats:
        with self._cond:
            return GateStats(
                workers=self.workers,
                queue=self.queue,
                running=self._running,
                waiting=len(self._waiting),
                admitted=self._admitted,
                refused=self._refused,
                mean_inference_ms=None if self._mean_s is None else self._mean_s * 1000.0,
            )


def request_threads(workers: int, queue: int) -> int:
    """Threads the HTTP server needs for its synchronous routes: every inference slot and
    waiter holds one, and other requests (health, reads, writes) must still find one free."""
    return workers + queue + 32
