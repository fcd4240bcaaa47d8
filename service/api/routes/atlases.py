"""Atlases, their submaps and their model versions."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from fastapi import APIRouter, Response, status

from service.api.auth import AdminAccess, OperatorAccess, RobotAccess, UnscopedAdminAccess
from service.api.deps import RowId, ServiceDep
from service.api.schemas import AtlasIn, AtlasOut, ErrorOut, ModelVersionOut, SubmapIn, SubmapOut
from service.app.model_versions import VersionConfig

if TYPE_CHECKING:
    from service.storage.models import ModelVersion

router = APIRouter(tags=["atlases"])
NOT_FOUND: dict[int | str, dict[str, Any]] = {404: {"model": ErrorOut}}


@router.post(
    "/atlases",
    response_model=AtlasOut,
    status_code=status.HTTP_201_CREATED,
    responses={409: {"model": ErrorOut}},
    summary="Create an atlas",
)
def create_atlas(body: AtlasIn, service: ServiceDep, _: UnscopedAdminAccess) -> AtlasOut:
    service.create_atlas(body.name, body.description)
    return AtlasOut(**service.reads.atlas_summary(body.name))


@router.get("/atlases", response_model=list[AtlasOut], summary="List atlases")
def list_atlases(service: ServiceDep, caller: RobotAccess) -> list[AtlasOut]:
    return [AtlasOut(**s) for s in service.reads.atlas_summaries(caller.may_use)]


@router.get("/atlases/{atlas}", response_model=AtlasOut, responses=NOT_FOUND)
def get_atlas(atlas: str, service: ServiceDep, _: RobotAccess) -> AtlasOut:
    return AtlasOut(**service.reads.atlas_summary(atlas))


@router.delete(
    "/atlases/{atlas}",
    status_code=status.HTTP_204_NO_CONTENT,
    responses=NOT_FOUND,
    summary="Delete an atlas with its submaps, frames, features, models and index",
)
def delete_atlas(atlas: str, service: ServiceDep, _: AdminAccess) -> Response:
    service.delete_atlas(atlas)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@router.post(
    "/atlases/{atlas}/submaps",
    response_model=SubmapOut,
    status_code=status.HTTP_201_CREATED,
    responses={**NOT_FOUND, 409: {"model": ErrorOut}},
    summary="Create a submap",
)
def create_submap(atlas: str, body: SubmapIn, service: ServiceDep, _: RobotAccess) -> SubmapOut:
    submap = service.create_submap(atlas, body.name)
    return SubmapOut(name=submap.name, frames=0, created_at=submap.created_at)


@router.get("/atlases/{atlas}/submaps", response_model=list[SubmapOut], responses=NOT_FOUND)
def list_submaps(atlas: str, service: ServiceDep, _: RobotAccess) -> list[SubmapOut]:
    rows = service.reads.submaps_with_counts(atlas)
    return [SubmapOut(name=s.name, frames=n, created_at=s.created_at) for s, n in rows]


@router.delete(
    "/atlases/{atlas}/submaps/{submap}",
    status_code=status.HTTP_204_NO_CONTENT,
    responses=NOT_FOUND,
    summary="Delete a submap with its frames",
    description="Every API process drops its frames from its index within LOOPNET_SYNC_SECONDS.",
)
def delete_submap(atlas: str, submap: str, service: ServiceDep, _: OperatorAccess) -> Response:
    service.delete_submap(atlas, submap)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


def model_version_out(version: ModelVersion) -> ModelVersionOut:
    return ModelVersionOut(
        version=version.version,
        is_active=version.is_active,
        trained=VersionConfig.of(version).trained,
        config=version.config,
        metrics=version.metrics,
        created_at=version.created_at,
    )


@router.get(
    "/atlases/{atlas}/models",
    response_model=list[ModelVersionOut],
    responses=NOT_FOUND,
    summary="List the atlas's model versions",
)
def list_models(atlas: str, service: ServiceDep, _: OperatorAccess) -> list[ModelVersionOut]:
    return [model_version_out(v) for v in service.reads.model_versions(atlas)]


@router.post(
    "/atlases/{atlas}/models/{version}/activate",
    response_model=ModelVersionOut,
    responses=NOT_FOUND,
    summary="Make a model version the active one (roll back or forward)",
    description="Every API process, this one included, serves it within LOOPNET_SYNC_SECONDS "
    "plus the time to load it.",
)
def activate_model(
    atlas: str, version: RowId, service: ServiceDep, _: OperatorAccess
) -> ModelVersionOut:
    return model_version_out(service.activate_version(atlas, version))
