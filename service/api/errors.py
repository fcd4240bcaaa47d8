"""Domain errors -> HTTP status codes, in one place; messages never show server paths."""

from __future__ import annotations

import re

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
    RequestTooLarge,
    TooManyFailures,
    Unauthorized,
    WeightsUnavailable,
)

STATUS_OF: list[tuple[type[LoopNetError], int]] = [
    (ImageTooLarge, 413),
    (RequestTooLarge, 413),
    (TooManyFailures, 429),
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
    """Seconds a client should wait before retrying a 503 or 429: the error's own estimate
    (the gate's when saturated, the failure window's when refused), else 5."""
    return error.retry_after_s if isinstance(error, Overloaded | TooManyFailures) else 5


# An absolute path of two or more parts not inside a URL (``http://host/a/b`` stays), and the
# credentials of a URL (``redis://:secret@host``).
_PATH = re.compile(r"(?<![\w:/.~-])(?:/[\w.@+~-]+)+/([\w.@+~-]+)")
_URL_CREDENTIALS = re.compile(r"(\b[a-z][a-z0-9+.-]*://)[^/@\s]*@", re.IGNORECASE)


def redact(message: str) -> str:
    """``message`` without server paths (each becomes its last part) or URL credentials."""
    return _PATH.sub(r"\1", _URL_CREDENTIALS.sub(r"\1***@", message))


def error_response(exc: LoopNetError) -> JSONResponse:
    status = status_of(exc)
    headers = {"Retry-After": str(retry_after_s(exc))} if status in (429, 503) else None
    if status == 401:
        headers = {"WWW-Authenticate": "Bearer"}
    return JSONResponse(
        {"detail": redact(str(exc)), "error": type(exc).__name__},
        status_code=status,
        headers=headers,
    )


def install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(LoopNetError)
    async def _loopnet_error(_request: Request, exc: LoopNetError) -> JSONResponse:
        return error_response(exc)
