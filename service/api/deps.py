"""Dependencies shared by the routes."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Path, Request

from service.app.catalog import AtlasService
from service.domain.limits import MAX_ROW_ID
from service.runtime import Runtime


def get_runtime(request: Request) -> Runtime:
    runtime: Runtime = request.app.state.runtime
    return runtime


def get_service(runtime: Annotated[Runtime, Depends(get_runtime)]) -> AtlasService:
    return runtime.service  # raises NotReady (503) while loading


RuntimeDep = Annotated[Runtime, Depends(get_runtime)]
ServiceDep = Annotated[AtlasService, Depends(get_service)]

# A larger id in a path is a bad request (422), not a database overflow (500).
RowId = Annotated[int, Path(ge=1, le=MAX_ROW_ID, description="A positive id (at most 2^31 - 1).")]
