"""Retraining jobs: submit, watch, cancel."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from fastapi import APIRouter, status

from service.api.auth import OperatorAccess
from service.api.deps import RowId, RuntimeDep, ServiceDep
from service.api.schemas import ErrorOut
from service.api.schemas_admin import JobIn, JobOut

if TYPE_CHECKING:
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
    summary="Queue a retraining or calibration job",
    description=(
        "kind 'retrain': few-shot retraining of the atlas's heads from stored features, "
        "activated only when not worse than the active version on the frames it did not train "
        "on. kind 'calibrate': fit the atlas's calibration (also run automatically at frame-count "
        "milestones). Watch it with GET; on success it creates a new model version. One job per "
        "atlas at a time (409 otherwise)."
    ),
)
def submit_job(
    atlas: str, body: JobIn, service: ServiceDep, runtime: RuntimeDep, _: OperatorAccess
) -> JobOut:
    job = runtime.jobs.submit(atlas, body.kind, body.job_params())
    return job_out(atlas, job)


@router.get("/atlases/{atlas}/jobs", response_model=list[JobOut], responses=ERRORS)
def list_jobs(
    atlas: str, service: ServiceDep, runtime: RuntimeDep, _: OperatorAccess
) -> list[JobOut]:
    return [job_out(atlas, job) for job in runtime.jobs.list(atlas)]


@router.get("/atlases/{atlas}/jobs/{job_id}", response_model=JobOut, responses=ERRORS)
def get_job(
    atlas: str, job_id: RowId, service: ServiceDep, runtime: RuntimeDep, _: OperatorAccess
) -> JobOut:
    return job_out(atlas, runtime.jobs.get(atlas, job_id))


@router.post(
    "/atlases/{atlas}/jobs/{job_id}/cancel",
    response_model=JobOut,
    responses=ERRORS,
    summary="Cancel a queued job, or ask a running one to stop",
)
def cancel_job(
    atlas: str, job_id: RowId, service: ServiceDep, runtime: RuntimeDep, _: OperatorAccess
) -> JobOut:
    return job_out(atlas, runtime.jobs.cancel(atlas, job_id))
