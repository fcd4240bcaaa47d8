"""API keys (admin): create (the token is shown once), list, revoke.

A scoped admin works within its atlases: it creates keys only for them (and at most admin),
lists and revokes only keys limited to them (others answer as if they did not exist).
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, status

from service.api.auth import AdminAccess
from service.api.deps import RowId, RuntimeDep
from service.api.schemas import ApiKeyIn, ApiKeyOut, ErrorOut, NewApiKeyOut
from service.auth import Role, create_key, list_keys, revoke_key
from service.errors import NotReady
from service.storage.db import transaction
from service.storage.models import ApiKey

router = APIRouter(tags=["keys"])
ERRORS: dict[int | str, dict[str, Any]] = {
    401: {"model": ErrorOut},
    403: {"model": ErrorOut},
    404: {"model": ErrorOut},
}


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
def create(body: ApiKeyIn, runtime: RuntimeDep, caller: AdminAccess) -> NewApiKeyOut:
    with transaction(_sessions(runtime)) as session:
        new = create_key(
            session, name=body.name, role=Role[body.role], atlases=body.atlases, creator=caller
        )
        return NewApiKeyOut(**key_out(new.key).model_dump(), token=new.token)


@router.get("/keys", response_model=list[ApiKeyOut], responses=ERRORS, summary="List API keys")
def list_all(runtime: RuntimeDep, caller: AdminAccess) -> list[ApiKeyOut]:
    with _sessions(runtime)() as session:
        return [key_out(key) for key in list_keys(session, viewer=caller)]


@router.delete(
    "/keys/{key_id}",
    response_model=ApiKeyOut,
    responses=ERRORS,
    summary="Revoke an API key",
)
def revoke(key_id: RowId, runtime: RuntimeDep, caller: AdminAccess) -> ApiKeyOut:
    with transaction(_sessions(runtime)) as session:
        return key_out(revoke_key(session, key_id=key_id, revoker=caller))
