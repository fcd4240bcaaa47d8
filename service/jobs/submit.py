"""Submitting, listing and cancelling jobs: the rules the API and the CLI share.

A job is validated (a retraining's parameters build a training config whose ``embed_dim`` the
atlas's active heads can fill, and the atlas has frames in two submaps; a calibration's build a
calibration config and the atlas has enough frames), created, then enqueued; when the queue is
unreachable the job is failed at once so nothing waits forever for a worker that will never see
it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from service.errors import NotReady
from service.jobs.kinds import kind_of
from service.storage import jobs
from service.storage import repository as repo
from service.storage.db import transaction
from service.storage.models import Job, JobStatus


def submit_job(
    sessions: sessionmaker[Session],
    enqueue: Callable[[int], None],
    *,
    atlas: str,
    kind: str,
    params: dict[str, Any],
) -> Job:
    """Validate, create and enqueue a job; returns it as it stands once enqueued."""
    job_kind = kind_of(kind)
    config = job_kind.parse(params)  # 422 before anything is written
    with transaction(sessions) as session:
        found = repo.get_atlas(session, name=atlas)
        job_kind.check_ready(session, found.id, atlas, config)
        job = jobs.create_job(session, atlas_id=found.id, kind=kind, params=params)
    enqueue_or_fail(sessions, enqueue, job.id)
    with sessions() as session:  # a worker may have claimed it already
        return jobs.get_job(session, job_id=job.id)


def enqueue_or_fail(
    sessions: sessionmaker[Session], enqueue: Callable[[int], None], job_id: int
) -> None:
    """Hand a created job to the queue; when the queue is unreachable, fail it (NotReady)."""
    try:
        enqueue(job_id)
    except Exception as exc:
        with transaction(sessions) as session:
            jobs.finish_job(
                session,
                job=jobs.get_job(session, job_id=job_id),
                status=JobStatus.FAILED,
                message="could not be queued",
                error=f"{type(exc).__name__}: {exc}",
            )
        raise NotReady(f"the job queue is unavailable: {exc}") from exc


def list_jobs(sessions: sessionmaker[Session], *, atlas: str) -> list[Job]:
    with sessions() as session:
        found = repo.get_atlas(session, name=atlas)
        return jobs.list_jobs(session, atlas_id=found.id)


def get_job(sessions: sessionmaker[Session], *, atlas: str, job_id: int) -> Job:
    with sessions() as session:
        found = repo.get_atlas(session, name=atlas)
        return jobs.get_job(session, job_id=job_id, atlas_id=found.id)


def cancel_job(sessions: sessionmaker[Session], *, atlas: str, job_id: int) -> Job:
    """Cancel a queued job, or ask a running one to stop."""
    with transaction(sessions) as session:
        found = repo.get_atlas(session, name=atlas)
        return jobs.request_cancel(
            session, job=jobs.get_job(session, job_id=job_id, atlas_id=found.id)
        )
