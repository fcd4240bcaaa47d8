"""Submitting, listing and cancelling jobs: the rules the API and the CLI share.

A job is validated (its parameters build a training config whose ``embed_dim`` the atlas's
active heads can fill; the atlas has frames in two submaps), created, then enqueued; when the
queue is unreachable the job is failed at once so nothing waits forever for a worker that will
never see it.
"""

from __future__ import annotations

from typing import Any

from pydantic import ValidationError
from sqlalchemy.orm import Session, sessionmaker

from service.atlas.model_versions import VersionConfig
from service.errors import InvalidInput, NotReady
from service.jobs.queue import Queue
from service.ml.training import TrainingConfig
from service.storage import jobs
from service.storage import repository as repo
from service.storage.db import transaction
from service.storage.models import Job, JobStatus


def check_params(params: dict[str, Any]) -> TrainingConfig:
    """Refuse parameters the training config would refuse (422 before anything is written)."""
    try:
        return TrainingConfig(**params)
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in e['loc']) or 'params'}: {e['msg']}" for e in exc.errors()
        )
        raise InvalidInput(f"invalid job parameters: {problems}") from exc


def check_fits(session: Session, config: TrainingConfig, *, atlas_id: int) -> None:
    """Refuse a config the worker would fail on with the atlas's active heads (422 at submit)."""
    active = repo.active_model_version(session, atlas_id=atlas_id)
    try:
        config.check_fits(VersionConfig.of(active).heads)
    except ValueError as exc:
        raise InvalidInput(str(exc)) from exc


def submit_job(
    sessions: sessionmaker[Session], queue: Queue, *, atlas: str, kind: str, params: dict[str, Any]
) -> Job:
    """Validate, create and enqueue a job; returns it as it stands once enqueued."""
    config = check_params(params)
    with transaction(sessions) as session:
        found = repo.get_atlas(session, name=atlas)
        check_fits(session, config, atlas_id=found.id)
        populated = repo.count_populated_submaps(session, atlas_id=found.id)
        if populated < 2:
            raise InvalidInput(
                f"retraining needs frames in at least two submaps; atlas '{atlas}' has {populated}"
            )
        job = jobs.create_job(session, atlas_id=found.id, kind=kind, params=params)
    try:
        queue.enqueue(job.id)
    except Exception as exc:
        with transaction(sessions) as session:
            jobs.finish_job(
                session,
                job=jobs.get_job(session, job_id=job.id),
                status=JobStatus.FAILED,
                message="could not be queued",
                error=f"{type(exc).__name__}: {exc}",
            )
        raise NotReady(f"the job queue is unavailable: {exc}") from exc
    with sessions() as session:  # a worker may have claimed it already
        return jobs.get_job(session, job_id=job.id)


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
