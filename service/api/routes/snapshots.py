"""Atlas snapshots over HTTP (admin): download an archive, upload one to restore it."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, File, Query, UploadFile, status
from fastapi.responses import FileResponse
from starlette.background import BackgroundTask

from service.api.auth import AdminAccess, UnscopedAdminAccess
from service.api.deps import RuntimeDep, ServiceDep
from service.api.schemas import AtlasOut, ErrorOut

router = APIRouter(tags=["snapshots"])
ERRORS: dict[int | str, dict[str, Any]] = {
    401: {"model": ErrorOut},
    403: {"model": ErrorOut},
    404: {"model": ErrorOut},
    409: {"model": ErrorOut},
    422: {"model": ErrorOut},
}


@router.get(
    "/atlases/{atlas}/snapshot",
    response_class=FileResponse,
    responses=ERRORS,
    summary="Export the atlas to one archive (download)",
    description="The same archive as `loopnet snapshot export`; restore it with POST /v1/snapshots.",
)
def export(atlas: str, runtime: RuntimeDep, _: AdminAccess) -> FileResponse:
    folder = Path(tempfile.mkdtemp(prefix="loopnet-snapshot-"))
    path = folder / f"{atlas}.loopnet-snapshot.tar"
    try:
        runtime.snapshots.export(atlas, path)
    except Exception:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    return FileResponse(
        path,
        media_type="application/x-tar",
        filename=path.name,
        background=BackgroundTask(shutil.rmtree, folder, ignore_errors=True),
    )


@router.post(
    "/snapshots",
    response_model=AtlasOut,
    status_code=status.HTTP_201_CREATED,
    responses=ERRORS,
    summary="Restore an uploaded snapshot archive as a new atlas",
)
def restore(
    runtime: RuntimeDep,
    service: ServiceDep,
    _: UnscopedAdminAccess,
    archive: Annotated[UploadFile, File(description="An archive from a snapshot export.")],
    name: Annotated[
        str | None, Query(description="The new atlas's name (default: archived)")
    ] = None,
) -> AtlasOut:
    with tempfile.TemporaryDirectory(prefix="loopnet-restore-") as tmp:
        path = Path(tmp) / "snapshot.tar"
        with path.open("wb") as out:
            shutil.copyfileobj(archive.file, out)
        restored = runtime.snapshots.restore(path, name=name)
    return AtlasOut(**service.reads.atlas_summary(restored))
