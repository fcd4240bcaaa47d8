"""Domain errors -> HTTP status codes, in one place."""

from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse

from service.errors import (
    Conflict,
    Forbidden,
    ImageTooLarge,
    InvalidImage,
    InvalidInput,
    LoopNetError,
    NotFound,
    NotReady,
    Overloaded,
    Unauthorized,
    WeightsUnavailable,
)

STATUS_OF: list[tuple[type[LoopNetError], int]] = [
    (ImageTooLarge, 413),
    (InvalidImage, 422),
    (InvalidInput, 422),
    (NotFound, 404),
    (Unauthorized, 401),
    (Forbidden, 403),
    (Conflict, 409),
    (NotReady, 503),
    (Overloaded, 503),
    (WeightsUnavailable, 503),
]


def status_of(error: LoopNetError) -> int:
    for kind, status in STATUS_OF:
        if isinstance(error, kind):
            return status
    return 500


def retry_after_s(error: LoopNetError) -> int:
    """Seconds a client should wait before retrying a 503: the gate's estimate when saturated."""
    return error.retry_after_s if isinstance(error, Overloaded) else 5


def install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(LoopNetError)
    async def _loopnet_error(_request: Request, exc: LoopNetError) -> JSONResponse:
        status = status_of(exc)
        headers = {"Retry-After": str(retry_after_s(exc))} if status == 503 else None
        if status == 401:
            headers = {"WWW-Authenticate": "Bearer"}
        return JSONResponse(
            {"detail": str(exc), "error": type(exc).__name__}, status_code=status, headers=headers
        )
