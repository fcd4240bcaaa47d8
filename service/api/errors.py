"""Domain errors -> HTTP status codes, in one place; every error answer has the documented
shape ``{"detail": str, "error": str}``, FastAPI's and Starlette's own included, and messages
never show server paths."""

from __future__ import annotations

import logging
import re
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException

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
    RequestTimeout,
    RequestTooLarge,
    TooManyFailures,
    Unauthorized,
    UnknownHost,
    WeightsUnavailable,
)

log = logging.getLogger(__name__)

# Starlette's HTTP errors by status, named like the domain errors
HTTP_ERROR_NAMES = {
    400: "BadRequest",
    401: "Unauthorized",
    403: "Forbidden",
    404: "NotFound",
    405: "MethodNotAllowed",
    413: "TooLarge",
    415: "UnsupportedMediaType",
    422: "InvalidInput",
}

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
    (UnknownHost, 400),
    (RequestTimeout, 408),
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

    @app.exception_handler(RequestValidationError)
    async def _invalid_request(_request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = [_plain(error) for error in exc.errors()]
        return JSONResponse(
            {"detail": validation_summary(errors), "error": "InvalidInput", "errors": errors},
            status_code=422,
        )

    @app.exception_handler(HTTPException)
    async def _http_error(_request: Request, exc: HTTPException) -> JSONResponse:
        name = HTTP_ERROR_NAMES.get(exc.status_code, "HTTPError")
        return JSONResponse(
            {"detail": str(exc.detail), "error": name},
            status_code=exc.status_code,
            headers=getattr(exc, "headers", None),
        )

    @app.exception_handler(Exception)
    async def _server_error(request: Request, exc: Exception) -> JSONResponse:
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return JSONResponse(
            {"detail": "internal server error; the server log has the cause", "error": "Internal"},
            status_code=500,
        )


def validation_summary(errors: list[dict[str, Any]]) -> str:
    """FastAPI's list of validation errors in one line: ``body.name: String should ...``."""
    return "; ".join(
        f"{'.'.join(str(part) for part in error.get('loc', ())) or 'request'}: {error.get('msg')}"
        for error in errors
    )


def _plain(error: dict[str, Any]) -> dict[str, Any]:
    """A validation error without its ``ctx``/``url`` (may hold exception objects)."""
    return {key: error[key] for key in ("type", "loc", "msg") if key in error}
