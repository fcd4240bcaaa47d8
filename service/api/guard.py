"""The request guard: authenticate, then bound the body, before any of it is read.

FastAPI reads (and spools to disk) a whole request body before a route's dependencies run, so
a key check in a dependency comes after the upload. This pure ASGI middleware runs first:

1. every path but the probes and the docs needs a valid key once keys are on: 401 (or 429
   after too many failures from the address) is answered before a byte of the body is read;
2. a declared ``Content-Length`` over the route's limit is answered 413 at once;
3. the body is counted as it arrives, and the moment it passes the limit (chunked uploads
   declare no length) the answer is 413 and the app sees the client as gone;
4. a body whose next part does not arrive within ``LOOPNET_BODY_TIMEOUT_SECONDS`` is
   answered 408 and the app sees the client as gone (a slow sender holds no worker thread
   and no connection for long).

The caller found in step 1 is left in the ASGI scope for the role dependencies
(:mod:`service.api.auth`), which add the role and atlas checks (403).
"""

from __future__ import annotations

from typing import Any

import anyio
import anyio.to_thread
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api.auth import PRINCIPAL_KEY, presented_token
from service.api.errors import error_response
from service.config import Settings
from service.errors import LoopNetError, RequestTimeout, RequestTooLarge
from service.fleet.keys import Authenticator

OPEN_PATHS = frozenset(
    {"/", "/v1/health", "/v1/ready", "/docs", "/docs/oauth2-redirect", "/redoc", "/openapi.json"}
)
OPEN_PREFIXES = ("/console/", "/docs-static/")  # static files: the console asks for a key itself


def is_open(settings: Settings, path: str) -> bool:
    """Paths served without a key: probes, docs, the console's files, public metrics."""
    if path in OPEN_PATHS or path.startswith(OPEN_PREFIXES):
        return True
    return path == "/metrics" and settings.metrics_public


SNAPSHOT_UPLOAD = ("POST", "/v1/snapshots")
FORM_OVERHEAD_BYTES = 1024 * 1024  # multipart boundaries and the small fields beside a file


def body_limit(settings: Settings, method: str, path: str) -> int:
    """The largest body a route accepts: snapshot uploads have their own limit, every other
    route carries at most one upload (an image or a features file) and a few small fields."""
    if (method, path.rstrip("/")) == SNAPSHOT_UPLOAD:
        return settings.max_snapshot_bytes
    return settings.max_upload_bytes + FORM_OVERHEAD_BYTES


class RequestGuard:
    """ASGI middleware: 401/429 before the body, 413 by ``Content-Length`` and while streaming."""

    def __init__(self, app: ASGIApp, settings: Settings) -> None:
        self.app = app
        self.settings = settings

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        path: str = scope["path"]
        authenticator: Authenticator | None = getattr(scope["app"].state, "authenticator", None)
        if authenticator is not None and not is_open(self.settings, path):
            token = presented_token(headers.get("authorization"), headers.get("x-api-key"))
            client = scope["client"][0] if scope.get("client") else None
            try:
                scope[PRINCIPAL_KEY] = await anyio.to_thread.run_sync(
                    authenticator.authenticate, token, client
                )
            except LoopNetError as exc:
                await error_response(exc)(scope, receive, send)
                return
        limit = body_limit(self.settings, scope["method"], path)
        declared = headers.get("content-length", "")
        if declared.isdigit() and int(declared) > limit:
            await error_response(_too_large(limit))(scope, receive, send)
            return
        timeout = self.settings.body_timeout_seconds
        await self.app(scope, *_bounded(receive, send, scope, limit, timeout))


def _too_large(limit: int) -> RequestTooLarge:
    return RequestTooLarge(f"the request body is over this route's limit of {limit} bytes")


def _bounded(
    receive: Receive, send: Send, scope: Scope, limit: int, timeout: float
) -> tuple[Receive, Send]:
    """``receive`` and ``send`` for the app: past ``limit`` bytes received, or no part of an
    unfinished body for ``timeout`` seconds, answer 413 or 408 (unless the app already began
    its answer), tell the app the client left, and drop what it sends."""
    state: dict[str, Any] = {"received": 0, "refused": False, "started": False, "done": False}

    async def refuse(error: LoopNetError) -> Message:
        state["refused"] = True
        if not state["started"]:
            answer = error_response(error)
            answer.headers["Connection"] = "close"  # the rest of the body is never read
            await answer(scope, _no_body, send)
        return {"type": "http.disconnect"}

    async def bounded_receive() -> Message:
        if state["refused"]:
            return {"type": "http.disconnect"}
        if state["done"]:  # after the body, the app waits for a disconnect: no time-out
            return await receive()
        with anyio.move_on_after(timeout) as waited:
            message = await receive()
        if waited.cancelled_caught:
            return await refuse(
                RequestTimeout(f"no part of the request body arrived for {timeout:g} s")
            )
        if message["type"] == "http.request":
            state["received"] += len(message.get("body", b""))
            state["done"] = not message.get("more_body", False)
            if state["received"] > limit:
                return await refuse(_too_large(limit))
        return message

    async def guarded_send(message: Message) -> None:
        if state["refused"]:
            return
        if message["type"] == "http.response.start":
            state["started"] = True
        await send(message)

    return bounded_receive, guarded_send


async def _no_body() -> Message:
    return {"type": "http.disconnect"}
