"""Retraining jobs: submit, watch, cancel."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, status

from service.api.auth import OperatorAccess
from service.api.deps import RowId, RuntimeDep, ServiceDep
from service.api.schemas import ErrorOut, JobIn, JobOut
from service.errors import InvalidInput, NotReady
from service.ml.heads import HeadsConfig
from service.ml.training import TrainingConfig
from service.storage import jobs
from service.storage import repository as repo
from service.storage.db import transaction
from service.storage.models import Job

router = APIRouter(tags=["jobs"])
ERRORS: dict[int | str, dict[str, Any]] = {404: {"model": ErrorOut}, 409: {"model": ErrorOut}}


def job_out(atlas: str, job: Job) -> JobOut:
    return JobOut(atlas=atlas, **{f: getattr(job, f) for f in JobOut.model_fields if f != "atlas"})


@router.post(
    "/atlases/{atlas}/jobs",
    response_model=JobOut,
    status_code=status.HTTP_202_ACCEPTED,
    responses={**ERRORS, 422: {"model": ErrorOut}, 503: {"model": ErrorOut}},
    summary="Queue a retraining job",
    description=(
        "Few-shot retraining of the atlas's heads from stored features. Watch it with GET; on "
        "success it creates and activates a new model version. One retraining per atlas at a "
        "time (409 otherwise)."
    ),
)
def submit_job(
    atlas: str, body: JobIn, service: ServiceDep, runtime: RuntimeDep, _: OperatorAccess
) -> JobOut:
    params = body.params.model_dump()
    with transaction(service.sessions) as session:
        found = repo.get_atlas(session, name=atlas)
        try:
            config = TrainingConfig(**{**params, "train": tuple(params["train"])})
            active = repo.active_model_version(session, atlas_id=found.id)
            config.check_fits(HeadsConfig(**active.config["heads"]))
        except ValueError as exc:
            raise InvalidInput(str(exc)) from exc
        populated = repo.count_populated_submaps(session, atlas_id=found.id)
        if populated < 2:
            raise InvalidInput(
                f"retraining needs frames in at least two submaps; atlas '{atlas}' has {populated}"
            )
        job = jobs.create_job(session, atlas_id=found.id, kind=body.kind, params=params)
        job_id = job.id
    try:
        runtime.queue.enqueue(job_id)
    except Exception as exc:
        with transaction(service.sessions) as session:
            job = jobs.get_job(session, job_id=job_id)
            jobs.finish_job(
                session,
                job=job,
                status="failed",
                message="could not be queued",
                error=f"{type(exc).__name__}: {exc}",
            )
        raise NotReady(f"the job queue is unavailable: {exc}") from exc
    with service.sessions() as session:
        return job_out(atlas, jobs.get_job(session, job_id=job_id))


@router.get("/atlases/{atlas}/jobs", response_model=list[JobOut], responses=ERRORS)
def list_jobs(atlas: str, service: ServiceDep, _: OperatorAccess) -> list[JobOut]:
    with service.sessions() as session:
        found = repo.get_atlas(session, name=atlas)
        return [job_out(atlas, job) for job in jobs.list_jobs(session, atlas_id=found.id)]


@router.get("/atlases/{atlas}/jobs/{job_id}", response_model=JobOut, responses=ERRORS)
def get_job(atlas: str, job_id: RowId, service: ServiceDep, _: OperatorAccess) -> JobOut:
    with service.sessions() as session:
        found = repo.get_atlas(session, name=atlas)
        return job_out(atlas, jobs.get_job(session, job_id=job_id, atlas_id=found.id))


@router.post(
    "/atlases/{atlas}/jobs/{job_id}/cancel",
    response_model=JobOut,
    responses=ERRORS,
    summary="Cancel a queued job, or ask a running one to stop",
)
def cancel_job(atlas: str, job_id: RowId, service: ServiceDep, _: OperatorAccess) -> JobOut:
    with transaction(service.sessions) as session:
        found = repo.get_atlas(session, name=atlas)
        job = jobs.request_cancel(
            session, job=jobs.get_job(session, job_id=job_id, atlas_id=found.id)
        )
        return job_out(atlas, job)
