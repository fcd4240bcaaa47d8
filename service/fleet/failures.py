"""Failed authentications counted per client address, so a key cannot be guessed at speed.

Counted in each process's memory (a sliding window per address; the least recently failing
addresses are forgotten first when too many are remembered): beyond the limit the address gets
429 with ``Retry-After`` until its oldest failure in the window ages out.
"""

from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict, deque

from service.errors import TooManyFailures


class FailureLimiter:
    """Failed authentications per client address in a sliding window; over the limit, 429."""

    MAX_ADDRESSES = 10_000  # addresses remembered at once (the oldest are forgotten first)

    def __init__(self, limit: int, window_s: float) -> None:
        self.limit = limit
        self.window_s = window_s
        self._failures: OrderedDict[str, deque[float]] = OrderedDict()
        self._lock = threading.Lock()

    def _recent(self, address: str, now: float) -> deque[float]:
        times = self._failures.get(address, deque())
        while times and now - times[0] >= self.window_s:
            times.popleft()
        return times

    def check(self, address: str) -> None:
        """Raise :class:`TooManyFailures` while ``address`` is over the limit."""
        now = time.monotonic()
        with self._lock:
            times = self._recent(address, now)
            if len(times) >= self.limit:
                wait = times[len(times) - self.limit] + self.window_s - now
                raise TooManyFailures(
                    "too many failed authentications from this address; retry later",
                    retry_after_s=max(1, math.ceil(wait)),
                )

    def record(self, address: str) -> None:
        now = time.monotonic()
        with self._lock:
            times = self._recent(address, now)
            times.append(now)
            self._failures[address] = times
            self._failures.move_to_end(address)
            while len(self._failures) > self.MAX_ADDRESSES:
                self._failures.popitem(last=False)
