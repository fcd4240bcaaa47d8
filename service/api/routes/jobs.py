"""Retraining jobs: submit, watch, cancel."""

from __future__ import annotations

from dataclasses import asdict
from typing import TYPE_CHECKING, Any

from fastapi import APIRouter, status

from service.api.auth import OperatorAccess
from service.api.deps import RowId, RuntimeDep, ServiceDep
from service.api.schemas import ErrorOut, JobIn, JobOut
from service.jobs import submit

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
    job = submit.submit_job(
        service.sessions,
        runtime.queue,
        atlas=atlas,
        kind=body.kind,
        params=asdict(body.params),
    )
    return job_out(atlas, job)


@router.get("/atlases/{atlas}/jobs", response_model=list[JobOut], responses=ERRORS)
def list_jobs(atlas: str, service: ServiceDep, _: OperatorAccess) -> list[JobOut]:
    return [job_out(atlas, job) for job in submit.list_jobs(service.sessions, atlas=atlas)]


@router.get("/atlases/{atlas}/jobs/{job_id}", response_model=JobOut, responses=ERRORS)
def get_job(atlas: str, job_id: RowId, service: ServiceDep, _: OperatorAccess) -> JobOut:
    return job_out(atlas, submit.get_job(service.sessions, atlas=atlas, job_id=job_id))


@router.post(
    "/atlases/{atlas}/jobs/{job_id}/cancel",
    response_model=JobOut,
    responses=ERRORS,
    summary="Cancel a queued job, or ask a running one to stop",
)
def cancel_job(atlas: str, job_id: RowId, service: ServiceDep, _: OperatorAccess) -> JobOut:
    return job_out(atlas, submit.cancel_job(service.sessions, atlas=atlas, job_id=job_id))
