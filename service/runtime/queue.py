"""Build the Huey queue for a configuration and register LoopNet's task on it.

The API process enqueues with it; ``loopnet worker`` consumes with it. Both build it from the
same settings, so they agree on the storage (a SQLite file in the data directory, or Redis).
Messages are JSON carrying one job id (:mod:`service.runtime.messages`), never pickles.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from huey import Huey, RedisHuey, SqliteHuey

from service.config import Settings
from service.runtime.messages import JobIdSerializer, RejectedMessage
from service.storage.db import create_private_file, make_private_dir

log = logging.getLogger(__name__)

TASK_NAME = "loopnet.run_job"


class _NoExecutedLines(logging.Filter):
    """Drop Huey's "Executing"/"executed in" lines: the job runner logs each job's id, atlas and
    outcome, and Huey would call a cancelled or skipped job "executed"."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not (
            isinstance(record.msg, str)
            and (record.msg.startswith("Executing ") or " executed in " in record.msg)
        )


_HUEY_LOG_FILTER = _NoExecutedLines()


class Queue:
    """A Huey instance plus LoopNet's one task, ``run_job(job_id)``."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.huey: Huey = make_huey(settings)
        logging.getLogger("huey").addFilter(_HUEY_LOG_FILTER)  # the same filter once only
        self._runner: Any = None
        task = self.huey.task(name=TASK_NAME)(self._run_job)
        self.run_job: Callable[[int], Any] = task
        # the serializer admits only this task, under the name Huey's registry gives it
        self.huey.serializer.task_name = f"{task.task_class.__module__}.{task.task_class.__name__}"

    def _run_job(self, job_id: int) -> None:
        """Executed in the worker: the job runner is built on first use, once per process."""
        if self._runner is None:
            from service.jobs.retraining import JobRunner
            from service.storage.db import make_engine, make_session_factory

            engine = make_engine(self.settings.resolved_database_url)
            self._runner = JobRunner(self.settings, make_session_factory(engine))
        self._runner.run(job_id)

    def enqueue(self, job_id: int) -> None:
        self.run_job(job_id)

    def pending_job_ids(self) -> set[int]:
        """Ids of the jobs waiting in the queue storage (not those a worker has taken)."""
        ids = set()
        for data in self.huey.storage.enqueued_items():
            try:
                task = self.huey.deserialize_task(data)
            except RejectedMessage:
                continue  # logged; the worker drops it when it reaches the head of the queue
            ids.add(int(task.args[0]))
        return ids


def make_huey(settings: Settings) -> Huey:
    serializer = JobIdSerializer(TASK_NAME)  # Queue sets the registered name
    if settings.redis_url:
        return RedisHuey(settings.queue_name, url=settings.redis_url, serializer=serializer)
    make_private_dir(settings.data_dir)
    create_private_file(settings.queue_path)
    return SqliteHuey(settings.queue_name, filename=str(settings.queue_path), serializer=serializer)
