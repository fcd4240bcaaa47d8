"""The job queue never unpickles: a pickle written into its storage is rejected, not run.

Whoever can write to Redis or to ``queue.sqlite3`` used to get code execution in the worker.
"""

from __future__ import annotations

import pickle
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from huey.consumer import Worker

from service.runtime.messages import RejectedMessage
from service.runtime.queue import Queue
from tests.conftest import make_settings


class CreatesAFile:
    """Unpickling this opens (creates) ``path``: what an attacker's payload would do."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __reduce__(self) -> tuple[Any, ...]:
        return (open, (str(self.path), "w"))


@pytest.fixture(params=["sqlite", "redis"])
def queue(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Queue]:
    overrides: dict[str, object] = {}
    if request.param == "redis":
        env = request.getfixturevalue("redis_queue")
        overrides = {"redis_url": env["LOOPNET_REDIS_URL"], "queue_name": env["LOOPNET_QUEUE_NAME"]}
    queue = Queue(make_settings(tmp_path / "data", **overrides))
    yield queue
    queue.huey.storage.flush_all()


def test_a_pickled_payload_in_the_queue_is_rejected_and_never_runs(
    queue: Queue, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    marker = tmp_path / "created-by-the-payload"
    queue.huey.storage.enqueue(pickle.dumps(CreatesAFile(marker)))
    queue.huey.storage.enqueue(b'{"message": {"name": "os.system", "id": "x"}}')
    queue.enqueue(7)  # a real job behind them

    with caplog.at_level("ERROR"):
        assert queue.pending_job_ids() == {7}
        # the consumer's own loop: it reads (and drops) each message in turn
        worker = Worker(queue.huey, threading.Event(), 0.01, 0.05, 1.0)
        worker.loop()
        worker.loop()
    assert not marker.exists()
    assert caplog.text.count("rejected a queue message that is not a LoopNet job") >= 2
    task = queue.huey.dequeue()
    assert task is not None and task.args == (7,) and task.kwargs == {}
    assert queue.huey.dequeue() is None


def test_only_job_ids_are_queued(queue: Queue) -> None:
    with pytest.raises(RejectedMessage):
        queue.run_job("7; rm -rf /")  # type: ignore[arg-type]
    with pytest.raises(RejectedMessage):
        queue.run_job(2**63)
    assert queue.pending_job_ids() == set()
