"""API keys (admin): create (the token is shown once), list, revoke.

A scoped admin works within its atlases: it creates keys only for them (and at most admin),
lists and revokes only keys limited to them (others answer as if they did not exist). Keys are
created over HTTP only by a caller showing an admin key: the first one comes from
``loopnet keys create`` on the server, so that nobody who merely reaches an open service (a
web page through a visitor's browser included) can make himself its admin.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from fastapi import APIRouter, status

from service.api.auth import AdminAccess
from service.api.deps import RowId, RuntimeDep
from service.api.schemas import ErrorOut
from service.api.schemas_admin import ApiKeyIn, ApiKeyOut, NewApiKeyOut
from service.errors import Forbidden
from service.fleet.keys import Role

if TYPE_CHECKING:
    from service.storage.models import ApiKey

router = APIRouter(tags=["keys"])
ERRORS: dict[int | str, dict[str, Any]] = {401: {"model": ErrorOut}, 403: {"model": ErrorOut}}
# an unknown atlas (create), a key that does not exist or lies outside the caller's atlases
NOT_FOUND: dict[int | str, dict[str, Any]] = {**ERRORS, 404: {"model": ErrorOut}}


def key_out(key: ApiKey) -> ApiKeyOut:
    return ApiKeyOut(**{f: getattr(key, f) for f in ApiKeyOut.model_fields})


@router.post(
    "/keys",
    response_model=NewApiKeyOut,
    status_code=status.HTTP_201_CREATED,
    responses=NOT_FOUND,
    summary="Create an API key",
    description="Needs an admin key (403 without one, also while the API is open): the first "
    "key is created on the server with `loopnet keys create --role admin --name NAME`.",
)
def create(body: ApiKeyIn, runtime: RuntimeDep, caller: AdminAccess) -> NewApiKeyOut:
    if caller.key_id is None:
        raise Forbidden(
            "keys are created over HTTP only with an admin key; create the first one on the "
            "server: loopnet keys create --role admin --name NAME"
        )
    new = runtime.key_admin.issue(
        name=body.name,
        role=Role[body.role],
        atlases=body.atlases,
        creator=caller,
    )
    return NewApiKeyOut(**key_out(new.key).model_dump(), token=new.token)


@router.get("/keys", response_model=list[ApiKeyOut], responses=ERRORS, summary="List API keys")
def list_all(runtime: RuntimeDep, caller: AdminAccess) -> list[ApiKeyOut]:
    return [key_out(key) for key in runtime.key_admin.listing(viewer=caller)]


@router.delete(
    "/keys/{key_id}",
    response_model=ApiKeyOut,
    responses=NOT_FOUND,
    summary="Revoke an API key",
)
def revoke(key_id: RowId, runtime: RuntimeDep, caller: AdminAccess) -> ApiKeyOut:
    return key_out(runtime.key_admin.revoke(key_id=key_id, revoker=caller))
