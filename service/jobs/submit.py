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

from pydantic import ValidationError
from sqlalchemy.orm import Session, sessionmaker

from service.atlas.model_versions import VersionConfig
from service.errors import InvalidInput, NotReady
from service.jobs.calibration import MIN_FRAMES, calibration_config
from service.ml.training import TrainingConfig
from service.storage import jobs
from service.storage import repository as repo
from service.storage.db import transaction
from service.storage.models import Job, JobStatus

JOB_KINDS = ("retrain", "calibrate")


def check_params(kind: str, params: dict[str, Any]) -> TrainingConfig | None:
    """Refuse parameters the job would refuse (422 before anything is written); a retraining's
    training config, to check against the atlas (None for a calibration)."""
    if kind == "calibrate":
        try:
            calibration_config(params)
        except (TypeError, ValueError) as exc:
            raise InvalidInput(str(exc)) from exc
        return None
    if kind != "retrain":
        raise InvalidInput(f"unknown job kind {kind!r}; choose one of {list(JOB_KINDS)}")
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


def check_atlas_ready(session: Session, atlas_id: int, atlas: str, kind: str) -> None:
    """A retraining needs frames in two submaps; a calibration, enough frames to fit on."""
    if kind == "calibrate":
        frames = repo.count_frames(session, atlas_id=atlas_id)
        if frames < MIN_FRAMES:
            raise InvalidInput(
                f"a calibration needs at least {MIN_FRAMES} frames; atlas '{atlas}' has {frames}"
            )
        return
    populated = repo.count_populated_submaps(session, atlas_id=atlas_id)
    if populated < 2:
        raise InvalidInput(
            f"retraining needs frames in at least two submaps; atlas '{atlas}' has {populated}"
        )


def submit_job(
    sessions: sessionmaker[Session],
    enqueue: Callable[[int], None],
    *,
    atlas: str,
    kind: str,
    params: dict[str, Any],
) -> Job:
    """Validate, create and enqueue a job; returns it as it stands once enqueued."""
    config = check_params(kind, params)
    with transaction(sessions) as session:
        found = repo.get_atlas(session, name=atlas)
        if config is not None:
            check_fits(session, config, atlas_id=found.id)
        check_atlas_ready(session, found.id, atlas, kind)
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
