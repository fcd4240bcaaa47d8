"""Liveness and readiness.

Readiness is open (probes carry no key), so it says to callers without a key only how many
atlases are unavailable; their names and errors, and a failed start-up's cause, go to callers
showing a valid key (or to anyone while the API is open).
"""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse

from service.api.auth import key_holder
from service.api.deps import RuntimeDep
from service.api.errors import redact
from service.api.schemas import HealthOut, ReadyOut
from service.fleet.keys import Principal

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
def ready(runtime: RuntimeDep, request: Request) -> ReadyOut | JSONResponse:
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
            unavailable_atlases=_visible(unavailable, key_holder(request)),
        )
    if runtime.error:
        detail = "start-up failed (the service log says why)"
        if key_holder(request) is not None:
            detail = f"start-up failed: {redact(runtime.error)}"
    elif not runtime.ready:
        detail = "loading models and indexes"
    else:
        detail = "database unreachable"
    body = ReadyOut(ready=False, detail=detail)
    return JSONResponse(body.model_dump(), status_code=503, headers={"Retry-After": "2"})


def _visible(unavailable: dict[str, str], viewer: Principal | None) -> dict[str, str]:
    """The unavailable atlases a caller may see: none without a key, its own atlases with one."""
    if viewer is None:
        return {}
    return {name: why for name, why in unavailable.items() if viewer.may_use(name)}
