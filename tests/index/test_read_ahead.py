"""Reading ahead in a thread keeps the order, hands the producer's error to the consumer, and
stops the producer when the consumer stops early."""

from __future__ import annotations

import itertools
import threading
from collections.abc import Iterator

import pytest

from service.index.builder import read_ahead


def test_items_arrive_in_order_at_most_depth_ahead() -> None:
    produced: list[int] = []

    def items() -> Iterator[int]:
        for i in range(20):
            produced.append(i)
            yield i

    seen = []
    for item in read_ahead(items(), 2):
        assert len(produced) - item <= 4  # this one, 2 queued, 1 waiting to be queued
        seen.append(item)
    assert seen == list(range(20))


def test_the_producers_error_reaches_the_consumer_after_the_items_before_it() -> None:
    def items() -> Iterator[int]:
        yield 1
        yield 2
        raise RuntimeError("read failed")

    seen = []
    with pytest.raises(RuntimeError, match="read failed"):
        for item in read_ahead(items(), 2):
            seen.append(item)
    assert seen == [1, 2]


def test_a_consumer_that_stops_stops_the_producer() -> None:
    reader = read_ahead(itertools.count(), 2)
    assert next(reader) == 0
    reader.close()  # what an exception in the consumer's loop does
    assert not any(t.name == "read-ahead" for t in threading.enumerate())
