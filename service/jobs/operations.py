"""Jobs as the API and the CLI use them: submit, list, read, cancel and count, bound to the
process's database and queue so that no caller handles sessions."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from service.jobs import submit
from service.jobs.stats import JobFigures, job_figures
from service.storage.models import Job


class Jobs:
    """The job use cases of one process (:mod:`service.jobs.submit` does the work)."""

    def __init__(self, sessions: sessionmaker[Session], enqueue: Callable[[int], None]) -> None:
        self.sessions = sessions
        self.enqueue = enqueue  # hands a job id to the process's queue

    def submit(self, atlas: str, kind: str, params: dict[str, Any]) -> Job:
        """Check, record and queue a job (one per atlas at a time)."""
        return submit.submit_job(self.sessions, self.enqueue, atlas=atlas, kind=kind, params=params)

    def list(self, atlas: str) -> list[Job]:
        return submit.list_jobs(self.sessions, atlas=atlas)

    def get(self, atlas: str, job_id: int) -> Job:
        return submit.get_job(self.sessions, atlas=atlas, job_id=job_id)

    def cancel(self, atlas: str, job_id: int) -> Job:
        """Cancel a queued job, or ask a running one to stop."""
        return submit.cancel_job(self.sessions, atlas=atlas, job_id=job_id)

    def figures(self, recent: int) -> JobFigures:
        """Counts by kind and state, and the run times of the last ``recent`` finished jobs."""
        return job_figures(self.sessions, recent)
