"""One log line per HTTP request, and its latency in the request histogram.

Each request gets an id: the caller's ``X-Request-ID`` when it is a sane token, else a new
one; the response echoes it in ``X-Request-ID`` so a robot's report can be found in the log.
The line (logger ``loopnet.access``) is a JSON object by default (``LOOPNET_LOG_FORMAT=json``)
with method, route template, path, status, duration, atlas, robot and request id; ``text``
gives the same fields as one plain line of ``key=value`` pairs, where a value that is not a
plain printable token (the decoded path may hold a newline: ``%0A``) is written as a JSON
string, so no request can forge a line or a field.
"""

from __future__ import annotations

import json
import logging
import re
import sys
import time
import uuid
from datetime import UTC, datetime
from typing import Any

from starlette.routing import compile_path
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.fleet.keys import Role
from service.metrics import REQUEST_SECONDS, method_label

log = logging.getLogger("loopnet.access")
REQUEST_ID_HEADER = "X-Request-ID"
_SANE_ID = re.compile(r"^[A-Za-z0-9._:-]{1,128}$")


class _CurrentStderr(logging.StreamHandler):  # type: ignore[type-arg]
    """Writes to whatever ``sys.stderr`` is at the time (test runners swap it)."""

    @property
    def stream(self) -> Any:
        return sys.stderr

    @stream.setter
    def stream(self, _value: Any) -> None:
        pass


def configure_access_log() -> None:
    """Give ``loopnet.access`` its own bare handler: each record is the whole line."""
    if not any(isinstance(h, _CurrentStderr) for h in log.handlers):
        handler = _CurrentStderr()
        handler.setFormatter(logging.Formatter("%(message)s"))
        log.addHandler(handler)
    log.setLevel(logging.INFO)
    log.propagate = False


def route_template(scope: Scope) -> str:
    """The matched route's path template (``/v1/atlases/{atlas}``), never the raw path: keeps
    the metric's labels few."""
    context = scope.get("fastapi", {}).get("effective_route_context")  # with a router's prefix
    path = getattr(context, "path", None) or getattr(scope.get("route"), "path", None)
    if isinstance(path, str):
        return path
    matched = _match_route(scope)
    if matched is not None:
        return matched[0]
    return "/console/{asset}" if scope["path"].startswith("/console/") else "unmatched"


def path_params(scope: Scope) -> dict[str, Any]:
    """The request's path parameters, also when it was answered before routing (the guard's
    401, 413 and 429)."""
    if scope.get("path_params"):
        return dict(scope["path_params"])
    matched = _match_route(scope)
    return matched[1] if matched is not None else {}


def _match_route(scope: Scope) -> tuple[str, dict[str, Any]] | None:
    """Match a request the router never saw against the API's path templates."""
    app = scope.get("app")
    if app is None or not hasattr(app, "openapi"):
        return None
    templates = _TEMPLATES.get(id(app))
    if templates is None:
        templates = [(t, compile_path(t)[0]) for t in app.openapi().get("paths", {})]
        _TEMPLATES[id(app)] = templates
    for template, pattern in templates:
        found = pattern.match(scope["path"])
        if found is not None:
            return template, found.groupdict()
    return None


_TEMPLATES: dict[int, list[tuple[str, re.Pattern[str]]]] = {}


def robot_of(scope: Scope) -> str | None:
    """The robot a request acts as: a robot key's name, else a ``robot``/``robot_id`` query."""
    caller = scope.get("state", {}).get("caller")
    if caller is not None and caller.role is Role.robot and caller.key_id is not None:
        return str(caller.name)
    query = dict(
        part.split("=", 1)
        for part in scope.get("query_string", b"").decode().split("&")
        if "=" in part
    )
    return query.get("robot_id") or query.get("robot")


class RequestLogMiddleware:
    """Pure ASGI middleware (streams and background tasks pass through untouched)."""

    def __init__(self, app: ASGIApp, log_format: str = "json") -> None:
        self.app = app
        self.log_format = log_format
        configure_access_log()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        incoming = dict(scope.get("headers", [])).get(b"x-request-id", b"").decode("latin-1")
        request_id = incoming if _SANE_ID.match(incoming) else uuid.uuid4().hex
        start = time.perf_counter()
        status = 500

        async def send_with_id(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = int(message["status"])
                headers = list(message.get("headers", []))
                headers.append((REQUEST_ID_HEADER.lower().encode(), request_id.encode()))
                message = {**message, "headers": headers}
            await send(message)

        try:
            await self.app(scope, receive, send_with_id)
        finally:
            seconds = time.perf_counter() - start
            route = route_template(scope)
            REQUEST_SECONDS.labels(method_label(scope["method"]), route, str(status)).observe(
                seconds
            )
            self._log(scope, route, status, seconds, request_id)

    def _log(self, scope: Scope, route: str, status: int, seconds: float, request_id: str) -> None:
        fields = {
            "ts": datetime.now(UTC).isoformat(timespec="milliseconds"),
            "method": scope["method"],
            "route": route,
            "path": scope["path"],
            "status": status,
            "duration_ms": round(seconds * 1000.0, 2),
            "atlas": path_params(scope).get("atlas"),
            "robot": robot_of(scope),
            "request_id": request_id,
        }
        if self.log_format == "json":
            log.info(json.dumps(fields))
        else:
            log.info(" ".join(f"{k}={text_value(v)}" for k, v in fields.items() if v is not None))


_PLAIN_TOKEN = re.compile(r"^[!#-<>-~]+$")  # printable ASCII but space, '"' and '='


def text_value(value: object) -> str:
    """A field's value in the text format: as is when it is a plain printable token, else a
    JSON string (control characters, spaces, quotes, '=' and non-ASCII escaped)."""
    text = str(value)
    return text if _PLAIN_TOKEN.match(text) else json.dumps(text)
