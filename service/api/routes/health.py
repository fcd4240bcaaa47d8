"""Liveness and readiness."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from service.api.deps import RuntimeDep
from service.api.schemas import HealthOut, ReadyOut

router = APIRouter(tags=["health"])


@router.get("/health", response_model=HealthOut, summary="The process is up")
async def health() -> HealthOut:
    """Answered on the event loop itself, so it stays fast while every worker thread is busy."""
    return HealthOut(status="ok")


@router.get(
    "/ready",
    response_model=ReadyOut,
    responses={503: {"model": ReadyOut}},
    summary="Models loaded, indexes reconciled and the database reachable",
)
def ready(runtime: RuntimeDep) -> ReadyOut | JSONResponse:
    if runtime.ready and runtime.database_reachable():
        service = runtime.service
        preset = service.pipeline.preset
        unavailable = service.unavailable_atlases()
        return ReadyOut(
            ready=True,
            detail=f"ready; {len(unavailable)} atlas(es) unavailable" if unavailable else "ready",
            preset=preset.name,
            backbone=preset.backbone.name,
            local_extractor=preset.local.name,
            unavailable_atlases=unavailable,
        )
    if runtime.error:
        detail = f"start-up failed: {runtime.error}"
    elif not runtime.ready:
        detail = "loading models and indexes"
    else:
        detail = "database unreachable"
    body = ReadyOut(ready=False, detail=detail)
    return JSONResponse(body.model_dump(), status_code=503, headers={"Retry-After": "2"})
