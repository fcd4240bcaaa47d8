"""Liveness and readiness."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from service.api.deps import RuntimeDep
from service.api.schemas import HealthOut, ReadyOut
from service.atlas_service import AtlasService
from service.storage import repository as repo

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
        unavailable = unavailable_atlases(service)
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


def unavailable_atlases(service: AtlasService) -> dict[str, str]:
    """Atlas name -> why it cannot be loaded (atlases deleted since are left out)."""
    reasons = service.broken.reasons()
    if not reasons:
        return {}
    with service.sessions() as session:
        names = {a.id: a.name for a in repo.list_atlases(session)}
    return {names[i]: reason for i, reason in reasons.items() if i in names}
