"""Security headers on every answer: what a browser may do with the API's and the console's
pages (a pure ASGI middleware, so errors and static files get them too).

- ``Content-Security-Policy``: API answers (JSON, images) load and run nothing; the console
  (``/`` and ``/console/*``) runs only its own scripts and styles, shows its own images and
  the thumbnails it fetched (``blob:``) and talks only to its own origin. A page that sets its
  own policy keeps it (``/docs`` and ``/redoc`` allow exactly their inline start-up script,
  see :mod:`service.api.docs`). No page of the service may be framed (``frame-ancestors``,
  and ``X-Frame-Options`` for older browsers): no click-jacking of the console.
- ``X-Content-Type-Options: nosniff``: an upload echoed back is never run as a script.
- ``Referrer-Policy: no-referrer``: URLs (atlas names, ids) never leave in a Referer header.
"""

from __future__ import annotations

from starlette.types import ASGIApp, Message, Receive, Scope, Send

NOTHING = "default-src 'none'; frame-ancestors 'none'; base-uri 'none'; form-action 'none'"
CONSOLE = (
    "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' blob: data:; "
    "connect-src 'self'; object-src 'none'; base-uri 'none'; form-action 'self'; "
    "frame-ancestors 'none'"
)
FIXED = (
    (b"x-content-type-options", b"nosniff"),
    (b"x-frame-options", b"DENY"),
    (b"referrer-policy", b"no-referrer"),
)
CSP = b"content-security-policy"


def policy_for(path: str) -> str:
    """The default Content-Security-Policy of an answer to ``path``."""
    return CONSOLE if path == "/" or path.startswith("/console/") else NOTHING


class SecurityHeaders:
    """ASGI middleware adding the headers above to every HTTP answer that lacks them."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        policy = policy_for(scope["path"]).encode()

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", []))
                present = {name.lower() for name, _ in headers}
                headers += [(k, v) for k, v in (*FIXED, (CSP, policy)) if k not in present]
                message = {**message, "headers": headers}
            await send(message)

        await self.app(scope, receive, send_with_headers)
