"""Build the Huey queue for a configuration and register LoopNet's task on it.

The API process enqueues with it; ``loopnet worker`` consumes with it. Both build it from the
same settings, so they agree on the storage (a SQLite file in the data directory, or Redis).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from huey import Huey, RedisHuey, SqliteHuey

from service.config import Settings

log = logging.getLogger(__name__)

TASK_NAME = "loopnet.run_job"


class Queue:
    """A Huey instance plus LoopNet's one task, ``run_job(job_id)``."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.huey: Huey = make_huey(settings)
        self._runner: Any = None
        self.run_job: Callable[[int], Any] = self.huey.task(name=TASK_NAME)(self._run_job)

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
        return {
            int(task.args[0])
            for task in self.huey.pending()
            if task.name == TASK_NAME and task.args
        }


def make_huey(settings: Settings) -> Huey:
    if settings.redis_url:
        return RedisHuey(settings.queue_name, url=settings.redis_url)
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    return SqliteHuey(settings.queue_name, filename=str(settings.queue_path))
