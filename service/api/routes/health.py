"""Liveness and readiness."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse

from service.api.auth import client_address, presented_token
from service.api.deps import RuntimeDep
from service.api.errors import redact
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
            unavailable_atlases=unavailable,
        )
    if runtime.error:
        detail = "start-up failed (the service log says why)"
        if _shows_a_key(request):
            detail = f"start-up failed: {redact(runtime.error)}"
    elif not runtime.ready:
        detail = "loading models and indexes"
    else:
        detail = "database unreachable"
    body = ReadyOut(ready=False, detail=detail)
    return JSONResponse(body.model_dump(), status_code=503, headers={"Retry-After": "2"})


def _shows_a_key(request: Request) -> bool:
    """Whether the caller may read start-up errors: it shows a valid key, or the API is open."""
    authenticator = getattr(request.app.state, "authenticator", None)
    if authenticator is None:
        return False
    token = presented_token(request.headers.get("authorization"), request.headers.get("x-api-key"))
    return authenticator.identify(token, client_address(request)) is not None
