"""API keys (admin): create (the token is shown once), list, revoke."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from fastapi import APIRouter, status

from service.api.auth import AdminAccess
from service.api.deps import RowId, RuntimeDep
from service.api.schemas import ApiKeyIn, ApiKeyOut, ErrorOut, NewApiKeyOut
from service.errors import NotReady
from service.fleet import keys
from service.fleet.keys import Role

if TYPE_CHECKING:
    from service.storage.models import ApiKey

router = APIRouter(tags=["keys"])
ERRORS: dict[int | str, dict[str, Any]] = {401: {"model": ErrorOut}, 403: {"model": ErrorOut}}


def key_out(key: ApiKey) -> ApiKeyOut:
    return ApiKeyOut(**{f: getattr(key, f) for f in ApiKeyOut.model_fields})


def _sessions(runtime: RuntimeDep):  # type: ignore[no-untyped-def]
    if runtime.sessions is None:
        raise NotReady("the service is starting")
    return runtime.sessions


@router.post(
    "/keys",
    response_model=NewApiKeyOut,
    status_code=status.HTTP_201_CREATED,
    responses=ERRORS,
    summary="Create an API key",
)
def create(body: ApiKeyIn, runtime: RuntimeDep, _: AdminAccess) -> NewApiKeyOut:
    new = keys.issue(_sessions(runtime), name=body.name, role=Role[body.role], atlases=body.atlases)
    return NewApiKeyOut(**key_out(new.key).model_dump(), token=new.token)


@router.get("/keys", response_model=list[ApiKeyOut], responses=ERRORS, summary="List API keys")
def list_all(runtime: RuntimeDep, _: AdminAccess) -> list[ApiKeyOut]:
    return [key_out(key) for key in keys.listing(_sessions(runtime))]


@router.delete(
    "/keys/{key_id}",
    response_model=ApiKeyOut,
    responses={**ERRORS, 404: {"model": ErrorOut}},
    summary="Revoke an API key",
)
def revoke(key_id: RowId, runtime: RuntimeDep, _: AdminAccess) -> ApiKeyOut:
    return key_out(keys.revoke(_sessions(runtime), key_id=key_id))
